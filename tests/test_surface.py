"""The surface prior (docs/method.md, "Surfaces at the sparse points"): the windows around the points, the
prior's gradient against autograd, and training that makes the windows opaque."""

from __future__ import annotations

import numpy as np
import torch
from render_helpers import cascade_grid
from wall_points import with_wall_points

from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.grid.sparse_grid import corner_weights
from hdrplenoxels.train.free_space import SightSegments, line_stretches, observed_lines, sample_levels
from hdrplenoxels.train.surface import surface_grad_


def test_windows_straddle_each_training_views_points():
    points = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]])
    lines = SightLines(points, np.array([0, 1, 1]), np.array([0, 0, 1]))
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, :3, 3] = [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    world_from_data = np.diag([2.0, 2.0, 2.0, 1.0])  # the grid's world is twice the data's scale
    windows = line_stretches(
        observed_lines(lines, c2w, world_from_data, views=[0]), 1.0 - 0.25, 1.0 + 0.1, "cpu"
    )
    assert len(windows) == 1  # view 1's observations are not a training view's
    np.testing.assert_allclose(windows.starts[0], [0.0, 0.0, 2.0 - 0.25 * 3.0])  # the point is (0, 0, 2)
    np.testing.assert_allclose(windows.ends[0], [0.0, 0.0, 2.0 + 0.1 * 3.0])


def _autograd_loss(grid, windows, weight, target, lines, samples, seed):
    """The hinge written with autograd: weight x mean over windows of (target - tau) where tau < target,
    tau's gradient taken as that of sum(sigma 2^-l L/S), so that negative density is pulled up too."""
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(len(windows), (lines,), generator=g)
    u = torch.rand((lines, samples, 1), generator=g)
    s, e = windows.starts[pick], windows.ends[pick]
    pos, level, inside = sample_levels(grid, s[:, None, :] + u * (e - s)[:, None, :])
    density = grid.density.detach().clone().requires_grad_(True)
    rows, cw = corner_weights(grid.links, pos, level)
    values = torch.where(rows >= 0, density[rows.clamp(min=0)], torch.zeros_like(cw))
    sigma = (cw * values).sum(-1) * inside
    length = 0.5 ** level.float() * (e - s).norm(dim=-1)[:, None] / samples
    tau = (sigma.clamp(min=0) * length).sum(-1).detach()
    short = tau < target
    loss = weight * ((target - (sigma * length).sum(-1)) * short).mean()
    loss.backward()
    return weight * (target - tau).clamp(min=0).mean(), density.grad


def test_the_gradient_pulls_short_windows_up_as_autograd_says():
    grid = cascade_grid((8, 8, 8), 1, seed=11, levels=3)
    grid.density.data[::3] = -grid.density.data[::3].abs()  # some negative density, as training leaves
    g = torch.Generator().manual_seed(0)
    starts = torch.randn(40, 3, generator=g) * 3.0  # from every level and from outside them all
    windows = SightSegments(starts, starts + torch.randn(40, 3, generator=g) * 0.5)
    grad = torch.zeros_like(grid.density)
    touched = torch.zeros(grid.num_voxels, dtype=torch.uint8)
    gen = torch.Generator().manual_seed(5)
    loss = surface_grad_(grid, windows, 0.3, 2.0, 64, 8, gen, grad, touched, with_loss=True)
    ref_loss, ref_grad = _autograd_loss(grid, windows, 0.3, 2.0, 64, 8, seed=5)
    torch.testing.assert_close(loss, ref_loss, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-5, atol=1e-7)
    assert (grad <= 0).all() and grad.lt(0).sum() > 20  # only ever up, and the windows reached voxels
    assert grad[grid.density < 0].lt(0).any()  # negative density too
    assert torch.equal(touched.bool(), grad != 0)  # every row with a gradient is marked for the optimiser


def test_opaque_windows_have_no_gradient():
    grid = cascade_grid((8, 8, 8), 1, seed=11, levels=1)
    grid.density.data.fill_(100.0)
    windows = SightSegments(torch.zeros(4, 3), torch.full((4, 3), 0.3))
    grad = torch.zeros_like(grid.density)
    generator = torch.Generator().manual_seed(0)
    loss = surface_grad_(grid, windows, 1.0, 3.0, 16, 8, generator, grad, with_loss=True)
    assert float(loss) == 0.0 and not grad.any()


def test_training_with_the_prior_makes_the_windows_opaque(tmp_path):
    """Points on the walls of the walled scene (truth standing in for SfM points), after a short run:
    with the prior the windows around them fall short of the target by a fraction of what they do
    without, and `train` says it is on."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene
    from hdrplenoxels.train.config import apply_overrides
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import Trainer

    scene = with_wall_points(load_scene(write_procedural_scene(tmp_path / "walled", TINY_WALLED)), 30, 1.0)
    shortfall = {}
    for weight in (0.0, 1.0):
        cfg = {
            "device": "cpu",
            "grid.reso_schedule": [(16, 16, 16)],
            "optim.n_iters": 30,
            "optim.batch_size": 256,
            "optim.lambda_surface": weight,
            "optim.surface_target": 3.0,  # the shortfall below is measured against it
            "optim.free_space_lines": 256,
            "checkpoint_every": 0,
        }
        trainer = Trainer(scene, apply_overrides(preset("fast"), cfg), tmp_path / f"w{weight}")
        assert ("surfaces:" in trainer.sight_priors_note) == (weight > 0)
        model = trainer.run(progress=False)
        c2w, world_from_data = model.cameras.c2w, model.geometry.world_from_data
        windows = line_stretches(
            observed_lines(scene.sight_lines, c2w, world_from_data, scene.train_ids), 0.9, 1.2, "cpu"
        )
        grad = torch.zeros_like(model.grid.density)
        generator = torch.Generator().manual_seed(1)
        loss = surface_grad_(model.grid, windows, 1.0, 3.0, 2048, 32, generator, grad, with_loss=True)
        shortfall[weight] = float(loss)
    assert shortfall[1.0] < 0.5 * shortfall[0.0], shortfall
