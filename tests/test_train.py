"""Trainer pieces on a tiny scene: ray pool protocol, learning, upsampling, checkpoints, exact resume."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch
from helpers import raises_naming
from test_cli import _tiny_dataset

from hdrplenoxels.cli.main import main
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.placement import setup_scene
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.grid.io import load_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid, grid_in_data_frame
from hdrplenoxels.render import ray_order
from hdrplenoxels.synth.procedural import ProceduralSceneSpec
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines import warp_grid
from hdrplenoxels.train.engines.grid_engine import view_prior_pull
from hdrplenoxels.train.optim import StepClock
from hdrplenoxels.train.presets import PRESETS, preset
from hdrplenoxels.train.ray_pool import RayPool
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR
from hdrplenoxels.train.trainer import Trainer

TINY = ProceduralSceneSpec(grid_reso=24, num_views=16, width=24, height=20)


def tiny_config(n_iters: int) -> TrainConfig:
    cfg = preset("fast")
    cfg.grid.reso_schedule = [(12, 12, 12), (20, 20, 20)]
    cfg.grid.upsample_every = 20
    cfg.optim.n_iters = n_iters
    cfg.optim.batch_size = 512
    cfg.optim.lr_decay_steps = 60
    cfg.checkpoint_every = 15
    cfg.checkpoint_gap_seconds = 0.0  # every 15th step, however fast the steps
    cfg.log_every = 5
    return cfg


def test_white_balance_statistics_never_read_right_halves_of_test_views(tiny_scene):
    """Painting the scored right halves white must not move any image's white-balance statistics."""
    cams, geom = setup_scene(tiny_scene)
    images = [im.copy() for im in tiny_scene.images]
    args = (cams, geom, tiny_scene.train_ids, tiny_scene.test_ids, "right-half", "cpu")
    before = RayPool(images, *args).linear_channel_means(len(images), 1.0)
    for i in tiny_scene.test_ids:
        images[i][:, left_width(TINY.width) :] = 255
    assert torch.equal(RayPool(images, *args).linear_channel_means(len(images), 1.0), before)
    images[tiny_scene.test_ids[0]][:, 0] = 255  # the left half does count
    assert not torch.equal(RayPool(images, *args).linear_channel_means(len(images), 1.0), before)


def test_camera_response_sharing_gives_each_camera_body_its_curve(tiny_scene, tmp_path):
    """Under the default "camera" sharing, images of another size (another body) get their own curve."""
    cropped = [im[:, :22] if i % 2 else im for i, im in enumerate(tiny_scene.images)]
    sizes = np.array([[22 if i % 2 else TINY.width, TINY.height] for i in range(len(cropped))])
    cams = tiny_scene.cameras
    scene = SceneData(
        cropped, Cameras(cams.c2w, cams.intrinsics, sizes), tiny_scene.names, tiny_scene.train_ids,
        tiny_scene.test_ids, tiny_scene.source, tiny_scene.scene_box, tiny_scene.forward_facing,
    )  # fmt: skip
    cfg = tiny_config(1)
    cfg.tonemap.enabled = True
    groups = Trainer(scene, cfg, tmp_path / "run").tonemapper.crf_group.tolist()
    assert groups[0] != groups[1] and groups == [groups[i % 2] for i in range(len(cropped))]
    cfg.tonemap.crf_sharing = "scene"
    assert set(Trainer(scene, cfg, tmp_path / "scene").tonemapper.crf_group.tolist()) == {0}


def test_the_grid_tv_is_set_from_the_number_of_photos(tiny_scene, tmp_path):
    """`optim.tv_photos` reaches the engine as the TV weights for this capture's 16 photos, the run's
    config.json keeps the rule (a resume resolves it again), and a line says what it did."""
    cfg = tiny_config(1)
    cfg.optim.tv_photos = 32.0  # (32 / 16)^2 = 4
    trainer = Trainer(tiny_scene, cfg, tmp_path)
    assert trainer.engine.cfg.optim.lambda_tv_sigma == pytest.approx(4 * cfg.optim.lambda_tv_sigma)
    assert trainer.engine.cfg.optim.lambda_tv_sh == pytest.approx(4 * cfg.optim.lambda_tv_sh)
    assert any("TV weights x4 for 16 photos" in note for note in trainer.config_notes)
    trainer.run(progress=False)
    saved = TrainConfig.from_dict(json.loads((tmp_path / "config.json").read_text()))
    assert saved.optim.tv_photos == 32.0 and saved.optim.lambda_tv_sigma == cfg.optim.lambda_tv_sigma
    cfg.holdout = "full"  # the test views are not learned from at all: fewer photos, a stronger TV
    trained = len(tiny_scene.train_ids)
    full = Trainer(tiny_scene, cfg, tmp_path / "full")
    assert trained < 16 and any(f"for {trained} photos" in note for note in full.config_notes)
    stronger = (32 / trained) ** 2 * cfg.optim.lambda_tv_sigma
    assert full.engine.cfg.optim.lambda_tv_sigma == pytest.approx(stronger)


