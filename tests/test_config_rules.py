"""The rules between settings live in `TrainConfig.check`, which the trainer calls once before anything
is written: the library API refuses what the command line refuses (docs/usage.md)."""

from __future__ import annotations

import pytest

from hdrplenoxels.core.settings import flatten
from hdrplenoxels.train.config import (
    CASCADE_DISTORTION,
    TV_SCALE_MAX,
    ConfigError,
    TrainConfig,
    apply_overrides,
    tv_scale,
)
from hdrplenoxels.train.presets import TV_PHOTOS, preset

TONE_SWITCHES = {
    "tonemap.known_exposure": True,
    "tonemap.exposure_init_from_metadata": True,
    "tonemap.lambda_crf_loglog": 0.01,
}


@pytest.mark.parametrize(("key", "value"), list(TONE_SWITCHES.items()))
def test_a_tone_mapping_switch_needs_the_tone_mapper(key, value):
    off = apply_overrides(preset("fast"), {"tonemap.enabled": False, key: value})
    with pytest.raises(ConfigError, match=key.replace(".", r"\.") + ".*needs the tone mapper"):
        off.check("bbox")
    assert apply_overrides(off, {"tonemap.enabled": True}).check("bbox") == []


def test_every_tone_switch_at_once_is_named():
    cfg = apply_overrides(preset("fast"), {"tonemap.enabled": False, **TONE_SWITCHES})
    with pytest.raises(ConfigError) as refused:
        cfg.check("bbox")
    assert all(key in str(refused.value) for key in TONE_SWITCHES) and " need the " in str(refused.value)


@pytest.mark.parametrize(
    ("settings", "mode", "refused"),
    [
        ({"nerf.appearance": True}, "bbox", "nerf.appearance"),
        ({"model": "nerf", "background.enabled": True}, "bbox", "a NeRF has no MSI"),
        ({"background.enabled": True}, "ndc", "NDC"),
    ],
)
def test_settings_no_run_can_train_are_refused(settings, mode, refused):
    with pytest.raises(ConfigError, match=refused):
        apply_overrides(TrainConfig(), settings).check(mode)


@pytest.mark.parametrize(
    ("enabled", "mode", "note"),
    [
        (True, "bbox", "all the same"),
        (False, "cascade", "no background model"),
        (None, "cascade", None),
    ],
)
def test_a_setting_that_overrules_the_scene_mode_is_said(enabled, mode, note):
    notes = apply_overrides(TrainConfig(), {"background.enabled": enabled}).check(mode)
    assert (notes == []) if note is None else (len(notes) == 1 and note in notes[0])


