"""The Warp kernel (forward and hand-written backward) equals the PyTorch reference to <= 1e-5."""

from __future__ import annotations

import pytest
import torch
from render_helpers import (
    BACKEND_DEVICES,
    assert_parity,
    both_backends,
    inward_rays,
    random_sparse_grid,
    render_on,
)

from hdrplenoxels.geometry.cameras import NDCSpec, to_ndc
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.march_reference import ray_segments
from hdrplenoxels.render import RenderOptions


@pytest.mark.parametrize("basis_dim", [1, 4, 9])
def test_parity_bbox_rays_on_sparse_grid(basis_dim):
    grid = random_sparse_grid((11, 9, 8), basis_dim, seed=basis_dim)
    o, d = inward_rays(300, seed=1)
    out = both_backends(grid, o, d, RenderOptions())
    assert_parity(out)
    assert out["torch"][1].abs().max() > 1e-3 and out["torch"][2].abs().max() > 1e-3  # gradients really flow


def test_parity_rays_that_miss_return_background_and_no_gradient():
    grid = random_sparse_grid((8, 8, 8), 9, seed=3)
    o, d = inward_rays(64, seed=2)
    o[:32] = torch.tensor([6.0, 6.0, 6.0])
    d[:32] = torch.nn.functional.normalize(torch.tensor([1.0, 0.3, 0.2]), dim=0)  # pointing away
    opt = RenderOptions(background_brightness=0.37)
    seg = ray_segments(grid, o, d, opt)
    assert (seg.num_samples[:32] == 0).all() and (seg.num_samples[32:] > 0).sum() > 24
    out = both_backends(grid, o, d, opt)
    assert_parity(out)
    assert torch.allclose(out["warp"][0][:32], torch.full((32, 3), 0.37))


def test_parity_with_early_termination():
    grid = random_sparse_grid((10, 10, 10), 9, seed=4, empty_fraction=0.1)
    grid.density = grid.density.abs() * 20.0  # opaque: most rays stop early
    o, d = inward_rays(200, seed=5)
    opt = RenderOptions(stop_thresh=1e-3)
    out = both_backends(grid, o, d, opt)
    assert_parity(out)
    # Early-stopped rays add no background, so with a huge background the output stays bounded.
    loud = both_backends(grid, o, d, RenderOptions(stop_thresh=1e-3, background_brightness=1e4))
    stopped = (loud["torch"][0] < 100).all(-1)
    assert stopped.float().mean() > 0.5
    assert_parity(loud)


def test_parity_on_grid_with_empty_cells_and_axis_aligned_rays():
    grid = random_sparse_grid((9, 7, 6), 4, seed=6, empty_fraction=0.7)
    o = torch.tensor([[0.1, -0.2, -3.0], [0.3, 0.1, -3.0], [-3.0, 0.0, 0.0], [0.2, 3.0, 0.1]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert_parity(both_backends(grid, o, d, RenderOptions()))


def test_parity_ndc_rays():
    # A forward-facing rig: cameras near z = 0 looking along +z, rays warped to NDC.
    g = torch.Generator().manual_seed(8)
    n = 256
    origins = torch.randn(n, 3, generator=g) * 0.1
    dirs = torch.nn.functional.normalize(
        torch.cat([torch.randn(n, 2, generator=g) * 0.3, torch.ones(n, 1)], dim=-1), dim=-1
    )
    o_ndc, d_ndc = to_ndc(origins, dirs, NDCSpec(1.6, 2.1, 1.0))
    assert torch.allclose(d_ndc.norm(dim=-1), torch.ones(n))
    assert (o_ndc[:, 2] - -1.0).abs().max() < 1e-5  # the near plane maps to NDC z = -1
    grid = random_sparse_grid((10, 8, 12), 9, seed=9, center=(0.0, 0.0, 0.0))
    grid.radius = (1.5, 1.66, 1.0)
    assert_parity(both_backends(grid, o_ndc, d_ndc, RenderOptions()))


def test_forward_matches_hand_computed_single_voxel_column():
    # 2x2x2 grid, uniform density s and colour c: the ray crosses the box along z.
    s, c = 3.0, 0.2
    grid = SparseGrid.create((2, 2, 2), radius=(1.0, 1.0, 1.0), basis_dim=1, init_sigma=s)
    grid.sh[:] = (c - 0.5) / 0.28209479177387814
    o = torch.tensor([[0.0, 0.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    opt = RenderOptions(background_brightness=0.5, step_size=0.5)
    # Grid box [-0.5, 1.5] in grid units (1 world unit per grid unit): samples at t = 0, 0.5, ..., 2.0.
    n_samples, delta = 5, 0.5
    transmittance = torch.exp(torch.tensor(-s * delta * n_samples))
    expected = c * (1 - transmittance) + 0.5 * transmittance
    for backend, device in BACKEND_DEVICES:
        rgb = render_on(device, grid, o, d, opt, backend)
        assert torch.allclose(rgb, expected.expand(1, 3), atol=1e-6), backend


def test_ndc_rays_that_do_not_point_forward_render_background():
    origins = torch.zeros(3, 3)
    dirs = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.1, 0.995]])
    o_ndc, d_ndc = to_ndc(origins, dirs, NDCSpec(1.6, 2.1, 1.0))
    assert torch.isfinite(o_ndc).all() and torch.isfinite(d_ndc).all()
    grid = random_sparse_grid((8, 8, 8), 1, seed=10, empty_fraction=0.0, center=(0.0, 0.0, 0.0))
    grid.density = grid.density.abs() + 50.0  # everything opaque: only a miss shows the background
    for backend, device in BACKEND_DEVICES:
        rgb = render_on(device, grid, o_ndc, d_ndc, RenderOptions(background_brightness=0.25), backend)
        assert torch.allclose(rgb[:2], torch.full((2, 3), 0.25)), backend
        assert not torch.allclose(rgb[2], torch.full((3,), 0.25)), backend


def test_empty_grid_renders_background_on_both_backends():
    grid = SparseGrid.create((4, 4, 4), basis_dim=1).prune(torch.zeros(64, dtype=torch.bool))
    o, d = inward_rays(5, seed=11)
    for backend, device in BACKEND_DEVICES:
        rgb = render_on(device, grid, o, d, RenderOptions(background_brightness=0.5), backend)
        assert torch.allclose(rgb, torch.full((5, 3), 0.5)), backend
