"""`benchmarks/gpu_preset.py` (choosing a GPU preset for real captures on validation views): what can be
held without a GPU. Every candidate is a configuration `train` accepts, as the command line will pass it;
a kit is its dataset at the benchmark's downscale; the choice keeps to its rule; a run continues the last
session's results and stops at its deadline."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hdrplenoxels.core.settings import apply_overrides, parse_overrides
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.sight_lines import POINTS_KEY, SightLines, write_sight_lines
from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.presets import preset

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import gpu_preset  # noqa: E402


@pytest.mark.parametrize("name", list(gpu_preset.CANDIDATES))
def test_every_candidate_is_a_configuration_train_accepts(name):
    config = gpu_preset.candidate_config(name)
    assert isinstance(config.check("cascade"), list)  # raises for a rule it breaks
    items = [a for a in gpu_preset.set_args(gpu_preset.CANDIDATES[name].overrides) if a != "--set"]
    assert apply_overrides(preset("balanced"), parse_overrides(TrainConfig, items)) == config
    assert config.optim.n_iters % len(config.grid.reso_schedule) == 0


def test_the_base_candidate_is_balanced_and_the_schedule_keeps_its_proportions():
    assert gpu_preset.candidate_config("balanced") == preset("balanced")
    same = gpu_preset.schedule(3000, gpu_preset.BALANCED_LEVELS)
    balanced = preset("balanced")
    assert apply_overrides(balanced, same | {"checkpoint_every": balanced.checkpoint_every}) == balanced


def test_a_kit_is_the_validation_dataset_at_its_downscale(tmp_path):
    data = write_procedural_scene(tmp_path / "walled", TINY_WALLED).parent
    scene = load_scene(data)
    rng = np.random.default_rng(0)
    lines = SightLines(rng.normal(size=(5, 3)), np.array([0, 1, 2, 3]), np.array([0, 1, 2, 4]))
    write_sight_lines(data / "points.npz", lines, scene.names)
    meta = json.loads((data / "transforms.json").read_text())
    (data / "transforms.json").write_text(json.dumps(meta | {POINTS_KEY: "points.npz"}))
    kit = load_scene(gpu_preset.write_kit(data, tmp_path / "kit", 2, None))
    reduced = load_scene(data, 2)
    assert [Path(n).stem for n in kit.names] == [Path(n).stem for n in reduced.names]
    assert all(np.array_equal(a, b) for a, b in zip(kit.images, reduced.images, strict=True))
    np.testing.assert_array_equal(kit.cameras.intrinsics, reduced.cameras.intrinsics)
    np.testing.assert_array_equal(kit.cameras.c2w, reduced.cameras.c2w)
    np.testing.assert_array_equal(kit.cameras.sizes, reduced.cameras.sizes)
    np.testing.assert_array_equal(kit.sight_lines.points, reduced.sight_lines.points)
    np.testing.assert_array_equal(kit.sight_lines.view, reduced.sight_lines.view)
    jpeg = load_scene(gpu_preset.write_kit(data, tmp_path / "jpeg", 2, 95))
    error = np.mean([np.abs(a.astype(int) - b).mean() for a, b in zip(jpeg.images, reduced.images)])
    assert 0 < error < 4.0  # codes, JPEG's loss on 16-pixel images of hard edges


def test_a_kit_of_a_validation_fold_holds_out_the_folds_views(tmp_path):
    """A fold other than 0 names its validation views by file (`test_filenames`); the kit renames its
    files, and its split with them."""
    from real_captures import validation_set

    data = write_procedural_scene(tmp_path / "walled", TINY_WALLED).parent
    fold = load_scene(validation_set(data, tmp_path / "fold1", 1))
    kit = load_scene(gpu_preset.write_kit(tmp_path / "fold1", tmp_path / "kit", 2, 95))
    held = [Path(fold.names[i]).stem for i in fold.test_ids]
    assert held and [Path(kit.names[i]).stem for i in kit.test_ids] == held
    assert fold.test_ids != list(range(0, len(fold.names), 8))  # not the every-8th split from the first


def test_validation_folds_hold_out_every_8th_remaining_view_from_their_own_start(tmp_path):
    """No fold holds a test view; fold 0 is the loader's every-8th split, fold J starts at the J-th view
    left; together the folds hold out every view left once."""
    from real_captures import validation_set

    data = write_procedural_scene(tmp_path / "walled", TINY_WALLED).parent
    scene = load_scene(data)
    names = [Path(n).name for n in scene.names]
    test = {names[i] for i in scene.test_ids}
    left = [n for n in names if n not in test]
    held = []
    for fold in range(min(8, len(left))):
        split = load_scene(validation_set(data, tmp_path / f"fold{fold}", fold))
        ids = split.test_ids
        assert [Path(split.names[i]).name for i in ids] == left[fold::8]
        assert {Path(n).name for n in split.names} == set(left)
        held += [Path(split.names[i]).name for i in ids]
    assert sorted(held) == sorted(left)
    with pytest.raises(ValueError, match="fold 8"):
        validation_set(data, tmp_path / "fold8", 8)


def _row(capture, candidate, psnr, seconds=60.0):
    config = gpu_preset.config_key(candidate)
    return {"capture": capture, "candidate": candidate, "psnr": psnr, "wall_s": seconds, "config": config}


def test_the_choice_is_the_best_mean_among_candidates_that_ran_everywhere_in_budget():
    rows = [
        _row("a", "balanced", 20.0),
        _row("b", "balanced", 22.0),
        _row("a", "long", 21.0),
        _row("b", "long", 24.0),
        _row("a", "fine", 23.0, seconds=200.0),  # the best, but over the budget on one capture
        _row("b", "fine", 26.0),
        _row("a", "fine-long", 30.0),  # better still, but not run on b yet
        {"capture": "b", "candidate": "fine-batch", "error": "out of memory"},
    ]
    assert gpu_preset.choose(rows, 180.0) == "long"
    assert gpu_preset.choose(rows, 300.0) == "fine"
    assert gpu_preset.gains(rows)["long"] == {"a": 1.0, "b": 2.0}
    table = gpu_preset.report(rows, 180.0)
    assert "21.00 (+1.00) / 60" in table and "failed" in table and "): long" in table


def _stand_in(monkeypatch) -> list[tuple]:
    """`train_and_score` replaced by a stand-in; the list it returns gets (capture, candidate, kit,
    reference kit) for each run."""
    calls = []

    def fake(kit, run, name, reference, sheet):
        assert sheet.name == f"{kit.parent.name}-{name}.png"
        calls.append((kit.parent.name, name, kit.name, reference.name))
        return {"psnr": 20.0, "ssim": 0.5, "views": 1, "train_s": 1.0, "wall_s": 1.0, "peak_gb": 0.1}

    monkeypatch.setattr(gpu_preset, "train_and_score", fake)
    return calls


def _run_args(tmp_path, candidates, results=None) -> argparse.Namespace:
    return argparse.Namespace(
        kits=tmp_path / "kits",
        out=tmp_path / "out",
        results=results,
        deadline=float("inf"),
        budget=180.0,
        captures=None,
        candidates=candidates,
        keep=False,
    )


def test_a_run_continues_the_last_results_and_starts_nothing_past_its_deadline(tmp_path, monkeypatch):
    for capture in ("a", "b"):
        (tmp_path / "kits" / capture / "x1").mkdir(parents=True)
    calls = _stand_in(monkeypatch)
    previous = tmp_path / "previous.json"
    old = _row("b", "balanced", 25.0) | {"config": "0123456789ab"}  # trained before a default changed
    previous.write_text(
        json.dumps([_row("a", "balanced", 19.0), old, _row("a", "long", 18.0) | {"config": None}])
    )
    args = _run_args(tmp_path, ["balanced", "long"], previous)
    gpu_preset.runs(args)
    assert [(c[0], c[1]) for c in calls] == [("b", "balanced"), ("a", "long"), ("b", "long")]
    rows = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [(r["capture"], r["candidate"]) for r in rows][0] == ("a", "balanced") and len(rows) == 4
    assert {r["psnr"] for r in rows} == {19.0, 20.0}  # the stale rows were run again, not kept
    assert all(r["config"] == gpu_preset.config_key(r["candidate"]) for r in rows)
    assert "Chosen" in (tmp_path / "out" / "results.md").read_text()
    calls.clear()
    gpu_preset.runs(argparse.Namespace(**vars(args) | {"results": None, "deadline": -1.0}))
    assert calls == []


def test_a_candidate_on_finer_photos_trains_on_them_and_is_scored_on_the_benchmarks_pixels(
    tmp_path, monkeypatch
):
    for x in ("x1", "x2"):
        (tmp_path / "kits" / "a" / x).mkdir(parents=True)
    calls = _stand_in(monkeypatch)
    gpu_preset.runs(_run_args(tmp_path, ["fine", "fine-photos"]))
    assert calls == [("a", "fine", "x1", "x1"), ("a", "fine-photos", "x2", "x1")]


@pytest.mark.parametrize(("factor", "finer"), [(4, 2), (3, 1), (1, 1), (6, 3), (8, 4), (5, 1), (2, 1)])
def test_finer_photos_are_a_whole_divisor_of_the_benchmarks_downscale(factor, finer):
    assert gpu_preset.finer_downscale(factor, 2) == finer


def test_a_finer_models_pictures_are_scored_block_averaged_to_the_references_pixels(tmp_path):
    """At the reference's own resolution the score is `evaluate`'s; against photos that are the model's
    own pictures block-averaged (what a finer picture reduced should be) it is nearly perfect, and one
    column off it is not."""
    import dataclasses

    import torch
    from test_train import TINY, tiny_config

    from hdrplenoxels.data.downscale import block_average
    from hdrplenoxels.eval.evaluate import evaluate, test_view_picture
    from hdrplenoxels.train.model import MODEL_FILE, Model
    from hdrplenoxels.train.trainer import Trainer

    # Twice the suite's tiny images, so that the reduced right halves are wide enough for SSIM's window.
    data = write_procedural_scene(tmp_path / "scene", dataclasses.replace(TINY, width=48, height=44))
    scene = load_scene(data)
    cfg = tiny_config(20)
    cfg.tonemap.enabled = True
    Trainer(scene, cfg, tmp_path / "run").run(progress=False)
    model = Model.load(tmp_path / "run" / MODEL_FILE)
    with torch.no_grad():
        same = gpu_preset.scores_at(model, scene, tmp_path / "sheet.png")
        result = evaluate(model, scene, lpips=False)
        pictures = {
            i: test_view_picture(model, model.render_camera(i), i, "own").numpy() for i in model.test_ids
        }
    assert (same["psnr"], same["ssim"], same["views"]) == pytest.approx(
        (result["psnr"], result["ssim"], result["num_test_views"])
    )
    sheet = np.asarray(Image.open(tmp_path / "sheet.png"))  # a row per view: photo | picture
    h, w = scene.images[0].shape[:2]
    assert sheet.shape == (h * len(model.test_ids), 2 * w, 3)
    first = model.test_ids[0]
    np.testing.assert_array_equal(sheet[:h, :w], scene.images[first])
    assert np.abs(sheet[:h, w:] / 255.0 - pictures[first]).max() <= 0.5 / 255 + 1e-6
    coarse = load_scene(data, 2)
    own = [
        np.rint(block_average(pictures[i], 2) * 255).astype(np.uint8) if i in pictures else image
        for i, image in enumerate(coarse.images)
    ]
    shifted = [np.roll(image, 1, axis=1) if i in pictures else image for i, image in enumerate(own)]
    with torch.no_grad():
        exact = gpu_preset.scores_at(model, dataclasses.replace(coarse, images=own))
        off = gpu_preset.scores_at(model, dataclasses.replace(coarse, images=shifted))
    assert exact["psnr"] > 50.0 and exact["views"] == len(model.test_ids)
    assert off["psnr"] < exact["psnr"] - 10.0


def test_the_committed_baseline_is_balanced_on_every_shared_capture_and_chooses_nothing():
    """The file a device session continues from (`--results`): only the reference's rows, so that no
    candidate's CPU row is taken for a run done, and none of them in the GPU budget."""
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "gpu_preset_baseline.json"
    rows = json.loads(path.read_text())
    assert sorted(r["capture"] for r in rows) == ["asclepius", "brickstamp", "freiburg_office", "kermit"]
    assert {r["candidate"] for r in rows} == {gpu_preset.BASE}
    assert all(r["device"] == "cpu" and r["psnr"] > 0 and r["views"] >= 1 for r in rows)
    assert set(gpu_preset.gains(rows)[gpu_preset.BASE].values()) == {0.0}
    assert gpu_preset.choose(rows, gpu_preset.BUDGET_S) is None


