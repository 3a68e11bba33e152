"""The grid's Cauchy sparsity prior (`train/sparsity.py`): its gradient is its loss's, on the rows the
rays reached and no other, and a grid engine adds it when its weight is on."""

from __future__ import annotations

import pytest
import torch

from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.sparsity import cauchy_sparsity_grad_, cauchy_sparsity_loss
from hdrplenoxels.train.trainer import Trainer


def test_the_gradient_is_the_losss_on_the_rows_the_rays_reached_in_any_part():
    g = torch.Generator().manual_seed(0)
    density = torch.randn(50, generator=g, dtype=torch.float64) * 3.0
    parts = torch.zeros(2, 50, dtype=torch.float64)
    parts[0, :10] = torch.randn(10, generator=g, dtype=torch.float64)
    parts[1, 5:20] = torch.randn(15, generator=g, dtype=torch.float64)  # rows 10-19 in part 1 only
    before = parts.clone()
    cauchy_sparsity_grad_(density, parts, 1e-3)

    seen = torch.zeros(50, dtype=torch.bool)
    seen[:20] = True
    leaf = density.clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(cauchy_sparsity_loss(leaf, seen, 1e-3), [leaf])
    assert torch.allclose(parts[0] - before[0], expected, rtol=1e-12, atol=1e-15)
    assert (expected[:20] != 0).all() and torch.equal(parts[0, 20:], before[0, 20:])
    assert torch.equal(parts[1], before[1])
    # It pulls towards zero from either side.
    assert ((parts[0] - before[0])[:20] * density[:20] > 0).all()


def test_off_adds_nothing():
    density = torch.randn(8)
    parts = torch.ones(1, 8)
    cauchy_sparsity_grad_(density, parts, 0.0)
    assert torch.equal(parts, torch.ones(1, 8))


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_a_grid_engine_adds_the_prior_to_what_its_rays_reached(backend, tiny_scene, tmp_path):
    cfg = preset("fast")
    cfg.device, cfg.backend = "cpu", backend
    cfg.grid.reso_schedule = [(12, 12, 12)]
    cfg.optim.lambda_tv_sigma = cfg.optim.lambda_tv_sh = cfg.optim.lambda_free_space = 0.0
    cfg.optim.lambda_sparsity = 1e-2
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run")
    engine = trainer.engine
    rgb, rows = engine.forward(trainer.pool.sample(128, torch.Generator().manual_seed(0)))
    (grad,) = torch.autograd.grad(torch.mean((rgb - rows.target) ** 2), [rgb])
    engine.backward(grad)
    grads = engine.gradients()
    rays = grads.density.clone()
    engine.regularise(torch.Generator().manual_seed(2))
    seen = (rays != 0).any(dim=0)
    leaf = engine.field.density.detach().clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(cauchy_sparsity_loss(leaf, seen, 1e-2), [leaf])
    assert seen.any() and not seen.all()
    assert torch.allclose(grads.density.sum(0) - rays.sum(0), expected, atol=1e-7)
