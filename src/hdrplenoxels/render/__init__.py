"""One render API over two backends: the Warp kernel (fast, CPU and CUDA) and the PyTorch reference."""

from __future__ import annotations

from typing import Literal

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render.options import RenderOptions

Backend = Literal["warp", "torch"]
BACKENDS: tuple[str, ...] = ("warp", "torch")


def render_rays(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    backend: Backend = "warp",
) -> torch.Tensor:
    """Linear radiance (N, 3) of rays with unit directions, differentiable w.r.t. density and SH."""
    if backend == "warp":
        from hdrplenoxels.render.autograd import render_warp

        return render_warp(grid, origins, dirs, opt)
    if backend == "torch":
        from hdrplenoxels.render.reference import render_reference

        return render_reference(grid, origins, dirs, opt)
    raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")


__all__ = ["BACKENDS", "Backend", "RenderOptions", "render_rays"]