def test_the_trainer_refuses_before_writing_anything(tmp_path):
    from test_train import TINY

    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import write_procedural_scene
    from hdrplenoxels.train.trainer import Trainer

    scene = load_scene(write_procedural_scene(tmp_path / "scene", TINY))
    cfg = apply_overrides(preset("fast"), {"tonemap.enabled": False, "tonemap.known_exposure": True})
    with pytest.raises(ConfigError, match="known_exposure"):
        Trainer(scene, cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_one_flag_table_maps_options_to_real_config_keys():
    from hdrplenoxels.train.config import FLAG_KEYS, flag_settings, setting_types

    assert set(FLAG_KEYS.values()) <= set(setting_types())
    assert flag_settings({"iters": 7, "tonemap": None, "device": "cpu"}) == {
        "optim.n_iters": 7,
        "device": "cpu",
    }
    with pytest.raises(KeyError, match="lr"):
        flag_settings({"lr": 1.0})


def test_a_flag_that_sets_a_number_takes_its_limit_from_the_config(capsys):
    from hdrplenoxels.cli.common import setting_option
    from hdrplenoxels.cli.main import main
    from hdrplenoxels.core.settings import fields_of

    option = setting_option("--batch-size", "rays")(lambda **_: None).__click_params__[0]
    assert option.type.min == fields_of(TrainConfig)["optim.batch_size"][1].metadata["at_least"] == 1
    with pytest.raises(TypeError, match="--tonemap"):
        setting_option("--tonemap", "a switch")
    with pytest.raises(SystemExit) as refused:
        main(["train", "anywhere", "--batch-size", "0"])
    assert refused.value.code == 2 and "--batch-size" in capsys.readouterr().err


def test_every_numeric_setting_declares_its_limits():
    """Each int or float key carries its range beside it (`core.settings.setting`), so a bad value is
    refused when it is set, not deep in a run; bools, names and choices are bounded by their types."""
    import dataclasses
    import typing

    from hdrplenoxels.core import settings

    bare = []
    for key, (hint, field) in settings.fields_of(TrainConfig).items():
        kinds = set(typing.get_args(hint)) - {type(None)} or {hint}
        if dataclasses.is_dataclass(hint) or not kinds & {int, float}:
            continue
        limits = field.metadata or {}
        if all(limits.get(k) is None for k in ("at_least", "below", "check")):
            bare.append(key)
    assert not bare, f"settings without limits: {bare}"


@pytest.mark.parametrize(
    ("key", "value"),
    [("optim.rms_beta", 1.0), ("optim.tv_sparsity", 1.5), ("tonemap.knot_power", 0.0), ("nerf.width", 0)],
)
def test_a_value_outside_its_limits_is_refused_when_set(key, value):
    from hdrplenoxels.core.settings import OverrideError

    with pytest.raises(OverrideError, match=key.split(".")[-1]):
        apply_overrides(TrainConfig(), {key: value})


def test_every_none_default_is_resolved_in_one_place():
    """The None defaults are exactly `TrainConfig.RESOLVED`, and `resolved` fills each from the capture
    or another key, keeps the values a user set, and leaves the config it was given as it was."""
    cfg = TrainConfig()
    assert {k for k, v in flatten(cfg.to_dict()).items() if v is None} == set(TrainConfig.RESOLVED)
    assert cfg.unresolved() == list(TrainConfig.RESOLVED)
    cascade = cfg.resolved(background_brightness=0.8, wants_background=True, levels=3)
    assert cascade.unresolved() == [] and cfg.unresolved() == list(TrainConfig.RESOLVED)
    assert cascade.render.background_brightness == 0.8 and cascade.background.enabled is True
    assert cascade.background.lr_decay_steps == cfg.optim.lr_decay_steps
    assert cascade.optim.lambda_distortion == CASCADE_DISTORTION
    assert (
        cfg.resolved(background_brightness=0.5, wants_background=False, levels=1).optim.lambda_distortion == 0
    )
    mine = {"render.background_brightness": 0.1, "background.enabled": False, "optim.lambda_distortion": 0.2}
    kept = apply_overrides(TrainConfig(), mine).resolved(
        background_brightness=0.8, wants_background=True, levels=3
    )
    assert flatten(kept.to_dict()).items() >= mine.items()


def test_the_grid_tv_grows_as_the_photos_get_fewer():
    """`optim.tv_photos` multiplies both TV weights by (tv_photos / photos)^2, never below 1 nor above
    `TV_SCALE_MAX`; `resolved` applies it once (a second `resolved` changes nothing); 0 leaves them."""
    assert tv_scale(90.0, 45) == pytest.approx(4.0)
    assert tv_scale(90.0, 9) == TV_SCALE_MAX and tv_scale(90.0, 3) == TV_SCALE_MAX
    assert tv_scale(90.0, 200) == 1.0 and tv_scale(0.0, 5) == 1.0
    cfg = apply_overrides(
        TrainConfig(), {"optim.tv_photos": 90.0, "optim.lambda_tv_sigma": 1e-5, "optim.lambda_tv_sh": 1e-4}
    )
    place = {"background_brightness": 0.5, "wants_background": False, "levels": 1}
    few = cfg.resolved(**place, photos=45)
    assert few.optim.lambda_tv_sigma == pytest.approx(4e-5) and few.optim.lambda_tv_sh == pytest.approx(4e-4)
    assert few.resolved(**place, photos=45).optim.lambda_tv_sigma == pytest.approx(4e-5)
    assert cfg.optim.tv_photos == 90.0 and cfg.optim.lambda_tv_sigma == 1e-5  # the given config unchanged
    off = apply_overrides(cfg, {"optim.tv_photos": 0.0}).resolved(**place, photos=9)
    assert off.optim.lambda_tv_sigma == 1e-5 and off.optim.lambda_tv_sh == 1e-4


@pytest.mark.parametrize("name", ["fast", "balanced", "nerf-fast", "nerf-cpu"])
def test_the_cpu_grid_presets_smooth_few_photos_more_and_the_nerf_ones_have_no_grid_tv(name):
    """Both CPU grid presets resolve 9 photos to `TV_SCALE_MAX` times their TV and 200 to 1x; the NeRF
    presets (built on `fast`) keep their weights, so a NeRF run's notes claim no grid TV."""
    cfg = preset(name)
    place = {"background_brightness": 0.5, "wants_background": False, "levels": 1}
    few, many = cfg.resolved(**place, photos=9), cfg.resolved(**place, photos=200)
    assert many.optim.lambda_tv_sigma == cfg.optim.lambda_tv_sigma
    expected = TV_SCALE_MAX if cfg.model == "grid" else 1.0
    assert cfg.optim.tv_photos == (TV_PHOTOS if cfg.model == "grid" else 0.0)
    assert few.optim.lambda_tv_sigma == pytest.approx(expected * cfg.optim.lambda_tv_sigma)
    assert few.optim.lambda_tv_sh == pytest.approx(expected * cfg.optim.lambda_tv_sh)


def test_a_grid_engine_refuses_an_unresolved_config():
    from hdrplenoxels.grid.sparse_grid import SparseGrid
    from hdrplenoxels.render import RenderOptions
    from hdrplenoxels.train.engines.torch_grid import TorchGridEngine

    grid = SparseGrid.create((4, 4, 4), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1)
    with pytest.raises(
        ValueError, match="still None: tonemap.enabled, render.background_brightness, background.enabled"
    ):
        TorchGridEngine(grid, TrainConfig(), RenderOptions())
    settings = TrainConfig().resolved(background_brightness=0.5, wants_background=False, levels=1)
    assert TorchGridEngine(grid, settings, RenderOptions()).distortion_weight == 0.0
