"""Sparse grid: transforms, interpolation, resampling with pruning (sigma and weight rules), dilation."""

from __future__ import annotations

import torch
from devices import FAST_DEVICE, on_fast

from hdrplenoxels.grid.sparse_grid import SparseGrid, dilate_mask, resample_axes, resampled_density
from hdrplenoxels.kernels.resample_kernel import resample, trilinear_rows
from hdrplenoxels.kernels.resample_reference import trilinear_rows_reference
from hdrplenoxels.train.pruning import max_weight_score


def test_world_grid_transform_maps_box_to_half_voxel_margins():
    grid = SparseGrid.create((8, 6, 4), center=(1.0, -2.0, 0.5), radius=(2.0, 1.5, 0.5), basis_dim=1)
    lo = torch.tensor([[-1.0, -3.5, 0.0]])
    hi = torch.tensor([[3.0, -0.5, 1.0]])
    assert torch.allclose(grid.world_to_grid(lo), torch.tensor([[-0.5, -0.5, -0.5]]))
    assert torch.allclose(grid.world_to_grid(hi), torch.tensor([[7.5, 5.5, 3.5]]))
    p = torch.randn(10, 3)
    assert torch.allclose(grid.grid_to_world(grid.world_to_grid(p)), p, atol=1e-5)


def test_create_allocates_every_voxel_with_init_density_and_grey_sh():
    grid = SparseGrid.create((3, 4, 5), basis_dim=4, init_sigma=0.1)
    assert grid.num_voxels == 60 and grid.basis_dim == 4 and grid.sh.shape == (60, 12)
    assert (grid.links.flatten() == torch.arange(60, dtype=torch.int32)).all()
    assert torch.allclose(grid.density, torch.full((60,), 0.1)) and (grid.sh == 0).all()


def test_trilinear_hits_voxel_values_and_counts_empty_corners_as_zero():
    grid = SparseGrid.create((4, 4, 4), basis_dim=1)
    grid.density = torch.arange(64, dtype=torch.float32)
    at_voxels = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [3.0, 3.0, 3.0]])
    out = trilinear_rows_reference(grid.links, grid.density[:, None], at_voxels)[:, 0]
    assert torch.allclose(out, torch.tensor([1 * 16 + 2 * 4 + 3, 0, 63], dtype=torch.float32))
    # Remove voxel (1,1,1): the midpoint of the cell (1..2)^3 loses that corner's 1/8 share.
    sparse = grid.prune(torch.arange(64) != 21)
    mid = torch.tensor([[1.5, 1.5, 1.5]])
    full = trilinear_rows_reference(grid.links, grid.density[:, None], mid)
    holed = trilinear_rows_reference(sparse.links, sparse.density[:, None], mid)
    assert torch.allclose(full - holed, torch.tensor([[21.0 / 8]]))


def test_upsampling_reproduces_a_linear_field_and_keeps_everything_above_threshold():
    grid = SparseGrid.create((6, 6, 6), basis_dim=1)
    dense = torch.zeros(6, 6, 6)
    xs = torch.arange(6, dtype=torch.float32)
    dense += 10 + 2 * xs[:, None, None] + 1 * xs[None, :, None] - 0.5 * xs[None, None, :]
    grid.density = dense.flatten()
    grid.sh = torch.stack([dense.flatten()] * 3, dim=-1) * 0.01
    up = resample(grid, (12, 12, 12), thresh=5.0, dilate=0)
    assert up.num_voxels == 12**3
    d_up, sh_up = (a[0] for a in up.to_dense())  # level 0 of the one-box grid
    # New voxel i sits at old coordinate (i + 0.5)/2 - 0.5; interior values are exactly linear.
    c = (torch.arange(12, dtype=torch.float32) + 0.5) / 2 - 0.5
    expect = 10 + 2 * c[:, None, None] + c[None, :, None] - 0.5 * c[None, None, :]
    inner = (slice(1, 11),) * 3
    assert torch.allclose(d_up[inner], expect[inner], atol=1e-4)
    assert torch.allclose(sh_up[inner][..., 0], 0.01 * expect[inner], atol=1e-5)


def test_resampled_density_is_the_trilinear_sample_at_every_new_voxel_centre():
    """The dense interpolation gives what gathering each new voxel's 8 corners gives (the sparse
    grid's own trilinear rule, empty voxels 0, edges clamped), up, down and at uneven ratios."""
    g = torch.Generator().manual_seed(3)
    links = torch.full((5, 6, 7), -1, dtype=torch.int32)
    present = torch.rand(links.shape, generator=g) < 0.6
    links[present] = torch.arange(int(present.sum()), dtype=torch.int32)
    density = torch.rand(int(present.sum()), generator=g) * 50
    for reso in [(10, 12, 14), (9, 11, 13), (3, 4, 5)]:
        axes = resample_axes(tuple(links.shape), reso, "cpu")
        pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
        expect = trilinear_rows_reference(links, density[:, None], pts)[..., 0]
        assert torch.allclose(resampled_density(links, density, reso), expect, atol=1e-4)


def test_sigma_pruning_keeps_dense_voxels_and_dilates_twice():
    grid = SparseGrid.create((9, 9, 9), basis_dim=1, init_sigma=0.0)
    dense = torch.zeros(9, 9, 9)
    dense[4, 4, 4] = 50.0
    grid.density = dense.flatten()
    same = resample(grid, (9, 9, 9), thresh=5.0, dilate=0)
    assert same.num_voxels == 1 and float(same.density[0]) == 50.0
    dilated = resample(grid, (9, 9, 9), thresh=5.0, dilate=2)
    assert dilated.num_voxels == 5**3  # two 26-neighbour dilations of one voxel
    assert int((dilated.links >= 0).sum()) == 125 and dilated.links[0, 2:7, 2:7, 2:7].min() >= 0


