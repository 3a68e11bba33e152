"""The march that marks the rows a forward reads (`kernels/march_read_rows.py`) against its oracle: every row
the forward reads with a weight is marked, and nothing off the rays' samples' corners (but row 0); and
against the forward and backward themselves: they read no row it left unmarked."""

import pytest
import torch
from devices import FAST_DEVICE

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.march_kernel import CUDA_LANES, accumulate_backward, mark_read_rows, render_forward
from hdrplenoxels.kernels.march_reference import read_rows_reference
from hdrplenoxels.render import RenderOptions


def _grid(levels: int = 1) -> SparseGrid:
    g = torch.Generator().manual_seed(5)
    grid = SparseGrid.create((24, 20, 16), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 4, 0.1, "cpu", levels)
    density = torch.rand(grid.num_voxels, generator=g) * 40.0
    density[torch.rand(grid.num_voxels, generator=g) < 0.5] = 0.0  # empty space the march skips
    grid.density.data.copy_(density)
    return grid


def _rays(n: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(6)
    origins = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -2.5])
    dirs = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=g) * 0.25 + torch.tensor([0.0, 0.0, 1.0]), dim=-1
    )
    return origins, dirs


def _check(grid: SparseGrid, opt: RenderOptions) -> torch.Tensor:
    origins, dirs = _rays()
    marks = torch.zeros(grid.num_voxels, dtype=torch.uint8, device=FAST_DEVICE)
    mark_read_rows(grid.to(FAST_DEVICE), origins.to(FAST_DEVICE), dirs.to(FAST_DEVICE), opt, marks)
    needed, possible = read_rows_reference(grid, origins, dirs, opt)  # the oracle on the CPU
    marked = marks.bool().cpu()
    assert needed.any()
    assert not (needed & ~marked).any(), "a row the forward reads is not marked"
    possible[0] = True  # an empty corner reads row 0 at weight 0
    assert not (marked & ~possible).any(), "a row off every sample's corners is marked"
    return marked


def test_marks_hold_every_row_the_forward_reads():
    grid, opt = _grid(), RenderOptions(step_size=0.5)
    marked = _check(grid, opt)
    assert marked.sum() < grid.num_voxels  # not every row: the marks follow the rays


def test_marks_stop_behind_opaque_surfaces():
    """Dense enough that rays end inside the grid: the marks stop soon after (fewer than every corner)."""
    grid, opt = _grid(), RenderOptions(step_size=0.5)
    grid.density.data.mul_(50.0)
    _, possible = read_rows_reference(grid, *_rays(), opt)
    assert _check(grid, opt).sum() < possible.sum()


def test_marks_on_a_cascade():
    _check(_grid(levels=2), RenderOptions(step_size=0.5))


POISON = 1e20
"""What an unmarked row's SH are set to: a colour or gradient that reads one is past any scene's."""


@pytest.mark.parametrize("lanes", [0, CUDA_LANES])
@pytest.mark.parametrize("levels", [1, 2])
def test_the_forward_and_backward_read_no_unmarked_row(lanes, levels):
    """The property the owed pull needs, on the device's own kernels (a thread per ray, and CUDA's warp
    of lanes per ray, whose backward re-marches): with every unmarked row's SH set to a huge value (NaN
    would vanish in the colour's clamp), the forward's colours and the backward's gradients stay those
    of a scene; the same value in one row the forward reads shows."""
    grid, opt = _grid(levels).to(FAST_DEVICE), RenderOptions(step_size=0.5)
    grid.sh.data.copy_(torch.rand(grid.sh.shape, generator=torch.Generator().manual_seed(8)).to(FAST_DEVICE))
    origins, dirs = (t.to(FAST_DEVICE) for t in _rays())
    marks = torch.zeros(grid.num_voxels, dtype=torch.uint8, device=FAST_DEVICE)
    mark_read_rows(grid, origins, dirs, opt, marks)
    assert not marks.all()
    grid.sh.data[~marks.bool()] = POISON
    rgb = render_forward(grid, origins, dirs, opt, lanes=lanes)
    assert rgb.abs().max() < 100.0
    grads = GridGradients(grid, 1)
    accumulate_backward(grid, origins, dirs, rgb, torch.ones_like(rgb), opt, grads, lanes=lanes)
    assert grads.touched.any()
    assert grads.density.abs().max() < 1e6 and grads.sh.abs().max() < 1e6
    needed, _ = read_rows_reference(grid.to("cpu"), origins.cpu(), dirs.cpu(), opt)
    grid.sh.data[needed.to(FAST_DEVICE)] = POISON  # the control: the rows the forward reads with a weight
    assert render_forward(grid, origins, dirs, opt, lanes=lanes).abs().max() > 1e6