def test_ray_pool_never_samples_right_halves_of_test_views(tiny_scene):
    cams, geom = setup_scene(tiny_scene)
    pool = RayPool(
        tiny_scene.images, cams, geom, tiny_scene.train_ids, tiny_scene.test_ids, "right-half", "cpu"
    )
    w = TINY.width
    n_test_pixels = len(tiny_scene.test_ids) * left_width(w) * TINY.height
    assert len(pool) == len(tiny_scene.train_ids) * w * TINY.height + n_test_pixels
    batch = pool.sample(20000, torch.Generator().manual_seed(0))
    is_test = torch.isin(batch.image_ids, torch.tensor(tiny_scene.test_ids))
    assert is_test.any() and (batch.cols[is_test] < left_width(w)).all()
    assert (batch.cols[~is_test] >= left_width(w)).any()
    # Targets are the pixels the rays go through.
    i, r, c = int(batch.image_ids[0]), int(batch.rows[0]), int(batch.cols[0])
    assert torch.allclose(
        batch.target[0], torch.tensor(tiny_scene.images[i][r, c] / 255.0, dtype=torch.float32)
    )

    full = RayPool(tiny_scene.images, cams, geom, tiny_scene.train_ids, tiny_scene.test_ids, "full", "cpu")
    ids = full.sample(5000, torch.Generator().manual_seed(1)).image_ids
    assert not torch.isin(ids, torch.tensor(tiny_scene.test_ids)).any()