def test_max_voxels_cap_raises_the_threshold():
    grid = SparseGrid.create((8, 8, 8), basis_dim=1)
    grid.density = torch.linspace(6, 100, 512)
    kept = resample(grid, (8, 8, 8), thresh=5.0, dilate=0, max_voxels=100)
    assert kept.num_voxels == 100
    assert float(kept.density.min()) >= float(torch.topk(grid.density, 100).values[-1]) - 1e-4


def test_max_voxels_bounds_the_dilated_cascade_not_just_the_voxels_that_pass():
    # Scattered bright voxels in a two-box cascade: two dilations grow each of them up to 125-fold, so a
    # cap counted before the dilation would let the grid past it many times over.
    grid = SparseGrid.create((16, 16, 16), basis_dim=1, levels=2)
    density = torch.zeros_like(grid.density)
    lit = torch.randperm(density.numel(), generator=torch.Generator().manual_seed(3))[:60]
    density[lit] = torch.linspace(10.0, 100.0, 60)
    grid.density = density
    free = resample(grid, (16, 16, 16), thresh=5.0, dilate=2)
    assert free.num_voxels > 2000  # the uncapped grid is well over the cap below
    capped = resample(grid, (16, 16, 16), thresh=5.0, dilate=2, max_voxels=1000)
    assert 875 <= capped.num_voxels <= 1000  # under it by less than one voxel's neighbourhood (ties)
    # The brightest voxel survives the cap, and every voxel kept under the cap is kept without it too.
    assert float(capped.density.max()) == float(free.density.max())
    assert bool(((capped.links >= 0) <= (free.links >= 0)).all())


def test_dilate_mask_grows_by_one_voxel_per_pass():
    m = torch.zeros(7, 7, 7, dtype=torch.bool)
    m[3, 3, 3] = True
    assert int(dilate_mask(m, 1).sum()) == 27 and int(dilate_mask(m, 3).sum()) == 343


def test_dilate_mask_is_the_26_neighbour_max_filter_applied_times_times():
    m = torch.rand((2, 6, 7, 8), generator=torch.Generator().manual_seed(1)) < 0.05
    for times in (0, 1, 2):
        expect = m.float()[:, None]
        for _ in range(times):
            expect = torch.nn.functional.max_pool3d(expect, kernel_size=3, stride=1, padding=1)
        out = dilate_mask(m, times)
        assert out.dtype == torch.bool and torch.equal(out, expect[:, 0] > 0.5)


def test_dilating_a_score_then_cutting_it_is_cutting_then_dilating():
    score = torch.rand((2, 6, 7, 8), generator=torch.Generator().manual_seed(2))
    best = dilate_mask(score, 2)
    expect = torch.nn.functional.max_pool3d(score[:, None], kernel_size=5, stride=1, padding=2)[:, 0]
    assert torch.equal(best, expect)
    for cut in (0.5, 0.9, 0.99):
        assert torch.equal(best >= cut, dilate_mask(score >= cut, 2))


def test_weight_rule_prunes_voxels_hidden_behind_an_opaque_wall():
    grid = SparseGrid.create((16, 16, 16), basis_dim=1, init_sigma=0.0)
    dense = torch.zeros(16, 16, 16)
    dense[:, :, 3] = 500.0  # opaque wall seen from -z
    dense[6:10, 6:10, 10:13] = 50.0  # blob behind the wall
    grid.density = dense.flatten()
    n = 400
    g = torch.Generator().manual_seed(0)
    origins = torch.cat([torch.rand(n, 2, generator=g) * 1.6 - 0.8, torch.full((n, 1), -3.0)], dim=-1)
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3)
    score = max_weight_score(grid, (16, 16, 16), [(origins, dirs)])[0]  # the one level
    assert score[:, :, 2:5].max() > 0.5  # the wall carries the weight
    assert score[6:10, 6:10, 10:13].max() < 1e-6  # nothing behind it is seen
    by_weight = resample(grid, (16, 16, 16), score, thresh=0.256 / 16, dilate=0)
    by_sigma = resample(grid, (16, 16, 16), thresh=5.0, dilate=0)
    assert by_sigma.links[0, 8, 8, 11] >= 0 and by_weight.links[0, 8, 8, 11] < 0
    assert by_weight.links[0, 8, 8, 3] >= 0


def test_trilinear_rows_kernel_matches_the_reference_sample():
    """The Warp sampler of the resample's kept voxels against `trilinear_rows_reference`: points inside, on
    and beyond the edges (clamped), with empty corners counted as 0."""
    g = torch.Generator().manual_seed(2)
    links = torch.full((5, 6, 7), -1, dtype=torch.int32)
    present = torch.rand(links.shape, generator=g) < 0.7
    links[present] = torch.arange(int(present.sum()), dtype=torch.int32)
    data = torch.randn(int(present.sum()), 27, generator=g)
    pts = torch.rand(3000, 3, generator=g) * torch.tensor([6.0, 7.0, 8.0]) - 0.7
    edges = [[0.0, 0.0, 0.0], [4.0, 5.0, 6.0], [3.0, 5.0, 2.5], [-1.0, 9.0, 3.2], [2.5, 2.5, 2.5]]
    pts[:5] = torch.tensor(edges)
    expect = trilinear_rows_reference(links, data, pts)
    fast_links, fast_data, fast_pts = on_fast(links, data, pts)
    got = trilinear_rows(fast_links, fast_data, fast_pts)
    assert got.device.type == FAST_DEVICE.type and torch.allclose(got.cpu(), expect, atol=1e-5)
    assert trilinear_rows(fast_links, fast_data, fast_pts[:0]).shape == (0, 27)
