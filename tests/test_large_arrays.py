"""Arrays past Warp's 32-bit extents and byte strides (JOURNAL.md, "Large arrays"): the launch
layer refuses what Warp would address wrongly, the gradient parts keep every stride small, and a CPU
backward over a grid of more than 20 M voxels matches the PyTorch oracle."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hdrplenoxels.core.host_memory import available_memory_bytes
from hdrplenoxels.core.warp_runtime import WARP_INDEX_LIMIT, WarpAddressingError, check_addressable, to_warp
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.background_kernel import MSIGradients
from hdrplenoxels.kernels.grad_buffers import GridGradients, part_buffers
from hdrplenoxels.kernels.rmsprop_kernel import fused_grid_rmsprop_touched_
from hdrplenoxels.render import RenderOptions, render_rays
from hdrplenoxels.train.background_tv import msi_tv_grad_
from hdrplenoxels.train.optim import Svox2RMSProp

TESTS = Path(__file__).parent
META = torch.device("meta")  # shapes and strides, no memory


def byte_strides(t: torch.Tensor) -> tuple[int, ...]:
    return tuple(s * t.element_size() for s in t.stride())


def test_the_stacked_parts_of_a_21_m_voxel_grid_are_refused_by_name():
    """The reproduction of JOURNAL.md: two stacked (21 M, 27) parts have a leading stride of
    2 268 000 000 bytes, which Warp would wrap to a negative offset. `torch.empty` reserves the
    address range without touching it, so this needs no 4.5 GB of memory."""
    t = torch.empty((2, 21_000_000, 27))
    with pytest.raises(
        WarpAddressingError, match=r"the SH gradient parts \(2x21000000x27, byte strides \(2268000000"
    ):
        to_warp(t, "the SH gradient parts")
    assert to_warp(t[0], "one part").shape == (21_000_000, 27)  # each part alone is addressable


def test_addressing_limits_apply_to_extents_and_to_strides_that_are_used():
    check_addressable("fits", (2, WARP_INDEX_LIMIT), (WARP_INDEX_LIMIT, 1))
    check_addressable("an axis of one", (1, 10), (2**40, 4))  # a stride never multiplied by a non-zero index
    for shape, strides in (((2, 5), (2**31, 4)), ((2**31,), (1,)), ((3, 2), (-8, 4))):
        with pytest.raises(WarpAddressingError, match="^x "):
            check_addressable("x", shape, strides)


@pytest.mark.parametrize(
    "row_axes,shape", [(1, (600_000_000,)), (1, (21_000_000, 27)), (2, (64, 4096, 4096, 3))]
)
def test_gradient_parts_keep_every_stride_within_warp(row_axes, shape):
    """Interleaved parts: each stride spans at most one row's parts, whatever the grid's size, and the
    optimiser's (parts, rows, columns) view of them is a view, not a copy."""
    parts = part_buffers(4, shape, row_axes, META)
    assert parts.shape == (4, *shape)
    check_addressable("the parts", tuple(parts.shape), byte_strides(parts))
    rows = parts.shape[1] * (parts.shape[2] if row_axes == 2 else 1)
    rows_view = parts.view(4, rows, -1)
    check_addressable("their rows", tuple(rows_view.shape), byte_strides(rows_view))
    stacked = torch.zeros((4, *shape), device=META)
    with pytest.raises(WarpAddressingError):
        check_addressable("stacked", tuple(stacked.shape), byte_strides(stacked))


def test_gradient_parts_are_independent_buffers():
    parts = part_buffers(3, (5, 2), 1, torch.device("cpu"))
    parts[1].add_(1.0)
    assert parts[1].sum() == 10 and parts[0].abs().sum() == 0 and parts[2].abs().sum() == 0


RAYS = 1024  # enough for two parts (`core.parallel.split`)
LARGE_RESO = 272  # 272^3 = 20.1 M voxels: one part of 27 SH columns passes 2^31 bytes
LARGE_GRID_BYTES = 14 * 2**30  # the grid, two gradient parts, the oracle's gradients or the optimiser's state


