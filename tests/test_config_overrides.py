"""One way to override config fields by name (`train.config.apply_overrides`), used by `train --set`,
`experiment --set`, the experiments' per-run settings and `validation --variant`."""

from __future__ import annotations

import json

import pytest
from test_cli import _tiny_dataset

from hdrplenoxels.cli.main import EXIT_INPUT_ERROR, main
from hdrplenoxels.experiments.common import ExperimentSettings, config_for
from hdrplenoxels.experiments.validation import parse_variant
from hdrplenoxels.train.config import OverrideError, apply_overrides, parse_overrides
from hdrplenoxels.train.presets import preset


@pytest.mark.parametrize(
    "item, key, value",
    [
        ("tonemap.enabled=false", "tonemap.enabled", False),
        ("tonemap.vignetting=True", "tonemap.vignetting", True),
        ("optim.n_iters=12", "optim.n_iters", 12),
        ("optim.lr_sh=1e-3", "optim.lr_sh", 1e-3),
        ("tonemap.lambda_sh_view=0", "tonemap.lambda_sh_view", 0.0),
        ("device=cuda:1", "device", "cuda:1"),
        ("backend=torch", "backend", "torch"),
        ("tonemap.crf_sharing=image", "tonemap.crf_sharing", "image"),
        ("render.background_brightness=none", "render.background_brightness", None),
        ("render.background_brightness=0.25", "render.background_brightness", 0.25),
        ("render.background=0.25", "render.background_brightness", 0.25),  # its name before 2026-11-26
        (
            "grid.reso_schedule=[[64,64,64],[128,128,128]]",
            "grid.reso_schedule",
            [(64, 64, 64), (128, 128, 128)],
        ),
    ],
)
def test_values_are_typed_as_the_config_declares(item, key, value):
    typed = parse_overrides([item])
    assert typed == {key: value} and type(typed[key]) is type(value)
    cfg = apply_overrides(preset("fast"), [item])
    section, _, name = key.rpartition(".")
    assert getattr(getattr(cfg, section) if section else cfg, name) == value


def test_apply_returns_a_copy_and_later_items_win():
    cfg = preset("fast")
    out = apply_overrides(cfg, ["optim.lr_sh=1", "optim.lr_sh=2"])
    assert out.optim.lr_sh == 2.0 and cfg.optim.lr_sh == preset("fast").optim.lr_sh
    assert apply_overrides(cfg, {"optim.n_iters": 7, "tonemap.enabled": True}).optim.n_iters == 7


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["optim.lr_shh=1"], "unknown setting 'optim.lr_shh'; optim has n_iters, batch_size"),
        (["nonsense=1"], "sections background, data, grid, nerf, optim, render, tonemap, or preset"),
        (["grid=1"], "grid is a section"),
        (["optim.lr_sh"], "expected KEY=VALUE"),
        (["optim.n_iters=1.5"], "optim.n_iters takes an integer, got '1.5'"),
        (["optim.lr_sh=fast"], "optim.lr_sh takes a number, got 'fast'"),
        (["tonemap.enabled=maybe"], "tonemap.enabled takes true or false"),
        (["backend=cuda"], "backend takes one of warp, torch"),
        (["render.background=grey"], "render.background takes a number or none"),
        (
            ["grid.reso_schedule=[[64,64]]"],
            "grid.reso_schedule takes a JSON array, list[tuple[int, int, int]]",
        ),
        (["grid.reso_schedule=[[64,64,64]"], "grid.reso_schedule takes a JSON array"),
        ({"optim.n_iters": True}, "optim.n_iters takes an integer, got True"),
    ],
)
def test_bad_overrides_name_the_key_and_the_type(overrides, message):
    with pytest.raises(OverrideError) as e:
        apply_overrides(preset("fast"), overrides)
    assert message in str(e.value)


def test_train_set_end_to_end(tmp_path, capsys):
    scene = _tiny_dataset(tmp_path / "scene")
    run = tmp_path / "run"
    main(
        ["train", str(scene), "--out", str(run), "--iters", "1", "--quiet", "--set", "optim.n_iters=2"]
        + ["--set", "grid.reso_schedule=[[8,8,8],[16,16,16]]", "--set", "tonemap.enabled=true"]
        + ["--response-prior", "0.5", "--set", "tonemap.lambda_crf_loglog=0.25"]
    )
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["optim"]["n_iters"] == 2  # after the flags
    assert cfg["grid"]["reso_schedule"] == [[8, 8, 8], [16, 16, 16]]
    assert cfg["tonemap"]["enabled"] and cfg["tonemap"]["lambda_crf_loglog"] == 0.25
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["train", str(scene), "--out", str(tmp_path / "bad"), "--set", "optim.lr_sh=fast"])
    assert e.value.code == EXIT_INPUT_ERROR
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err == ["error: --set: optim.lr_sh takes a number, got 'fast'"]
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize(
    "item, problem",
    [("optim.nope=1", "unknown setting 'optim.nope'"), ("tonemap.enabled=false", "chosen by the experiment")],
)
def test_experiment_set_is_checked_before_anything_runs(item, problem, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        main(["experiment", "crf-transfer", str(out), "--set", item])
    assert e.value.code == EXIT_INPUT_ERROR
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("error: --set: ") and problem in err[0]
    assert not out.exists()


def test_experiments_and_variants_go_through_the_same_overrides():
    s = ExperimentSettings(
        iters=5, backend="torch", overrides=("optim.lr_sh=0.5", "tonemap.lambda_crf_loglog=2")
    )
    cfg = config_for(
        s, tonemap=True, known_exposure=True, tone_settings=parse_variant("lambda_crf_loglog=1e-2,leak=0")
    )
    assert (cfg.optim.n_iters, cfg.backend, cfg.optim.lr_sh) == (5, "torch", 0.5)
    assert cfg.tonemap.enabled and cfg.tonemap.known_exposure and cfg.tonemap.leak == 0.0
    assert cfg.tonemap.lambda_crf_loglog == 2.0  # the user's --set last
    assert parse_variant("defaults") == {}
    with pytest.raises(OverrideError, match="tonemap.lambda_crf_loglog takes a number"):
        parse_variant("lambda_crf_loglog=big")
    with pytest.raises(OverrideError, match="chosen by the experiment"):
        parse_variant("known_exposure=true")
    with pytest.raises(OverrideError, match="unknown setting 'tonemap.nope'"):
        config_for(s, tonemap=False, tone_settings={"nope": 1})


def test_runs_saved_under_the_old_names_still_load():
    """Keys renamed on 2026-11-26 (docs/design.md, "Names") are read from saved configs, models' render
    options and geometry."""
    import numpy as np

    from hdrplenoxels.data.placement import SceneGeometry
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.model import render_options

    saved = TrainConfig().to_dict()
    saved["render"]["background"] = saved["render"].pop("background_brightness")
    saved["render"]["background"] = 0.3
    saved["background"]["lr_density"] = saved["background"].pop("lr_sigma")
    saved["background"]["lr_density"] = 2.0
    cfg = TrainConfig.from_dict(saved)
    assert cfg.render.background_brightness == 0.3 and cfg.background.lr_sigma == 2.0
    assert render_options({"step_size": 0.5, "background": 0.25}).background_brightness == 0.25
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), wants_background=True)
    old = geometry.to_dict()
    old["background"] = old.pop("wants_background")
    assert SceneGeometry.from_dict(old).wants_background