def test_training_learns_upsamples_and_checkpoints(tiny_scene, tmp_path):
    trainer = Trainer(tiny_scene, tiny_config(45), tmp_path)
    model = trainer.run(progress=False)
    assert model.grid.reso == (20, 20, 20) and trainer.engine.level == 1
    log = [json.loads(line) for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert log[-1]["mse"] < 0.5 * log[0]["mse"]
    assert log[0]["voxels"] == 12**3 and log[-1]["voxels"] < 20**3  # pruned at the upsample
    ckpts = sorted(p.name for p in (tmp_path / CHECKPOINT_DIR).glob("*.npz"))
    assert ckpts == ["step_0000015.npz", "step_0000030.npz", "step_0000045.npz"]
    assert (tmp_path / "model.npz").exists() and json.loads((tmp_path / "config.json").read_text())[
        "preset"
    ] == "fast"


def cpu_config(n_iters: int) -> TrainConfig:
    """On the CPU every run is bit-reproducible; CUDA's float atomics add in a varying order, so two
    GPU runs (resumed or not) drift apart by float rounding and cannot be compared exactly. Plain
    Plenoxels: with the tone mapper the view prior acts for a fraction of the schedule, so a run
    extended by --iters is not the run trained to the longer schedule (crash-safety tests resume
    tone-mapped runs of one schedule)."""
    cfg = tiny_config(n_iters)
    cfg.device = "cpu"
    cfg.tonemap.enabled = False
    return cfg


def test_resume_continues_exactly_like_an_unbroken_run(tiny_scene, tmp_path):
    unbroken = Trainer(tiny_scene, cpu_config(40), tmp_path / "a").run(progress=False)
    first = Trainer(tiny_scene, cpu_config(30), tmp_path / "b")
    first.run(progress=False)
    resumed_trainer = Trainer(tiny_scene, cpu_config(40), tmp_path / "b", resume=True)
    assert resumed_trainer.step == 30 and resumed_trainer.engine.level == 1
    resumed = resumed_trainer.run(progress=False)
    assert torch.equal(unbroken.grid.links, resumed.grid.links)
    assert torch.allclose(unbroken.grid.density, resumed.grid.density, atol=1e-6)
    assert torch.allclose(unbroken.grid.sh, resumed.grid.sh, atol=1e-6)
    grid, meta, extra = load_grid(tmp_path / "b" / CHECKPOINT_DIR / "step_0000030.npz")
    assert meta["step"] == 30 and "rng/state" in extra


def test_weight_pruning_runs_in_the_trainer(tiny_scene, tmp_path):
    cfg = tiny_config(21)
    cfg.tonemap.enabled = False  # plain Plenoxels: the density forms quickly enough to prune at step 20
    cfg.grid.prune = "weight"
    cfg.grid.weight_ray_stride = 4
    model = Trainer(tiny_scene, cfg, tmp_path).run(progress=False)
    assert 0 < model.grid.num_voxels < 20**3


def test_forward_facing_scene_goes_to_ndc():
    n = 6
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 0, 3] = np.linspace(-0.5, 0.5, n)  # a sideways sweep, all looking along +z
    c2w[:, 2, 3] = -4.0
    cams = Cameras(c2w, np.tile([40.0, 40.0, 16.0, 12.0], (n, 1)), np.tile([32, 24], (n, 1)))
    imgs = [np.zeros((24, 32, 3), np.uint8)] * n
    scene = SceneData(
        imgs, cams, [str(i) for i in range(n)], [1, 2, 3, 4, 5], [0], source=".", near_far=(2.0, 8.0)
    )
    world_cams, geom = setup_scene(scene)
    assert geom.mode == "ndc" and geom.ndc.coeff_x == pytest.approx(2 * 40 / 32)
    # Cameras are recentred (mean position at the origin) and still look along +z.
    assert np.allclose(world_cams.c2w[:, :3, 3].mean(0), 0, atol=1e-9)
    assert np.allclose(world_cams.c2w[:, :3, 2], [0, 0, 1], atol=1e-9)
    # A point at the near bound (depth 2) lands at depth 1/0.75 after scaling: beyond the near plane z = 1.
    cols, rows = torch.tensor([16]), torch.tensor([12])
    k = torch.tensor([[40.0, 40.0, 16.0, 12.0]])
    o, d = geom.rays(torch.tensor(world_cams.c2w[:1], dtype=torch.float32), k, cols, rows)
    assert o[0, 2] == pytest.approx(-1.0, abs=1e-5) and d[0, 2] > 0
    # Without depth bounds, auto mode needs a box, and says what to add when there is none.
    scene.near_far = None
    raises_naming(".", setup_scene, scene, contains=("forward-facing", '"near_far"', "--scene-mode bbox"))
    scene.scene_box = ((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))
    assert setup_scene(scene)[1].mode == "bbox"


def test_bbox_scenes_are_normalised_so_the_dataset_scale_does_not_matter(tiny_scene):
    """Density is per world unit: a scene in other units (SfM's are arbitrary) must train the same, so
    the box is moved to the origin with a largest half-side of 1, and the same poses come out."""
    cams, geom = setup_scene(tiny_scene)
    assert geom.center == (0.0, 0.0, 0.0) and max(geom.radius) == pytest.approx(1.0)
    scaled = SceneData(
        tiny_scene.images,
        Cameras(tiny_scene.cameras.c2w.copy(), tiny_scene.cameras.intrinsics, tiny_scene.cameras.sizes),
        tiny_scene.names,
        tiny_scene.train_ids,
        tiny_scene.test_ids,
        source=".",
        scene_box=tuple(tuple(3.0 * v + 5.0 for v in corner) for corner in tiny_scene.scene_box),
    )
    scaled.cameras.c2w[:, :3, 3] = 3.0 * scaled.cameras.c2w[:, :3, 3] + 5.0
    cams3, geom3 = setup_scene(scaled)
    assert np.allclose(cams3.c2w, cams.c2w, atol=1e-9) and np.allclose(geom3.radius, geom.radius)
    # A user's pose in the dataset's frame lands where the same camera of the training set does.
    assert np.allclose(geom3.poses_to_world(scaled.cameras.c2w[:2]), cams.c2w[:2], atol=1e-9)
    # Exports go back to the dataset's frame with density per dataset unit (optical depth unchanged).
    grid = SparseGrid.create((4, 4, 4))
    grid.center, grid.radius = geom3.center, geom3.radius
    grid.density = torch.full_like(grid.density, 6.0)
    back = grid_in_data_frame(grid, geom3)
    lo, hi = np.asarray(scaled.scene_box)
    assert np.allclose(back.center, (lo + hi) / 2) and np.allclose(back.radius, (hi - lo) / 2)
    assert torch.allclose(back.density * max(back.radius), grid.density * max(grid.radius))


