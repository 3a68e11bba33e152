"""The NeRF engine: its sampler, gradients through the tone-mapping module, NeRF-A's appearance blends,
saving and resuming, the CLI, and tone mapping after it on a varying-exposure scene."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from test_train import TINY

from hdrplenoxels.cli.main import main
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.eval.evaluate import evaluate
from hdrplenoxels.render.nerf import (
    Appearance,
    NerfField,
    box_near_far,
    composite,
    importance,
    stratified,
)
from hdrplenoxels.train.config import NerfSettings, TrainConfig
from hdrplenoxels.train.field_io import load_field
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR
from hdrplenoxels.train.run_state import load_run_state
from hdrplenoxels.train.trainer import Trainer

SMALL = NerfSettings(
    width=32,
    depth=2,
    skip=1,
    view_width=16,
    pos_freqs=4,
    dir_freqs=1,
    n_coarse=12,
    n_fine=12,
    lr=1e-2,
    lr_final=1e-3,
    lr_decay_steps=150,
)


def nerf_config(n_iters: int, **nerf) -> TrainConfig:
    cfg = preset("fast")
    cfg.model = "nerf"
    cfg.nerf = dataclasses.replace(SMALL, **nerf)
    cfg.optim.n_iters = n_iters
    cfg.optim.batch_size = 256
    cfg.device = "cpu"
    cfg.log_every = 5
    cfg.checkpoint_every = 0
    return cfg


def _rays(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -3.0])
    dirs = torch.randn(n, 3, generator=g) * 0.15 + torch.tensor([0.0, 0.0, 1.0])
    return origins, dirs / dirs.norm(dim=-1, keepdim=True)


def test_box_near_far_is_where_rays_cross_the_box():
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    near, far = box_near_far(origins, dirs, torch.zeros(3), torch.tensor([1.0, 1.0, 0.5]))
    assert torch.allclose(near[0], torch.tensor(2.5)) and torch.allclose(far[0], torch.tensor(3.5))
    assert near[1] == far[1]  # a miss: nothing to sample


@pytest.mark.parametrize("jitter", [False, True])
def test_coarse_and_fine_samples_are_increasing_and_within_near_far(jitter):
    g = torch.Generator().manual_seed(1) if jitter else None
    near, far = torch.tensor([1.0, 2.0, 0.5]), torch.tensor([3.0, 2.5, 4.0])
    t = stratified(near, far, 16, g)
    assert t.shape == (3, 16) and (t[:, 1:] > t[:, :-1]).all()
    assert (t >= near[:, None]).all() and (t <= far[:, None]).all()
    # Fine samples follow the coarse weights: all of the weight on one bin draws them into it.
    weights = torch.zeros(3, 16)
    weights[:, 7] = 1.0
    fine = importance(t, weights, 32, g)
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    assert (fine >= mids[:, 6:7] - 1e-6).all() and (fine <= mids[:, 7:8] + 1e-6).all()
    merged, _ = torch.sort(torch.cat([t, importance(t, torch.rand(3, 16), 32, g)], -1), -1)
    assert (merged[:, 1:] >= merged[:, :-1]).all()
    assert (merged >= near[:, None]).all() and (merged <= far[:, None]).all()


def test_radiance_is_linear_with_no_upper_bound():
    """Composite of one opaque sample shows its colour however bright; an empty ray the background."""
    t = torch.tensor([[1.0, 2.0], [1.0, 2.0]])
    sigma = torch.tensor([[1e4, 0.0], [0.0, 0.0]])
    rgb = torch.full((2, 2, 3), 7.5)
    colour, weights = composite(sigma, rgb, t, torch.tensor([3.0, 3.0]), 0.25)
    assert torch.allclose(colour[0], torch.tensor(7.5)) and torch.allclose(colour[1], torch.tensor(0.25))
    assert torch.allclose(weights.sum(1), torch.tensor([1.0, 0.0]))


def test_gradients_reach_both_networks_the_codes_and_the_tone_module(tiny_scene, tmp_path):
    cfg = nerf_config(1, appearance=True)
    cfg.tonemap.enabled = True
    trainer = Trainer(tiny_scene, cfg, tmp_path)
    batch = trainer.pool.sample(64, torch.Generator().manual_seed(0))
    rgb, rows = trainer.engine.forward(batch)
    assert rgb.shape == (128, 3) and rgb.requires_grad and rgb.is_leaf  # coarse and fine rows
    assert torch.equal(rows.image_ids, batch.image_ids.repeat(2))
    pred = trainer.tonemapper(rgb, rows.image_ids, rows.rows, rows.cols, training=True)
    tone = trainer.tone_optimiser.params
    grad_rgb, *grad_tone = torch.autograd.grad(trainer.tonemapper.loss(pred, rows.target), [rgb, *tone])
    trainer.engine.backward(grad_rgb)
    field = trainer.engine.field
    for net in (field.coarse, field.fine):
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    used = batch.image_ids.unique()
    assert (field.codes.weight.grad[used].abs().sum(1) > 0).all()
    assert any(g.abs().sum() > 0 for g in grad_tone)


def test_appearance_blend_of_weight_0_or_1_is_the_endpoint(tiny_scene):
    torch.manual_seed(0)
    field = NerfField(dataclasses.replace(SMALL, appearance=True), (0, 0, 0), (1, 1, 1), 4)
    torch.nn.init.normal_(field.codes.weight, std=1.0)
    o, d = _rays(50)
    first, second = field.render(o, d, 0.5, Appearance(1)), field.render(o, d, 0.5, Appearance(3))
    assert torch.equal(field.render(o, d, 0.5, Appearance(1, 3, 0.0)), first)
    assert torch.allclose(field.render(o, d, 0.5, Appearance(1, 3, 1.0)), second, atol=1e-6)
    half = field.render(o, d, 0.5, Appearance(1, 3, 0.5))
    assert (half - first).abs().max() > 1e-4 and (half - second).abs().max() > 1e-4
    with pytest.raises(ValueError, match="images 0..3"):
        field.render(o, d, 0.5, Appearance(4))


def test_appearance_of_a_group_is_the_mean_of_its_codes():
    field = NerfField(dataclasses.replace(SMALL, appearance=True), (0, 0, 0), (1, 1, 1), 4)
    torch.nn.init.normal_(field.codes.weight, std=1.0)
    codes = field.codes.weight
    mean = (codes[0] + codes[2]) / 2
    assert torch.allclose(field.appearance_codes(2, None, Appearance((0, 2)))[1], mean)
    assert torch.equal(field.appearance_codes(1, None, Appearance((3,)))[0], codes[3])
    blend = field.appearance_codes(1, None, Appearance((0, 2), (1, 3), 0.25))[0]
    assert torch.allclose(blend, 0.75 * mean + 0.25 * (codes[1] + codes[3]) / 2, atol=1e-6)
    for bad in ((), (0, 4)):
        with pytest.raises(ValueError):
            field.appearance_codes(1, None, Appearance(bad))


def test_model_file_round_trip_records_the_field_kind(tiny_scene, tmp_path):
    model = Trainer(tiny_scene, nerf_config(2, appearance=True), tmp_path).run(progress=False)
    loaded = Model.load(tmp_path / "model.npz")
    assert isinstance(loaded.field, NerfField) and loaded.field.cfg == model.field.cfg
    for i in (0, 3):
        assert torch.equal(loaded.render_camera(i), model.render_camera(i))
    assert not torch.equal(loaded.render_camera(0), loaded.render_camera(0, appearance=Appearance(3)))
    with pytest.raises(ValueError, match="NeRF"):
        _ = loaded.grid


def test_a_tone_mapped_nerf_gets_a_tone_controller_for_new_views(tiny_scene, tmp_path):
    """The tone controller works after any field: a NeRF trained with tone mapping is metered after
    training, saves its controller, and renders and scores new views through the predicted tone."""
    from hdrplenoxels.eval.renders import render_pose

    cfg = nerf_config(4)
    cfg.tonemap.enabled = True
    model = Trainer(tiny_scene, cfg, tmp_path).run(progress=False)
    loaded = Model.load(tmp_path / "model.npz")
    assert loaded.controller is not None and loaded.controller.form == model.controller.form
    pose = tiny_scene.cameras.c2w[tiny_scene.test_ids[0]]
    auto = render_pose(loaded, pose, tone="auto", convention="opencv")
    assert auto.ldr.shape == auto.hdr.shape and bool(torch.isfinite(auto.ldr).all())
    mean = render_pose(loaded, pose, tone="mean", convention="opencv")
    assert torch.equal(auto.hdr, mean.hdr)  # the camera changes the picture, never the radiance
    scores = evaluate(loaded, tiny_scene, lpips=False, tone="auto")
    assert scores["tone"] == "auto" and np.isfinite(scores["psnr"])


def test_resume_continues_exactly_like_an_unbroken_run(tiny_scene, tmp_path):
    unbroken = Trainer(tiny_scene, nerf_config(8), tmp_path / "a").run(progress=False)
    Trainer(tiny_scene, nerf_config(5), tmp_path / "b").run(progress=False)
    resumed = Trainer(tiny_scene, nerf_config(8), tmp_path / "b", resume=True)
    assert resumed.step == 5
    model = resumed.run(progress=False)
    for a, b in zip(unbroken.field.state_dict().values(), model.field.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # The finished run's last checkpoint was its training state beside the model, which held the field.
    meta, extra = load_run_state(tmp_path / "b" / CHECKPOINT_DIR / "step_0000005.npz")
    assert meta["step"] == 5 and "optim/generator" in extra and meta["field_file"] == MODEL_FILE


def test_the_optimiser_state_for_a_checkpoint_is_copied_not_shared(tiny_scene, tmp_path):
    """A checkpoint may be written behind the next steps (a GPU's periodic ones): what it is written from
    shares no memory with Adam's state, which those steps change in place (its step even on a GPU)."""
    trainer = Trainer(tiny_scene, nerf_config(2), tmp_path)
    trainer.run(progress=False)
    arrays = trainer.engine.state_arrays()
    live = [v for state in trainer.engine.optimiser.state.values() for v in state.values()]
    assert live and len(arrays) == len(live) + 1  # + the generator
    assert not any(np.shares_memory(a, v.numpy()) for a in arrays.values() for v in live)


def test_train_render_eval_nerf_a_from_the_cli(tiny_scene_path, tmp_path, capsys):
    run = tmp_path / "run"
    sets = ["--set", "nerf.width=32", "--set", "nerf.depth=2", "--set", "nerf.skip=1"]
    sets += ["--set", "nerf.n_coarse=8", "--set", "nerf.n_fine=8", "--set", "nerf.appearance_dim=4"]
    main(["train", str(tiny_scene_path), "--out", str(run), "--model", "nerf", "--appearance-embedding"]
         + ["--iters", "3", "--batch-size", "128", "--device", "cpu", "--quiet", *sets])  # fmt: skip
    config = json.loads((run / "config.json").read_text())
    assert (
        config["model"] == "nerf" and config["nerf"]["appearance"] and config["nerf"]["appearance_dim"] == 4
    )
    model = Model.load(run / "model.npz")
    assert model.field.codes.weight.shape == (TINY.num_views, 4)
    main(["eval", str(run), "--no-lpips"])
    assert "psnr" in capsys.readouterr().out.lower()
    for name, flags in [("own", []), ("blend", ["--embedding-from", "1", "--embedding-to", "2"])]:
        main(["render", str(run), "--out", str(tmp_path / name), *flags])
    view = sorted((tmp_path / "own").glob("*.exr"))[0].name
    assert (tmp_path / "blend" / view).exists()
    with pytest.raises(SystemExit) as e:
        args = ["--out", str(tmp_path / "g"), "--appearance-embedding", "--quiet"]
        main(["train", str(tiny_scene_path), *args])
    assert e.value.code == 2


def _varying(scene, evs: list[float]):
    """The scene as shot by a camera whose exposure changes from view to view (stops `evs`)."""
    images = [
        np.clip(np.asarray(img, np.float64) * 2.0**ev, 0, 255).round().astype(np.uint8)
        for img, ev in zip(scene.images, evs, strict=True)
    ]
    return dataclasses.replace(scene, images=images)


def test_tone_mapping_after_nerf_beats_nerf_alone_on_varying_exposure(tiny_scene, tmp_path):
    evs = [(-2.0, -1.0, 0.0, 1.0)[i % 4] for i in range(len(tiny_scene.images))]
    scene = _varying(tiny_scene, evs)
    psnr = {}
    for tonemap in (False, True):
        cfg = nerf_config(150)
        cfg.optim.batch_size = 512
        cfg.tonemap.enabled = tonemap
        cfg.tonemap.lr = 3e-2
        model = Trainer(scene, cfg, tmp_path / str(tonemap)).run(progress=False)
        psnr[tonemap] = evaluate(model, scene, lpips=False)["psnr"]
    assert psnr[True] >= psnr[False] + 5.0, psnr


def test_a_nerf_file_keeps_its_network_not_its_adam_settings(tiny_scene, tmp_path):
    model = Trainer(tiny_scene, nerf_config(1), tmp_path / "run").run(progress=False)
    path = tmp_path / "run" / "model.npz"
    with np.load(path) as z:
        header = json.loads(str(z["nerf_json"]))
    assert "lr" not in header["config"] and header["config"]["width"] == SMALL.width
    header["config"].update(lr=1.0, lr_final=0.5, lr_decay_steps=7)  # as files before the move hold
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["nerf_json"] = np.array(json.dumps(header))
    np.savez(tmp_path / "old.npz", **arrays)
    field, _, _ = load_field(tmp_path / "old.npz")
    assert field.cfg == model.field.cfg


def test_a_nerf_file_whose_settings_are_not_a_mapping_is_named(tiny_scene, tmp_path):
    Trainer(tiny_scene, nerf_config(1), tmp_path / "run").run(progress=False)
    with np.load(tmp_path / "run" / "model.npz") as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(str(arrays["nerf_json"]))
    arrays["nerf_json"] = np.array(json.dumps({**header, "config": [1, 2]}))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match="bad.npz"):
        load_field(tmp_path / "bad.npz")
