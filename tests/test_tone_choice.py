"""Tone mapping by default where the camera's settings vary, and not for one fixed camera: measured from the
photos (EXIF exposures, overlapping views' pixels), said in one line, overruled by the flags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hdrplenoxels.cli.main import main
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.camera_spread import camera_spread
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.train.tone_choice import EXPOSURE_STOPS, WHITE_BALANCE_STOPS, choose_tone_mapping


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    """16 views of the textured SfM room: one fixed camera (static/) and a -3/0/+3 EV bracket with a
    white-balance gain (varying/)."""
    out = tmp_path_factory.mktemp("gallery")
    synthesize("gallery", out, SynthOptions(n_views=16, width=160, height=120))
    return out


def test_a_fixed_camera_measures_no_spread_and_a_bracket_a_wide_one(gallery):
    static, varying = load_scene(gallery / "static"), load_scene(gallery / "varying")
    fixed = camera_spread(static, list(static.train_ids))
    bracket = camera_spread(varying, list(varying.train_ids))
    assert fixed.exif_stops is None and fixed.pairs >= 8 and fixed.pairs >= 0.75 * fixed.compared
    assert fixed.exposure_stops < EXPOSURE_STOPS / 4 and fixed.white_balance_stops < WHITE_BALANCE_STOPS / 2
    # the bracket's +3 EV views clip and its -3 EV views go dark: few pairs compare, and they do not link
    # half the views into one scale
    assert bracket.pairs < 0.5 * bracket.compared and bracket.exposure_stops is None
    assert choose_tone_mapping(static, list(static.train_ids))[:2] == (
        False,
        f"one fixed camera: overlapping views differ by {fixed.exposure_stops:.2f} stops in exposure and "
        f"{fixed.white_balance_stops:.2f} in white balance",
    )
    on, why, _ = choose_tone_mapping(varying, list(varying.train_ids))
    assert on and why == "too few views overlap to tell whether the camera's settings varied"


def test_an_object_on_black_measures_its_fixed_camera_from_few_matches(tmp_path):
    """objects360 at 128 px: SIFT finds few points on the object and none on the black, so a pair of
    views shares 10-20 matched points; with a pair needing 15 its fixed camera could not be told
    (the tone mapper ran and cost 0.39 dB at `balanced`), with 10 it is. Its bracket never reads as fixed."""
    synthesize("objects360", tmp_path, SynthOptions(n_views=24, width=128, height=128, spp=16))
    static, varying = load_scene(tmp_path / "static"), load_scene(tmp_path / "varying")
    on, why, spread = choose_tone_mapping(static, list(static.train_ids))
    assert not on and why.startswith("one fixed camera") and spread.pairs >= 0.5 * spread.compared
    assert choose_tone_mapping(varying, list(varying.train_ids))[0] is True


def test_exif_exposures_that_differ_decide_alone_and_missing_overlap_turns_it_on(gallery):
    """EXIF showing the exposure change decides without the pixels; a capture whose views cannot be
    compared gets the tone mapper (wrongly off, it costs 15 dB on a bracket; wrongly on, 1.6 at most)."""
    static = load_scene(gallery / "static")
    views = list(static.train_ids)
    static.extras["exposure_init_ev"] = [0.0 if i % 2 else 1.0 for i in range(len(static.names))]
    assert choose_tone_mapping(static, views)[:2] == (True, "the photos' EXIF exposures span 1.00 stops")
    static.extras["exposure_init_ev"] = [0.1] * len(static.names)  # EXIF says fixed: the pixels decide
    assert choose_tone_mapping(static, views)[0] is False
    flat = load_scene(gallery / "static")
    flat.images = [np.full_like(im, 128) for im in flat.images]  # nothing to match: cannot tell
    on, why, spread = choose_tone_mapping(flat, views)
    assert on and "too few views overlap" in why and spread.exposure_stops is None


def test_train_says_whether_it_learns_a_tone_per_photo_and_why(gallery, tmp_path, capsys):
    common = ["--preset", "fast", "--iters", "5", "--quiet"]
    main(["train", str(gallery / "static"), "--out", str(tmp_path / "a"), *common])
    out = capsys.readouterr().out
    assert "tone mapping: off (one fixed camera: " in out and "; --tonemap learns a tone per photo" in out
    assert not (tmp_path / "a" / "tone_params.json").exists()
    main(["train", str(gallery / "varying"), "--out", str(tmp_path / "b"), *common])
    out = capsys.readouterr().out
    assert "tone mapping: on (too few views overlap to tell" in out and "--no-tonemap trains plain" in out
    assert (tmp_path / "b" / "tone_params.json").exists()
    main(["train", str(gallery / "varying"), "--out", str(tmp_path / "c"), "--no-tonemap", *common])
    assert "tone mapping: off (tonemap.enabled, --tonemap / --no-tonemap)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("exposure", "balance", "on"),
    [(0.3, 0.02, True), (0.1, 0.02, False), (0.1, 0.08, True), (EXPOSURE_STOPS, WHITE_BALANCE_STOPS, False)],
)
def test_either_spread_past_its_threshold_turns_the_tone_mapper_on(monkeypatch, exposure, balance, on):
    from hdrplenoxels.data.camera_spread import CameraSpread
    from hdrplenoxels.train import tone_choice

    monkeypatch.setattr(
        tone_choice,
        "camera_spread",
        lambda scene, views, pixels=True: CameraSpread(None, exposure, balance, 9, 9),
    )
    chosen, why, _ = tone_choice.choose_tone_mapping(None, [])
    assert chosen is on and f"{exposure:.2f} stops in exposure and {balance:.2f} in white balance" in why