def test_no_resample_after_the_final_step(tiny_scene, tmp_path):
    # 20 iterations with upsample_every = 20: the final model must stay at the trained resolution.
    model = Trainer(tiny_scene, tiny_config(20), tmp_path).run(progress=False)
    assert model.grid.reso == (12, 12, 12)


def test_resume_refuses_a_changed_configuration(tiny_scene, tmp_path):
    Trainer(tiny_scene, tiny_config(15), tmp_path).run(progress=False)
    changed = tiny_config(30)
    changed.holdout = "full"  # would score pixels the run already trained on
    with pytest.raises(InputError, match="holdout"):
        Trainer(tiny_scene, changed, tmp_path, resume=True)
    assert Trainer(tiny_scene, tiny_config(30), tmp_path, resume=True).step == 15  # more iterations are fine
    how = tiny_config(30)
    how.view_prior_update = "owed"  # how the same update is computed (tests/test_owed_pull.py)
    assert Trainer(tiny_scene, how, tmp_path, resume=True).step == 15


def test_resample_that_keeps_nothing_is_an_error(tiny_scene, tmp_path):
    cfg = tiny_config(25)
    cfg.grid.density_thresh = 1e9
    with pytest.raises(RuntimeError, match="no voxel passed"):
        Trainer(tiny_scene, cfg, tmp_path).run(progress=False)


def test_ndc_needs_a_positive_near_bound():
    cams = Cameras(
        np.tile(np.eye(4), (2, 1, 1)), np.tile([20.0, 20.0, 8.0, 8.0], (2, 1)), np.tile([16, 16], (2, 1))
    )
    imgs = [np.zeros((16, 16, 3), np.uint8)] * 2
    scene = SceneData(imgs, cams, ["a", "b"], [1], [0], source="scene.json", near_far=(0.0, 5.0))
    with pytest.raises(InputError, match="positive near"):
        setup_scene(scene, "ndc")


