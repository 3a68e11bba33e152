"""The MSI background through the whole stack: the scene mode that asks for it, training it (both engines,
its own optimiser, exact resume), the model file, every render, and what it gains on a tiny unbounded
scene outside the box (docs/method.md, "Background")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.placement import choose_mode, placement_summary
from hdrplenoxels.data.transforms_json import describe_transforms
from hdrplenoxels.eval.regions import outside_box
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.synth.generate import transforms_json
from hdrplenoxels.synth.procedural import TINY_UNBOUNDED, ProceduralSceneSpec, write_procedural_scene
from hdrplenoxels.synth.scenes import SCENES
from hdrplenoxels.train.config import TrainConfig, apply_overrides
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.optim import StepClock
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer


@pytest.fixture(scope="module")
def unbounded_scene(tmp_path_factory):
    return load_scene(write_procedural_scene(tmp_path_factory.mktemp("unbounded"), TINY_UNBOUNDED))


def small_config(n_iters: int, enabled: bool | None = None) -> TrainConfig:
    """The fast preset shrunk to the tiny scene: one 16^3 grid in the objects' box (the truth's own
    layout; auto would choose a cascade, the cameras being outside it) and an MSI the truth's size."""
    cfg = apply_overrides(
        preset("fast"),
        {
            "device": "cpu",
            "scene_mode": "bbox+background",
            "holdout": "full",  # test views are scored whole, so none of their pixels trains
            "grid.reso_schedule": [(16, 16, 16)],
            "optim.n_iters": n_iters,
            "optim.batch_size": 1024,
            "optim.lr_decay_steps": n_iters,
            "optim.lr_sigma_delay_steps": n_iters // 6,
            "background.layers": 4,
            "background.height": 8,
            "background.width": 16,
            "checkpoint_every": 0,
        },
    )
    cfg.background.enabled = enabled
    return cfg


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10.0 * torch.log10(((a - b) ** 2).mean()))


def test_auto_picks_box_and_background_for_aabb_scale_only(unbounded_scene, tmp_path):
    assert choose_mode(unbounded_scene) == "cascade"  # content beyond the box, cameras outside it
    assert "aabb_scale 4" in placement_summary(unbounded_scene)
    plain = load_scene(
        write_procedural_scene(tmp_path / "plain", ProceduralSceneSpec(grid_reso=8, num_views=2))
    )
    assert choose_mode(plain) == "bbox"
    # The synthetic scenes keep their choice (NDC when forward-facing, else a box) but the open courtyard,
    # whose cameras stand outside its objects' box with content beyond: a cascade reaching them.
    for name, spec in SCENES.items():
        rig = spec.build(4, 8, 6)
        folder = tmp_path / name
        folder.mkdir()
        names = [f"v{i}" for i in range(4)]
        (folder / "images").mkdir()
        for n in names:
            Image.new("RGB", (8, 6)).save(folder / "images" / f"{n}.png")
        (folder / "transforms.json").write_text(json.dumps(transforms_json(rig, [(1.0, 9.0)] * 4, names)))
        scene = load_scene(folder / "transforms.json")
        unbounded = rig.aabb_scale is not None  # courtyard: an open scene that says it reaches beyond
        notes = describe_transforms(folder / "transforms.json").bounds_notes
        assert ("beyond" in notes) == unbounded, name
        expected = "cascade" if unbounded else "ndc" if rig.forward_facing else "bbox"
        assert choose_mode(scene) == expected, name


def test_the_background_model_learns_what_lies_beyond_the_box(unbounded_scene, tmp_path):
    """Same schedule with and without the MSI; scored on the test views (never trained on) where their
    rays miss the box. Without it those pixels are the flat constant; with it they follow the surround.
    Measured (150 steps): 30.3 dB vs 16.6 dB outside the box, 29.7 vs 16.7 dB over all pixels."""
    scores = {}
    for enabled in (None, False):  # None: the scene mode (bbox+background) turns it on
        model = Trainer(unbounded_scene, small_config(150, enabled), tmp_path / str(enabled)).run(
            progress=False
        )
        assert (model.background is not None) == (enabled is None)
        pred, truth, outside = [], [], []
        for i in unbounded_scene.test_ids:
            pred.append(model.render_camera(i).clamp(0.0, 1.0))
            truth.append(torch.as_tensor(np.array(unbounded_scene.images[i])).float() / 255.0)
            outside.append(outside_box(model, i))
        pred, truth, outside = torch.stack(pred), torch.stack(truth), torch.stack(outside)
        assert outside.float().mean() > 0.2
        scores[enabled] = {
            "all": psnr(pred, truth),
            "outside": psnr(pred[outside], truth[outside]),
            "spread": float(pred[outside].std(0).mean() / truth[outside].std(0).mean()),
        }
    with_bg, without = scores[None], scores[False]
    assert with_bg["outside"] > without["outside"] + 6.0, scores
    assert with_bg["all"] > without["all"] + 4.0, scores
    assert without["spread"] < 0.01 and with_bg["spread"] > 0.6, scores  # flat grey vs the surround


def hdr_model(unbounded_scene, tmp_path) -> Model:
    """A one-step background run whose MSI is then made brighter than any LDR value."""
    trainer = Trainer(unbounded_scene, small_config(1), tmp_path / "run")
    model = trainer.run(progress=False)
    model.background.color.mul_(6.0)  # linear HDR: values well above 1
    return model


