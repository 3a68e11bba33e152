"""The one place a kernel or its reference is chosen (`kernels/dispatch.py`): by the backend a caller
names, and by the tensor's device, with CUDA's path on a CPU inside `kernels_on_cpu`."""

from __future__ import annotations

import pytest
import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import dispatch
from hdrplenoxels.render import RenderOptions, render_rays


def test_a_backend_names_the_kernels_or_the_references_and_nothing_else():
    assert dispatch.kernels_for("warp") and not dispatch.kernels_for("torch")
    with pytest.raises(ValueError, match="unknown backend 'cuda'"):
        dispatch.kernels_for("cuda")
    grid = SparseGrid.create((4, 4, 4), basis_dim=1)
    o, d = torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="unknown backend"):
        render_rays(grid, o, d, RenderOptions(), backend="cuda")  # type: ignore[arg-type]


def test_a_cpu_tensor_takes_the_reference_unless_cuda_path_is_asked_for():
    t = torch.zeros(3)
    assert not dispatch.use_kernel(t)
    with dispatch.kernels_on_cpu():
        assert dispatch.use_kernel(t)
        with dispatch.kernels_on_cpu(False):
            assert not dispatch.use_kernel(t)
        assert dispatch.use_kernel(t)
    assert not dispatch.use_kernel(t) and not dispatch.KERNELS_ON_CPU
