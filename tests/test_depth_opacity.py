"""Depth and opacity for the viewer, from the forward kernel, against the readable reference march."""

from __future__ import annotations

import torch
from render_helpers import blob_grid

from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.kernels.march_reference import (
    composite_weights,
    optical_lengths,
    ray_segments,
    sample_points,
)
from hdrplenoxels.kernels.options import RenderOptions
from hdrplenoxels.render.auxiliary import depth_and_opacity


def reference_depth_opacity(grid, origins, dirs, opt):
    """sum_k w_k |x_k - o| / sum_k w_k and 1 - T from the PyTorch march (samples' own distances)."""
    seg = ray_segments(grid, origins, dirs, opt)
    pos, level, _, valid = sample_points(seg, opt.step_size)
    rows, cw = corner_weights(grid.links, pos, level)
    sigma = (cw * (rows >= 0) * grid.density[rows.clamp(min=0)]).sum(-1)  # missing corners count as 0
    weights, transmittance = composite_weights(sigma, valid, optical_lengths(seg, valid, opt), opt)
    distance = torch.linalg.norm(grid.grid_to_world(pos, level) - origins[:, None], dim=-1)
    opacity = 1.0 - transmittance
    return (weights * distance).sum(1) / opacity.clamp(min=1e-4), opacity


def test_depth_and_opacity_match_the_reference_march():
    """Opacity exactly; depth to within half a voxel on a grid allocated around its surfaces (as pruning
    with dilation leaves a trained grid: a missing corner would read as distance 0.5)."""
    sparse = blob_grid()
    dense_links = torch.arange(sparse.links.numel(), dtype=torch.int32).reshape(sparse.links.shape)
    density = torch.full((sparse.links.numel(),), -1.0)
    present = sparse.links >= 0
    density[dense_links[present].long()] = sparse.density[sparse.links[present].long()]
    grid = SparseGrid(dense_links, density, torch.zeros(density.numel(), 3), sparse.center, sparse.radius)
    eye = torch.tensor([0.1, -0.2, -3.0])
    target = grid.grid_to_world(torch.tensor([[12.0, 7.0, 9.0]]))  # the ball's centre
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(target - eye + 0.25 * torch.randn(400, 3, generator=g), dim=-1)
    origins = eye.expand_as(dirs).contiguous()
    opt = RenderOptions()
    depth, opacity = depth_and_opacity(grid, origins, dirs, opt, eye)
    ref_depth, ref_opacity = reference_depth_opacity(grid, origins, dirs, opt)
    assert torch.allclose(opacity, ref_opacity, atol=1e-5)
    hit = ref_opacity > 0.5
    assert hit.sum() > 50 and (~hit).sum() > 50  # rays through the ball and beside it
    half_voxel = 0.5 * float(torch.linalg.norm(2.0 * torch.tensor(grid.radius) / torch.tensor(grid.reso)))
    assert (depth[hit] - ref_depth[hit]).abs().max() < half_voxel
    assert ref_depth[hit].min() > 2.0  # the ball is 3 units away: depths are distances, not zeros
