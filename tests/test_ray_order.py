"""The locality order of training rays: a permutation that puts rays crossing the same voxels together."""

from __future__ import annotations

import torch
from render_helpers import inward_rays, random_sparse_grid

from hdrplenoxels.render import ray_order


def test_box_crossings_of_axis_rays():
    grid = random_sparse_grid((8, 6, 4), 1, seed=0, center=(0.0, 0.0, 0.0))  # radius (1, 1.2, 0.9)
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 5.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])  # the last one leaves the box
    enter, leave = ray_order.box_crossings(grid, o, d)
    assert torch.allclose(enter[0], torch.tensor([0.0, 0.5, 0.5]), atol=1e-6)
    assert torch.allclose(leave[0], torch.tensor([1.0, 0.5, 0.5]), atol=1e-6)
    assert torch.allclose(enter[1], torch.tensor([0.75, 1.7 / 2.4, 0.5]), atol=1e-6)  # starts inside
    assert torch.allclose(leave[1], torch.tensor([0.75, 0.0, 0.5]), atol=1e-6)
    assert ((enter[2] >= 0) & (enter[2] <= 1)).all() and ((leave[2] >= 0) & (leave[2] <= 1)).all()


def test_locality_order_is_a_permutation_that_brings_neighbours_together():
    grid = random_sparse_grid((16, 16, 16), 1, seed=1)
    o, d = inward_rays(4000, seed=2)
    order = ray_order.locality_order(grid, o, d)
    assert torch.equal(order.sort().values, torch.arange(4000))
    enter, leave = ray_order.box_crossings(grid, o, d)
    ends = torch.cat([enter, leave], -1)

    def mean_step(idx):
        return (ends[idx[1:]] - ends[idx[:-1]]).norm(dim=-1).mean()

    assert mean_step(order) < 0.4 * mean_step(torch.arange(4000))


def test_training_order_leaves_small_grids_alone(monkeypatch):
    grid = random_sparse_grid((8, 8, 8), 9, seed=3)
    o, d = inward_rays(100, seed=4)
    assert ray_order.training_order(grid, o, d) is None  # a few KB of SH rows: cached anyway
    monkeypatch.setattr(ray_order, "CACHED_GRID_BYTES", 0)
    assert torch.equal(ray_order.training_order(grid, o, d), ray_order.locality_order(grid, o, d))
