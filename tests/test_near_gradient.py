"""Gradients scaled near the cameras (`RenderOptions.near_grad`): the Warp backward kernels (thread, lane,
sample-record replay) held to the PyTorch reference, the forward unchanged, and the scale applied."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from render_helpers import assert_parity, both_backends, cascade_grid, cascade_rays

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.march_reference import near_gradient_scale
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.render import RenderOptions, render_rays

NEAR = RenderOptions(near_grad=1.5)  # 1.5 finest half-sides: rays from inside the cascade are scaled


def _reference_grads(grid: SparseGrid, o, d, opt: RenderOptions, weights):
    density, sh = grid.density.clone().requires_grad_(True), grid.sh.clone().requires_grad_(True)
    rgb = render_rays(SparseGrid(grid.links, density, sh, grid.center, grid.radius), o, d, opt, "torch")
    (rgb * weights).sum().backward()
    return rgb.detach(), density.grad, sh.grad


def test_thread_kernels_scale_near_gradients_as_the_reference():
    grid = cascade_grid((10, 9, 8), 9, seed=21)
    o, d = cascade_rays(400, seed=22)
    out = both_backends(grid, o, d, NEAR)
    assert_parity(out)
    plain = both_backends(grid, o, d, RenderOptions())
    assert torch.equal(out["warp"][0], plain["warp"][0])  # the forward is unchanged
    for k in (1, 2):  # the gradients change (each voxel's is a sum of scaled and unscaled samples')
        assert (out["warp"][k] - plain["warp"][k]).abs().max() > 1e-3


def test_the_scale_grows_with_the_square_of_the_distance_up_to_one():
    x = torch.ones(1, 5, 3, requires_grad=True)
    t = torch.tensor([[0.0, 1.0, 2.0, 4.0, 9.0]])
    near_gradient_scale(x, t, 4.0).sum().backward()
    assert torch.allclose(x.grad[0, :, 0], torch.tensor([0.0, 1 / 16, 1 / 4, 1.0, 1.0]))


@pytest.mark.parametrize("lanes", [1, 8, 32])
def test_lane_kernels_scale_near_gradients_as_the_reference(monkeypatch, lanes):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    grid = cascade_grid((9, 8, 7), 9, seed=lanes + 30)
    o, d = cascade_rays(300, seed=lanes + 31)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(3))
    ref = _reference_grads(grid, o, d, NEAR, weights)
    rgb = march_kernel.render_forward(grid, o, d, NEAR, lanes=lanes)
    grads = GridGradients(grid, parts=1)
    march_kernel.accumulate_backward(grid, o, d, rgb, weights, NEAR, grads, lanes=lanes)
    for a, b in zip(ref, (rgb, grads.density[0], grads.sh[0])):
        assert (a - b).abs().max() <= 1e-5


def test_a_sample_record_replays_the_near_scale():
    grid = cascade_grid((10, 9, 8), 4, seed=41, empty_fraction=0.2)
    o, d = cascade_rays(300, seed=42)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(4))
    ref = _reference_grads(grid, o, d, NEAR, weights)
    for capacity in (2, 1000):
        record = SampleRecord.empty(len(o), "cpu", capacity)
        rgb = march_kernel.render_forward(grid, o, d, NEAR, lanes=0, record=record)
        grads = GridGradients(grid, parts=2)
        march_kernel.accumulate_backward(grid, o, d, rgb, weights, NEAR, grads, lanes=0, record=record)
        density, sh = grads.total()
        assert (density - ref[1]).abs().max() <= 1e-5 and (sh - ref[2]).abs().max() <= 1e-5


def test_training_scales_near_gradients_only_when_asked():
    from hdrplenoxels.train.config import apply_overrides
    from hdrplenoxels.train.engines.warp_grid import WarpGridEngine
    from hdrplenoxels.train.presets import preset

    grid = cascade_grid((8, 8, 8), 4, seed=51)
    for near in (0.0, 1.0):
        cfg = apply_overrides(preset("fast"), {"device": "cpu", "optim.near_grad": near})
        cfg = cfg.resolved(background_brightness=0.2, wants_background=False, levels=grid.levels)
        engine = WarpGridEngine(grid, cfg, RenderOptions(background_brightness=0.2))
        assert engine.render_opt.near_grad == near and engine.render_opt.background_brightness == 0.2