def test_model_saves_loads_and_renders_its_hdr_background(unbounded_scene, tmp_path):
    model = hdr_model(unbounded_scene, tmp_path)
    model.save(tmp_path / "model.npz")
    loaded = Model.load(tmp_path / "model.npz")
    assert isinstance(loaded.background, MSIBackground) and loaded.geometry.wants_background
    assert torch.equal(loaded.background.density, model.background.density)
    assert torch.equal(loaded.background.color, model.background.color)
    i = unbounded_scene.test_ids[0]
    before, after = model.render_camera(i), loaded.render_camera(i)
    assert torch.equal(before, after)
    outside = outside_box(model, i)
    assert before[outside].max() > 1.5  # no upper bound on the background's radiance
    # The constant background alone renders differently where rays leave the box.
    loaded.background = None
    assert (loaded.render_camera(i)[outside] - before[outside]).abs().max() > 0.5


def test_warp_and_torch_engines_agree_on_a_background_step(unbounded_scene, tmp_path):
    """One training step of each engine on the same batch: the MSI's gradients (data term through the
    foreground's transmittance, TV) and the updated MSI agree. The MSI starts darker than the constant
    and the grid, so that density has a gradient from the first step (at one colour everywhere it has
    none, and RMSProp would scale rounding noise up to a full step)."""
    grads, after = {}, {}
    for backend in ("warp", "torch"):
        cfg = small_config(1)
        cfg.backend = backend
        cfg.background.init_color = 0.2
        trainer = Trainer(unbounded_scene, cfg, tmp_path / backend)
        engine = trainer.engine
        rgb, batch = engine.forward(trainer.pool.sample(512, torch.Generator().manual_seed(0)))
        (grad,) = torch.autograd.grad(torch.mean((rgb - batch.target) ** 2), [rgb])
        engine.backward(grad)
        engine.regularise(torch.Generator().manual_seed(1))
        grads[backend] = [g.clone() for g in engine.background_gradients().total()]
        engine.step(StepClock.at(0, engine.device))
        after[backend] = engine.background
    for warp, ref in zip(grads["warp"], grads["torch"]):
        assert ref.abs().max() > 1e-5
        assert torch.allclose(warp, ref, rtol=1e-3, atol=1e-4 * float(ref.abs().max()))
    start = small_config(1).background
    moved = (after["warp"].density - start.init_sigma).abs()
    assert moved.max() > 1.0  # a first RMSProp step moves by about the learning rate (3)
    clear = grads["torch"][0].abs() > 1e-3 * float(grads["torch"][0].abs().max())  # beyond rounding
    assert torch.allclose(after["warp"].density[clear], after["torch"].density[clear], atol=1e-4)
    assert torch.allclose(after["warp"].color, after["torch"].color, atol=1e-2)


def test_forcing_the_background_on_an_ndc_scene_is_an_error(tmp_path):
    from hdrplenoxels.data.placement import SceneGeometry

    ndc = SceneGeometry("ndc", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4))
    cfg = small_config(1, enabled=True)
    with pytest.raises(ValueError, match="bbox\\+background"):  # TrainConfig.check, as the trainer calls it
        cfg.check(ndc.mode)

    def trains_background(cfg, geometry: SceneGeometry) -> bool:
        settings = cfg.resolved(
            background_brightness=0.5, wants_background=geometry.wants_background, levels=1
        )
        return settings.background.enabled

    assert not trains_background(small_config(1), ndc)
    boxed = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), wants_background=True)
    assert trains_background(small_config(1), boxed) and not trains_background(small_config(1, False), boxed)


def test_background_survives_the_upsample_and_logs_its_rates(unbounded_scene, tmp_path):
    cfg = small_config(6)
    cfg.grid.reso_schedule = [(8, 8, 8), (16, 16, 16)]
    cfg.grid.upsample_every = 3
    cfg.log_every = 3
    trainer = Trainer(unbounded_scene, cfg, tmp_path)
    model = trainer.run(progress=False)
    assert model.grid.reso == (16, 16, 16) and model.background.density.shape == (4, 8, 16)
    log = [json.loads(line) for line in Path(tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert log[-1]["lr_bg_sigma"] < log[0]["lr_bg_sigma"] and "lr_bg_color" in log[-1]


def test_train_command_says_when_the_setting_overrules_the_mode(unbounded_scene, tmp_path, capsys):
    from hdrplenoxels.cli.main import main

    data = str(unbounded_scene.source)
    with pytest.raises(SystemExit) as done:
        main(
            [
                "train",
                data,
                "--out",
                str(tmp_path / "a"),
                "--scene-mode",
                "ndc",
                "--set",
                "background.enabled=true",
            ]
        )
    assert (
        done.value.code == 2
        and "needs a bounding box (--scene-mode bbox+background)" in capsys.readouterr().err
    )
    sets = ["--set", "background.enabled=false", "--set", "optim.n_iters=2", "--set", "checkpoint_every=0"]
    sets += ["--scene-mode", "bbox+background"]
    main(
        ["train", data, "--out", str(tmp_path / "b"), "--preset", "fast", "--quiet", "--device", "cpu", *sets]
    )
    out = capsys.readouterr().out
    assert (
        "scene: bounding box + background (--scene-mode)" in out
        and "background.enabled=false: no background model" in out
    )
    assert Model.load(tmp_path / "b" / "model.npz").background is None
