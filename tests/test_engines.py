"""Every registered engine honours the interface the trainer uses (docs/design.md, "Engine interface")."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from hdrplenoxels.render.fields import render_field
from hdrplenoxels.train.config import NerfSettings
from hdrplenoxels.train.engines import ENGINES, GridHooks, engine_key
from hdrplenoxels.train.field_io import load_field, load_field_with_background, save_field
from hdrplenoxels.train.optim import StepClock
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer


def engine_config(key: str):
    cfg = preset("fast")
    cfg.device = "cpu"
    cfg.grid.reso_schedule = [(12, 12, 12)]
    cfg.optim.n_iters = 10
    cfg.nerf = NerfSettings(
        width=16, depth=2, skip=1, view_width=8, pos_freqs=2, dir_freqs=1, n_coarse=8, n_fine=8
    )
    if key == "nerf":
        cfg.model = "nerf"
    else:
        cfg.backend = key
    assert engine_key(cfg) == key
    return cfg


@pytest.mark.parametrize("key", sorted(ENGINES))
def test_engine_interface(key, tiny_scene, tmp_path):
    trainer = Trainer(tiny_scene, engine_config(key), tmp_path / "run")
    engine = trainer.engine
    assert isinstance(engine, ENGINES[key]) and engine.level == 0
    probe = trainer.pool.sample(32, torch.Generator().manual_seed(1))
    o, d = probe.origins, probe.dirs
    before = engine.render(o, d)
    assert before.shape == (32, 3) and torch.isfinite(before).all() and not before.requires_grad

    batch = trainer.pool.sample(128, torch.Generator().manual_seed(0))
    rgb, rows = engine.forward(batch)
    assert rgb.is_leaf and rgb.requires_grad and rgb.shape[1] == 3
    assert rows.target.shape == rgb.shape and rows.image_ids.shape == rgb.shape[:1]
    assert set(rows.image_ids.tolist()) == set(batch.image_ids.tolist())
    (grad,) = torch.autograd.grad(torch.mean((rgb - rows.target) ** 2), [rgb])
    engine.backward(grad)
    assert isinstance(engine, GridHooks) == (key != "nerf")  # the grid's own hooks, the NeRF without
    if isinstance(engine, GridHooks):
        engine.regularise(torch.Generator().manual_seed(2))
    engine.step(StepClock.at(0, engine.device))
    after = engine.render(o, d)
    assert (after - before).abs().max() > 0  # the step moved the field
    assert all(isinstance(v, (int, float)) for v in engine.log_fields(1).values())

    # Checkpoint state: the field through its file, the optimiser state through restore.
    arrays = engine.state_arrays()
    save_field(tmp_path / "field.npz", engine.field, {"level": engine.level})
    field, meta, _ = load_field(tmp_path / "field.npz")
    opt = trainer.render_opt
    assert torch.equal(
        render_field(field, o, d, opt, "torch"), render_field(engine.field, o, d, opt, "torch")
    )
    engine.restore(field, meta["level"], arrays)
    restored = engine.state_arrays()
    assert restored.keys() == arrays.keys()
    assert all(np.array_equal(restored[k], arrays[k]) for k in arrays)
    assert torch.allclose(engine.render(o, d), after, atol=1e-6)


def test_engine_family_is_config():
    cfg = engine_config("warp")
    assert engine_key(dataclasses.replace(cfg, model="nerf")) == "nerf"
    assert engine_key(dataclasses.replace(cfg, backend="torch")) == "torch"


@pytest.mark.parametrize("key", ["warp", "torch"])
def test_grid_engines_carry_a_background_through_the_interface(key, tiny_scene, tmp_path):
    """The MSI as the interface's second component: stepped with the grid, saved beside it, restored with
    its optimiser state, rendered behind the grid."""
    cfg = engine_config(key)
    cfg.background.enabled = True
    cfg.background.layers, cfg.background.height, cfg.background.width = 3, 4, 8
    trainer = Trainer(tiny_scene, cfg, tmp_path / "run")
    engine = trainer.engine
    bg = engine.background
    assert bg is not None and bg.density.shape == (3, 4, 8)
    before = bg.color.clone()
    for step in range(2):
        rgb, rows = engine.forward(trainer.pool.sample(128, torch.Generator().manual_seed(step)))
        (grad,) = torch.autograd.grad(torch.mean((rgb - rows.target) ** 2), [rgb])
        engine.backward(grad)
        engine.regularise(torch.Generator().manual_seed(2))
        engine.step(StepClock.at(step, engine.device))
    assert (engine.background.color - before).abs().max() > 0  # the MSI trained
    arrays = engine.state_arrays()
    assert any(k.startswith("bg/") for k in arrays)
    save_field(tmp_path / "field.npz", engine.field, {"level": engine.level}, background=engine.background)
    field, background, meta, _ = load_field_with_background(tmp_path / "field.npz")
    probe = trainer.pool.sample(32, torch.Generator().manual_seed(3))
    o, d, opt = probe.origins, probe.dirs, trainer.render_opt
    assert torch.equal(
        render_field(field, o, d, opt, "torch", background=background),
        render_field(engine.field, o, d, opt, "torch", background=engine.background),
    )
    assert not torch.equal(render_field(field, o, d, opt, "torch"), engine.render(o, d))  # it is composited
    rendered = engine.render(o, d)
    engine.restore(field, meta["level"], arrays, background)
    assert all(np.array_equal(engine.state_arrays()[k], arrays[k]) for k in arrays)
    assert torch.allclose(engine.render(o, d), rendered, atol=1e-6)
    with pytest.raises(ValueError, match="has no background model"):
        engine.restore(field, meta["level"], arrays, None)
