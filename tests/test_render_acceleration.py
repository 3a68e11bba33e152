"""Empty-space skipping and multi-threaded launches change no output: each is held to the reference."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from devices import FAST_DEVICE
from render_helpers import assert_parity, blob_grid, both_backends, inward_rays, random_sparse_grid

from hdrplenoxels.core import parallel
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
from hdrplenoxels.kernels.occupancy_reference import occupancy_reference
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.render import RenderOptions, render_rays
from hdrplenoxels.train.optim import Svox2RMSProp


@pytest.mark.parametrize("block", [1, 2, 4, 8])
def test_occupancy_kernel_equals_reference(block):
    for grid in (random_sparse_grid((11, 9, 7), 1, seed=block), blob_grid()):
        occ = occupancy_for(grid.to(FAST_DEVICE), block)
        cells, blocks = occupancy_reference(grid.links, grid.density, block)
        assert torch.equal(occ.cells.cpu(), cells) and torch.equal(occ.blocks.cpu(), blocks)
    assert 0 < cells.float().mean() < 0.3  # the blob leaves most cells empty: skipping is exercised
    if block <= 4:
        assert 0 < blocks.float().mean() < 0.6


@pytest.mark.parametrize("block", [1, 2, 4])
def test_skipping_empty_blocks_keeps_parity(block):
    grid = blob_grid()
    o, d = inward_rays(400, seed=3)
    out = both_backends(grid, o, d, RenderOptions(), block=block)
    assert_parity(out)
    assert out["torch"][1].abs().max() > 1e-3


def test_occupancy_is_consulted_and_follows_density_updates():
    grid = blob_grid().to(FAST_DEVICE)
    o, d = (t.to(FAST_DEVICE) for t in inward_rays(300, seed=4))
    opt = RenderOptions(background_brightness=0.0)
    right = render_rays(grid, o, d, opt)
    occ = occupancy_for(grid)
    occ.cells.zero_()  # claim every cell is empty (blocks still occupied): the march must see nothing
    assert render_rays(grid, o, d, opt).abs().max() == 0
    occ.cells.fill_(1)
    occ.blocks.zero_()  # the same through the block level
    assert render_rays(grid, o, d, opt).abs().max() == 0
    assert right.abs().max() > 0.1
    with torch.no_grad():
        grid.density.add_(0.0)  # any in-place update bumps the version: the occupancy is rebuilt
    assert torch.allclose(render_rays(grid, o, d, opt), right)


def assert_marks_are_the_rows_with_gradient(grads: GridGradients) -> None:
    """Every row with a gradient is marked as touched (the optimiser visits only marked rows), and
    nearly every marked row got one: a corner a sample reaches with weight exactly 0 (a sample on a
    face of its cell, as at the grid's boundary) is marked with a zero gradient, which costs the
    optimiser a visit and nothing else."""
    has_sh_gradient = (grads.sh != 0).any(-1).any(0)
    has_gradient = has_sh_gradient | (grads.density != 0).any(0)
    marked = grads.touched != 0
    assert has_sh_gradient.any() and not (has_gradient & ~marked).any()
    assert (marked & ~has_gradient).sum() <= 0.01 * marked.sum()


def test_results_do_not_depend_on_the_thread_count(monkeypatch):
    grid = random_sparse_grid((12, 10, 9), 9, seed=5)
    o, d = inward_rays(3000, seed=6)
    weights = torch.randn(3000, 3)
    results = []
    for workers in (1, 2, 3):
        monkeypatch.setattr(march_kernel, "cpu_workers", lambda w=workers: w)
        rgb = march_kernel.render_forward(grid, o, d, RenderOptions())
        grads = GridGradients(grid, parts=workers)
        march_kernel.accumulate_backward(grid, o, d, rgb, weights, RenderOptions(), grads)
        assert_marks_are_the_rows_with_gradient(grads)
        results.append((rgb, *grads.total()))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert (a - b).abs().max() <= 1e-5


def test_split_covers_the_range_once():
    for n, parts in ((0, 2), (10, 4), (1000, 3), (4096, 8)):
        ranges = parallel.split(n, parts)
        covered = [i for a, b in ranges for i in range(a, b)]
        assert covered == list(range(n))
        assert len(ranges) <= parts


def test_fused_density_update_rebuilds_the_occupancy_in_the_same_pass():
    grid = blob_grid().to(FAST_DEVICE)
    occ = occupancy_for(grid, 2)
    before = occ.cells.clone()
    g = torch.Generator().manual_seed(9)
    grads = [torch.randn(2, grid.num_voxels, generator=g), torch.zeros(2, *grid.sh.shape)]
    grads = [t.to(FAST_DEVICE) for t in grads]
    Svox2RMSProp().step_accumulated([grid.density, grid.sh], grads, [3.0, 0.1], fused=True, occupancy=occ)
    cells, blocks = occupancy_reference(grid.links.cpu(), grid.density.cpu(), 2)
    assert not torch.equal(cells, before.cpu())  # the update really moved densities across 0
    assert torch.equal(occ.cells.cpu(), cells) and torch.equal(occ.blocks.cpu(), blocks)
    assert occ.density_stamp.matches(grid.density)  # renders will not rebuild it again


def assert_lane_kernels_equal_the_reference(grid, lanes: int, opt: RenderOptions, seed: int) -> torch.Tensor:
    """Forward and backward of the lane kernels against the reference; returns the lane forward."""
    o, d = inward_rays(300, seed=seed)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(1))
    density, sh = grid.density.clone().requires_grad_(True), grid.sh.clone().requires_grad_(True)
    ref_grid = SparseGrid(grid.links, density, sh, grid.center, grid.radius)
    ref = render_rays(ref_grid, o, d, opt, backend="torch")
    (ref * weights).sum().backward()
    rgb = march_kernel.render_forward(grid, o, d, opt, lanes=lanes)
    grads = GridGradients(grid, parts=1)
    march_kernel.accumulate_backward(grid, o, d, rgb, weights, opt, grads, lanes=lanes)
    pairs = (("rgb", ref, rgb), ("density", density.grad, grads.density[0]), ("sh", sh.grad, grads.sh[0]))
    for name, a, b in pairs:
        assert (a.detach() - b).abs().max() <= 1e-5, name
    assert sh.grad.abs().max() > 1e-3 and density.grad.abs().max() > 1e-3
    assert_marks_are_the_rows_with_gradient(grads)
    return rgb


@pytest.mark.parametrize("lanes", [1, 8, 32])
@pytest.mark.parametrize("basis_dim", [1, 4, 9])
def test_lane_kernels_equal_the_reference_on_cpu_blocks(monkeypatch, lanes, basis_dim):
    """The kernels CUDA runs (a block of lanes per ray, lanes splitting the SH coefficients and
    summing the colour block-wide), run here on CPU blocks as wide as on the GPU."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    grid = blob_grid(basis_dim=basis_dim) if basis_dim == 4 else random_sparse_grid((9, 8, 7), basis_dim, 2)
    assert_lane_kernels_equal_the_reference(grid, lanes, RenderOptions(), seed=basis_dim)


def test_lane_backward_flushes_its_slots_when_rays_stop_early(monkeypatch):
    """Rays that stop on the transmittance threshold leave the march by `break`, with gradients still
    held in their slots; 5 lanes do not divide the 27 SH coefficients, so lanes hold 5 or 6 each."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    grid = random_sparse_grid((9, 8, 7), 9, seed=4, empty_fraction=0.2)
    early = assert_lane_kernels_equal_the_reference(grid, 5, RenderOptions(stop_thresh=0.2), seed=5)
    o, d = inward_rays(300, seed=5)
    full = march_kernel.render_forward(grid, o, d, RenderOptions(), lanes=5)
    assert ((early - full).abs().max(-1).values > 1e-3).sum() > 30  # many rays really stopped early


def test_cuda_forward_marches_a_thread_per_ray_once_the_batch_fills_the_gpu(monkeypatch):
    """A warp per ray for training batches, a thread per ray for a whole view (benchmarks/RESULTS.md,
    "GPU, 2026-11-26"); the CPU always a thread per ray, and lanes asked for are kept. Also what
    `records_samples` tells the trainer."""

    class H100:
        sm_count = 132

    monkeypatch.setattr(march_kernel.wp, "get_device", lambda device: H100)
    fills = march_kernel.THREAD_RAYS_PER_SM * H100.sm_count
    assert march_kernel.lanes_for("cuda:0", None, 5000) == march_kernel.CUDA_LANES
    assert march_kernel.lanes_for("cuda:0", None, fills - 1) == march_kernel.CUDA_LANES
    assert march_kernel.lanes_for("cuda:0", None, fills) == 0
    assert march_kernel.lanes_for("cuda:0", None, 800 * 800) == 0
    assert march_kernel.lanes_for("cuda:0", None) == march_kernel.CUDA_LANES  # a backward: lanes
    assert march_kernel.lanes_for("cuda:0", 8, 800 * 800) == 8
    assert march_kernel.lanes_for("cpu", None, 5000) == 0 and march_kernel.lanes_for("cpu", None, 10**6) == 0
    assert march_kernel.records_samples("cpu") and not march_kernel.records_samples("cuda:0")


def test_a_thread_forward_feeds_the_lane_backward_as_on_a_large_cuda_batch(monkeypatch):
    """On CUDA a batch that fills the GPU is marched forward a thread per ray, while the backward stays a
    warp per ray: that pair gives the reference's gradients too (here on CPU blocks as wide as a warp)."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    grid = random_sparse_grid((9, 8, 7), 9, seed=6)
    o, d = inward_rays(200, seed=7)
    opt = RenderOptions()
    weights = torch.randn(200, 3, generator=torch.Generator().manual_seed(8))
    rgb = march_kernel.render_forward(grid, o, d, opt, lanes=0)
    grads = GridGradients(grid)
    march_kernel.accumulate_backward(grid, o, d, rgb, weights, opt, grads, lanes=32)
    density = grid.density.clone().requires_grad_(True)
    sh = grid.sh.clone().requires_grad_(True)
    ref = render_rays(SparseGrid(grid.links, density, sh, grid.center, grid.radius), o, d, opt, "torch")
    (ref * weights).sum().backward()
    assert (rgb - ref.detach()).abs().max() <= 1e-5
    assert (grads.density[0] - density.grad).abs().max() <= 1e-5 * max(1.0, float(density.grad.abs().max()))
    assert (grads.sh[0] - sh.grad).abs().max() <= 1e-5 * max(1.0, float(sh.grad.abs().max()))


def test_lane_kernels_refuse_per_thread_buffers():
    grid = random_sparse_grid((6, 6, 6), 1, seed=3)
    o, d = inward_rays(10, seed=1)
    rgb, g_rgb, two_parts = torch.zeros(10, 3), torch.ones(10, 3), GridGradients(grid, 2)
    with pytest.raises(ValueError, match="one gradient buffer"):
        march_kernel.accumulate_backward(grid, o, d, rgb, g_rgb, RenderOptions(), two_parts, lanes=32)


def record_run(grid, o, d, weights, opt, capacity: int | None, corrupt: bool = False):
    """(rgb, d density, d SH, the record) of the thread-per-ray kernels with a record of `capacity`
    samples per ray (None: no record); `corrupt` halves the recorded densities and colours before the
    backward."""
    record = None if capacity is None else SampleRecord.empty(len(o), "cpu", capacity)
    rgb = march_kernel.render_forward(grid, o, d, opt, lanes=0, record=record)
    if corrupt:
        record.values.mul_(0.5)
    grads = GridGradients(grid, parts=2)
    march_kernel.accumulate_backward(grid, o, d, rgb, weights, opt, grads, lanes=0, record=record)
    assert_marks_are_the_rows_with_gradient(grads)
    return rgb, *grads.total(), record


@pytest.mark.parametrize("stop_thresh", [1e-7, 0.2])
def test_backward_from_the_sample_record_equals_the_re_march(stop_thresh):
    """The backward replays the samples the forward recorded, then marches on for rays with more
    than the record holds: bit for bit what the re-march gives, which the reference checks."""
    grid = random_sparse_grid((12, 10, 9), 9, seed=8, empty_fraction=0.2)
    o, d = inward_rays(600, seed=9)
    weights = torch.randn(600, 3, generator=torch.Generator().manual_seed(2))
    opt = RenderOptions(stop_thresh=stop_thresh)
    rgb, d_density, d_sh, _ = record_run(grid, o, d, weights, opt, None)
    density, sh = grid.density.clone().requires_grad_(True), grid.sh.clone().requires_grad_(True)
    (
        render_rays(SparseGrid(grid.links, density, sh, grid.center, grid.radius), o, d, opt, "torch")
        * weights
    ).sum().backward()
    assert (d_density - density.grad).abs().max() <= 1e-5 and (d_sh - sh.grad).abs().max() <= 1e-5
    counts = []
    for capacity in (1, 3, 1000):
        *out, record = record_run(grid, o, d, weights, opt, capacity)
        for a, b in zip((rgb, d_density, d_sh), out):
            assert torch.equal(a, b)
        counts.append(record.count)
    assert (counts[1] == 3).any() and (counts[2] > 3).any()  # rays replayed in part and in whole
    assert (counts[2] < 1000).all() and counts[2].sum() > 1000
    if stop_thresh > 1e-3:
        assert (counts[2] < record_run(grid, o, d, weights, RenderOptions(), 1000)[-1].count).sum() > 30


def test_backward_reads_the_recorded_samples():
    """Recorded densities and colours altered before the backward change its gradients: the record
    is really used."""
    grid = random_sparse_grid((10, 9, 8), 4, seed=3, empty_fraction=0.2)
    o, d = inward_rays(300, seed=4)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(3))
    honest = record_run(grid, o, d, weights, RenderOptions(), 1000)
    corrupt = record_run(grid, o, d, weights, RenderOptions(), 1000, corrupt=True)
    assert (honest[1] - corrupt[1]).abs().max() > 1e-3 and (honest[2] - corrupt[2]).abs().max() > 1e-3


def test_sample_record_must_match_the_batch_and_the_kernel():
    grid = random_sparse_grid((6, 6, 6), 1, seed=3)
    o, d = inward_rays(10, seed=1)
    with pytest.raises(ValueError, match="holds 9 rays, the batch 10"):
        march_kernel.render_forward(grid, o, d, RenderOptions(), lanes=0, record=SampleRecord.empty(9, "cpu"))
    with pytest.raises(ValueError, match="lane kernels keep no sample record"):
        march_kernel.render_forward(
            grid, o, d, RenderOptions(), lanes=8, record=SampleRecord.empty(10, "cpu")
        )
    with pytest.raises(ValueError, match="capacity of at least 1"):
        SampleRecord.empty(10, "cpu", 0)
    assert march_kernel.records_samples("cpu") and not march_kernel.records_samples("cuda:0")