def test_the_committed_results_hold_balanced_and_name_their_device():
    """The file the next device session continues (`--results`): `balanced` with its TV rule (named in
    each row) on every capture of the baseline, measured on the CPU (quality does not depend on the
    device), and each further row a candidate measured on a GPU (a CPU row of another candidate there
    would count as a run done). They predate the near-camera and surface priors, so none counts as done
    today: the next session runs them again."""
    bench = Path(__file__).resolve().parent.parent / "benchmarks"
    baseline = json.loads((bench / "gpu_preset_baseline.json").read_text())
    rows = json.loads((bench / "gpu_preset_results.json").read_text())
    base = [r for r in rows if r["candidate"] == gpu_preset.BASE]
    assert sorted(r["capture"] for r in base) == sorted(r["capture"] for r in baseline)
    rule = f"optim.tv_photos={preset('balanced').optim.tv_photos:g}"
    assert all(r["device"] == "cpu" and rule in r["note"] and r["views"] >= 1 for r in base)
    later = [r for r in rows if r["candidate"] != gpu_preset.BASE]
    assert later and all(r["candidate"] in gpu_preset.CANDIDATES for r in later)
    assert all(r["device"] != "cpu" and r["wall_s"] > 0 and r["views"] >= 1 for r in later)
    assert gpu_preset.current(rows) == ([], rows)