def test_a_new_run_refuses_a_folder_holding_one_unless_overwriting(tiny_scene, tmp_path):
    Trainer(tiny_scene, tiny_config(15), tmp_path).run(progress=False)
    with pytest.raises(InputError, match="--resume"):
        Trainer(tiny_scene, tiny_config(15), tmp_path)
    again = Trainer(tiny_scene, tiny_config(10), tmp_path, overwrite=True).run(progress=False)
    assert again.step == 10 and not (tmp_path / CHECKPOINT_DIR / "step_0000015.npz").exists()
    steps = [json.loads(line)["step"] for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert steps == [5, 10]  # the old run's log is gone too


@pytest.mark.parametrize(
    "tonemap, prior_over, sort_rays",
    [(False, False, False), (True, False, False), (True, True, False), (True, False, True)],
)
def test_fused_warp_step_equals_the_pytorch_reference_step(
    tiny_scene, tmp_path, monkeypatch, tonemap, prior_over, sort_rays
):
    """Warp kernels with per-thread gradient buffers, the sample record and the Warp TV hand the
    optimiser the gradients that the PyTorch renderer, autograd and the torch TV give (the fused
    RMSProp has its own test). With `sort_rays` the Warp trainer reorders its batches for locality, as
    it does on large grids: targets and tone-mapping indices must follow their rays.

    One step from the same trained state is compared, not whole runs: RMSProp moves every coefficient
    by about one learning rate whatever its gradient's size, so float noise in near-zero gradients
    flips later steps.
    """
    sorted_batches = []
    if sort_rays:
        monkeypatch.setattr(ray_order, "CACHED_GRID_BYTES", -1)

        def spy_order(*args):
            sorted_batches.append(ray_order.locality_order(*args))
            return sorted_batches[-1]

        monkeypatch.setattr(warp_grid, "training_order", spy_order)
    trainers = {}
    for backend in ("warp", "torch"):
        cfg = tiny_config(30)
        cfg.backend = backend
        cfg.tonemap.enabled = tonemap
        cfg.tonemap.sh_view_until = 0.1 if prior_over else cfg.tonemap.sh_view_until  # over at step 3
        cfg.optim.lambda_tv_sigma, cfg.optim.lambda_tv_sh = 1e-3, 1e-3  # large enough to matter
        trainers[backend] = Trainer(tiny_scene, cfg, tmp_path / backend)
    fast, ref = trainers["warp"], trainers["torch"]
    for _ in range(8):
        fast.train_step()
    ref.engine.field = SparseGrid(
        fast.field.links,
        fast.field.density.detach().clone(),
        fast.field.sh.detach().clone(),
        fast.field.center,
        fast.field.radius,
    )
    ref.generator.set_state(fast.generator.get_state())
    ref.step = fast.step  # the view prior's end depends on it
    if tonemap:
        ref.tonemapper.load_state_dict(fast.tonemapper.state_dict())
    seen, touched, pulled = {}, {}, {}
    for backend, trainer in trainers.items():
        step_accumulated = trainer.engine.optimiser.step_accumulated

        def spy(params, grads, lrs, *rest, backend=backend, step_accumulated=step_accumulated, **kw):
            seen[backend] = (grads[0].sum(0).clone(), grads[1].sum(0).clone())
            touched[backend] = None if kw.get("touched") is None else kw["touched"].clone()
            pulled[backend] = kw["pulls"][1] is not None
            step_accumulated(params, grads, lrs, *rest, **kw)

        trainer.engine.optimiser.step_accumulated = spy
        trainer.train_step()
    if sort_rays:  # every Warp step sorted its batch, and sorting really moved rays
        assert len(sorted_batches) == 9 and not torch.equal(sorted_batches[-1].cpu(), torch.arange(512))
    for fused, reference in zip(seen["warp"], seen["torch"]):
        scale = reference.abs().max()
        assert scale > 1e-6 and (fused - reference).abs().max() <= 1e-4 * scale
    # The optimiser reads only the marked rows' gradients: every row with a gradient must be marked.
    # While the view prior is on, its pull makes the update dense (every row moves).
    assert touched["torch"] is None  # the reference's update is dense
    assert pulled["warp"] == pulled["torch"] == (tonemap and not prior_over)
    has_gradient = (seen["warp"][0] != 0) | (seen["warp"][1] != 0).any(1)
    marked = touched["warp"] != 0
    assert has_gradient.any() and not (has_gradient & ~marked).any() and not marked.all()
    assert not fast.engine.gradients().touched.any()  # cleared for the next step


@pytest.mark.parametrize("tonemap", [True, False])
def test_view_prior_pulls_the_non_dc_sh_with_tone_mapping_until_its_step(tiny_scene, tmp_path, tonemap):
    """lambda_sh_view is the L2 prior lambda * (sum of squared non-DC SH coefficients), which keeps the SH
    from absorbing per-view exposure, for the first sh_view_until of the schedule; plain Plenoxels, which
    has no per-view exposure, goes without. Its gradient, 2 * lambda * sh beyond the DC term, is added
    by the optimiser in its own pass: one step equals the reference step with that gradient added to
    the buffers' photometric one, which the prior leaves as it is."""
    cfg = tiny_config(30)
    cfg.tonemap.enabled = tonemap
    cfg.tonemap.lambda_sh_view = 0.25
    trainer = Trainer(tiny_scene, cfg, tmp_path)
    for _ in range(3):
        trainer.train_step()
    engine, grid = trainer.engine, trainer.field
    engine.settle()  # what the voxels owe of the pull is paid: the dense update's values
    sh = grid.sh.detach().clone()
    assert sh.view(-1, 3, grid.basis_dim)[..., 1:].abs().max() > 0
    engine.cfg.optim.lambda_tv_sigma = engine.cfg.optim.lambda_tv_sh = 0.0  # the view prior alone
    grads = engine.gradients()
    photometric = torch.randn(sh.shape, generator=torch.Generator().manual_seed(0)).to(sh.device)
    grads.sh.zero_()
    grads.sh[0] = photometric
    engine.regularise(trainer.generator)
    assert torch.equal(grads.sh[0], photometric)  # the buffers keep the photometric gradient
    weight = trainer._view_prior_weight()
    assert (view_prior_pull(grid.basis_dim, weight, grid.device) is not None) == tonemap  # a dense update
    grads.touched.fill_(1)  # the planted photometric gradient is on every row
    prior = (
        0.5 * sh.view(-1, 3, grid.basis_dim) if tonemap else torch.zeros_like(sh).view(-1, 3, grid.basis_dim)
    )
    prior[..., 0] = 0.0
    reference = copy.deepcopy(engine.optimiser)
    ref_params = [grid.density.detach().clone(), sh.clone()]
    ref_grads = [grads.density.sum(0), photometric + prior.view_as(sh)]
    reference.step(ref_params, ref_grads, [engine.lr_sigma(trainer.step), engine.lr_sh(trainer.step)])
    engine.step(StepClock.at(trainer.step, engine.device), weight)
    assert torch.allclose(grid.sh.detach(), ref_params[1], rtol=1e-5, atol=1e-6)
    assert (grid.sh.detach() - sh).abs().max() > 1e-3  # the step moved the SH

    # It stops at its fraction of the schedule (3 of 30 steps done: a tenth is over, a fifth is not).
    for until, active in ((0.1, False), (0.2, tonemap)):
        trainer.settings.tonemap.sh_view_until = until
        assert (trainer._view_prior_weight() > 0) == active


def test_the_reference_image_is_a_full_training_view(tiny_scene, tmp_path, monkeypatch):
    """A test view has only its left half to hold its frozen white balance against the gauge's drift, and
    its right half is scored: so the reference is picked among training views even when a test view's
    statistics are the closest to the dataset's."""
    n = len(tiny_scene.names)
    means = torch.linspace(0.1, 0.9, n)[:, None].repeat(1, 3)
    test_view = tiny_scene.test_ids[0]
    means[test_view] = means.mean(0)  # exactly the dataset's mean (the old choice)
    monkeypatch.setattr(RayPool, "linear_channel_means", lambda self, n_images, gamma: means.clone())
    cfg = tiny_config(10)
    cfg.tonemap.enabled = True
    trainer = Trainer(tiny_scene, cfg, tmp_path)
    reference = int(trainer.tonemapper.reference)
    assert reference in tiny_scene.train_ids
    overall = means.mean(1)
    closest = min(tiny_scene.train_ids, key=lambda i: abs(float(overall[i] - overall.mean())))
    assert reference == closest


def _cells(reso: tuple[int, int, int]) -> int:
    return reso[0] * reso[1] * reso[2]


def test_every_preset_is_a_valid_config_and_balanced_sits_between_fast_and_the_paper():
    """The ladder docs/usage.md documents: each rung trains a larger grid for more steps, and `balanced`
    gives the background a finer MSI than `fast` (its measured gain on unbounded scenes)."""
    for name in PRESETS:
        cfg = preset(name)
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg, name
    fast, balanced, paper = preset("fast"), preset("balanced"), preset("paper-synthetic")
    tops = [_cells(c.grid.reso_schedule[-1]) for c in (fast, balanced, paper)]
    assert tops == sorted(tops) and len(set(tops)) == 3
    steps = [c.optim.n_iters for c in (fast, balanced, paper)]
    assert steps == sorted(steps) and len(set(steps)) == 3
    assert balanced.grid.sh_degree == 2 > fast.grid.sh_degree
    msi = [c.background.height * c.background.width for c in (fast, balanced)]
    assert msi[1] >= 4 * msi[0]
    # the NeRF presets hold the response curve smoother than after the grid (JOURNAL.md)
    for name in ("nerf-fast", "nerf-cpu"):
        assert preset(name).tonemap.lambda_crf_smooth > fast.tonemap.lambda_crf_smooth, name


def test_balanced_preset_trains_from_the_command_line(tmp_path):
    run = tmp_path / "run"
    main(["train", str(_tiny_dataset(tmp_path / "scene")), "--preset", "balanced", "--tonemap"]
         + ["--iters", "2", "--out", str(run), "--device", "cpu", "--quiet"])  # fmt: skip
    assert json.loads((run / "config.json").read_text())["preset"] == "balanced"
    with np.load(run / "model.npz") as z:
        assert json.loads(str(z["meta_json"]))["step"] == 2