@pytest.mark.skipif(
    (available_memory_bytes() or 0) < LARGE_GRID_BYTES,
    reason="needs 14 GB of free memory for a 20 M voxel grid",
)
def test_cpu_backward_and_optimiser_over_a_grid_past_20_m_voxels_match_the_oracles():
    """Two gradient parts, half of the rays adding into each. Stacked whole, the optimiser's view of
    them had a 2.2 GB step to part 1, which Warp wrapped: it summed and cleared part 1 ~2 GB below
    the buffer (the heap corruption of JOURNAL.md). Only a small box of the grid is dense."""
    grid = SparseGrid.create((LARGE_RESO,) * 3, basis_dim=9, init_sigma=0.0)
    assert grid.num_voxels > 20_000_000
    g = torch.Generator().manual_seed(3)
    lo, hi = LARGE_RESO - 40, LARGE_RESO - 8
    rows = grid.links[0, lo:hi, lo:hi, lo:hi].reshape(-1).long()
    grid.density[rows] = torch.rand(rows.numel(), generator=g) * 8.0
    grid.sh[rows] = torch.randn(rows.numel(), 27, generator=g) * 0.4
    target = grid.grid_to_world(torch.full((1, 3), (lo + hi) / 2.0), torch.zeros(1, dtype=torch.long))
    origins = target + torch.nn.functional.normalize(torch.randn(RAYS, 3, generator=g), dim=-1) * 2.5
    dirs = torch.nn.functional.normalize(target + 0.05 * torch.randn(RAYS, 3, generator=g) - origins, dim=-1)
    weights = torch.randn(RAYS, 3, generator=g)
    opt = RenderOptions()

    rgb = march_kernel.render_forward(grid, origins, dirs, opt)
    grads = GridGradients(grid, parts=2)
    march_kernel.accumulate_backward(grid, origins, dirs, rgb, weights, opt, grads)
    checked = grads.touched.nonzero().squeeze(1)  # the rows the kernels say they added to
    assert grads.sh[1, checked].abs().max() > 0  # the second part really received gradients

    density = grid.density.requires_grad_(True)
    sh = grid.sh.requires_grad_(True)
    ref = render_rays(
        SparseGrid(grid.links, density, sh, grid.center, grid.radius), origins, dirs, opt, "torch"
    )
    (ref * weights).sum().backward()
    assert (ref.detach() - rgb).abs().max() <= 1e-5
    oracle_rows = ((density.grad != 0) | (sh.grad != 0).any(1)).nonzero().squeeze(1)
    assert oracle_rows.numel() > 1000 and torch.isin(oracle_rows, checked).all()
    assert (density.grad[checked] - grads.density[:, checked].sum(0)).abs().max() <= 1e-5
    assert (sh.grad[checked] - grads.sh[:, checked].sum(0)).abs().max() <= 1e-5
    assert sh.grad[checked].abs().max() > 1e-3
    assert grads.density.count_nonzero() == grads.density[:, checked].count_nonzero()  # nothing elsewhere
    density.grad = sh.grad = None
    density.requires_grad_(False)
    sh.requires_grad_(False)

    # One optimiser step over the touched rows, against the reference step on those rows alone.
    lrs = (3.0, 0.1)
    rows = [t[checked].clone() for t in (grid.density, grid.sh)]
    Svox2RMSProp().step(rows, [grads.density[:, checked].sum(0), grads.sh[:, checked].sum(0)], list(lrs))
    states = (torch.zeros_like(grid.density), torch.zeros_like(grid.sh))
    last_step = torch.zeros(grid.num_voxels, dtype=torch.int32)
    touched = grads.touched.clone()
    fused_grid_rmsprop_touched_(
        (grid.density, grid.sh),
        states,
        (grads.density, grads.sh),
        lrs,
        touched,
        last_step,
        1,
        0.95,
        1e-8,
        -1e9,
    )
    assert torch.allclose(grid.density[checked], rows[0], atol=1e-6)
    assert torch.allclose(grid.sh[checked], rows[1], atol=1e-6)
    assert grads.sh[1, checked].abs().max() == 0 and grads.density.count_nonzero() == 0  # the parts cleared


def test_cpu_kernels_stay_in_bounds_under_warp_debug_checks():
    """Every CPU kernel family, on tiny inputs, with Warp's debug build (each array access checked: an
    out-of-bounds index aborts the process) through `HDRPLENOXELS_WARP_DEBUG`."""
    env = {**os.environ, "HDRPLENOXELS_WARP_DEBUG": "1", "PYTHONPATH": str(TESTS)}
    done = subprocess.run(
        [sys.executable, str(TESTS / "warp_debug_run.py")],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert done.stdout.strip().endswith(
        "in bounds: forward, backward, lanes, record, occupancy, TV, MSI, optimiser, resample, training"
    )


def test_msi_gradient_parts_take_its_sampled_tv_like_one_buffer():
    """The MSI's parts stay contiguous: its sampled TV views each part flat (a view, never a copy)."""
    grid = SparseGrid.create((4, 4, 4), basis_dim=1)
    bg = MSIBackground.create(grid, layers=4, height=8, width=16, density=0.5)
    bg.density = torch.rand(bg.density.shape, generator=torch.Generator().manual_seed(0))
    texels = torch.arange(0, bg.density.numel(), 3)
    parts = MSIGradients(bg, parts=2)
    msi_tv_grad_(bg.density[..., None], parts.density[1][..., None], 0.5, texels)
    alone = torch.zeros_like(bg.density)
    msi_tv_grad_(bg.density[..., None], alone[..., None], 0.5, texels)
    assert (
        alone.abs().max() > 0 and torch.equal(parts.density[1], alone) and parts.density[0].abs().max() == 0
    )
