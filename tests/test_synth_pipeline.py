"""The simulated camera pipeline: monotonic, invertible on unclipped pixels, deterministic for a seed."""

from __future__ import annotations

import numpy as np
import pytest

from hdrplenoxels.synth.pipeline import (
    AE_METER_NOISE,
    CRFS,
    CameraSettings,
    PipelineConfig,
    add_shot_noise,
    auto_settings,
    capture,
    crf_curve,
    draw_settings,
    exposure_set,
    vignetting_factor,
)

X = np.linspace(0.0, 1.0, 2001)


@pytest.mark.parametrize("name", sorted(CRFS))
def test_response_curves_are_monotonic_with_fixed_ends_and_invert(name):
    forward, inverse = CRFS[name]
    y = forward(X)
    assert y[0] == pytest.approx(0.0, abs=1e-12) and y[-1] == pytest.approx(1.0, abs=1e-12)
    assert (np.diff(y) > 0).all()
    np.testing.assert_allclose(inverse(y), X, atol=1e-9)
    assert len(crf_curve(name)) == 256


def test_gamma3_is_the_cube_root():
    np.testing.assert_allclose(CRFS["gamma3"][0](np.array([0.125, 0.001])), [0.5, 0.1])


def test_filmic_is_an_s_curve_in_log_exposure():
    """Toe and shoulder: against log exposure, the slope peaks in the mid-tones and falls at both ends."""
    f = CRFS["filmic"][0]
    stops = np.linspace(-10, 0, 201)
    slope = np.gradient(f(2.0**stops), stops)
    peak = int(np.argmax(slope))
    assert 20 < peak < 180  # neither end is the steepest
    assert slope[0] < 0.2 * slope[peak] and slope[-1] < 0.5 * slope[peak]


def scene_radiance(seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    return (rng.uniform(0.02, 0.3, size=(h, w, 3))).astype(np.float32)


@pytest.mark.parametrize("crf", sorted(CRFS))
def test_capture_inverts_to_exposure_and_white_balance_on_unclipped_pixels(crf):
    radiance = scene_radiance()
    s = CameraSettings(ev=1.5, wb_gains=(1.0, 1.25, 1.0), crf=crf)
    ldr = capture(radiance, s).astype(np.float64) / 255.0
    linear = CRFS[crf][1](ldr)
    ok = (ldr > 0.1) & (ldr < 0.9)
    ratio = linear[ok] / radiance[ok]
    channel = np.broadcast_to(np.arange(3), ldr.shape)[ok]
    ev = [np.log2(np.median(ratio[channel == c])) for c in range(3)]
    assert ev[0] == pytest.approx(1.5, abs=0.02) and ev[2] == pytest.approx(1.5, abs=0.02)
    assert 2 ** (ev[1] - ev[0]) == pytest.approx(1.25, abs=0.01)


def test_saturation_clips_to_white():
    s = CameraSettings(ev=6.0)
    assert (capture(np.full((4, 4, 3), 0.5, np.float32), s) == 255).all()


def test_vignetting_falls_off_radially_and_is_recoverable():
    f = vignetting_factor(40, 60, -0.4, 0.1)[..., 0]
    assert f[20, 30] == pytest.approx(1.0, abs=1e-3) and f[0, 0] < f[10, 15] < f[20, 30]
    rows = (np.arange(40) + 0.5) / 40 - 0.5
    cols = (np.arange(60) + 0.5) / 60 - 0.5
    r2 = (rows[:, None] ** 2 + cols[None, :] ** 2).ravel()
    k1, k2 = np.linalg.lstsq(np.stack([r2, r2**2], 1), f.ravel() - 1, rcond=None)[0]
    assert (k1, k2) == (pytest.approx(-0.4, abs=1e-5), pytest.approx(0.1, abs=1e-4))


def test_shot_noise_is_poisson_gaussian_and_seeded():
    x = np.full((200, 200, 3), 0.25, np.float32)
    a = add_shot_noise(x, 4000.0, 3.0, np.random.default_rng(1))
    b = add_shot_noise(x, 4000.0, 3.0, np.random.default_rng(1))
    assert np.array_equal(a, b)
    assert a.mean() == pytest.approx(0.25, abs=1e-3)
    assert a.var() == pytest.approx(0.25 / 4000 + (3.0 / 4000) ** 2, rel=0.05)
    darker = add_shot_noise(x / 8, 4000.0, 3.0, np.random.default_rng(1))
    assert darker.std() / darker.mean() > 2.5 * a.std() / a.mean()  # fewer photons, relatively noisier


def test_settings_are_seeded_recorded_and_static_is_uniform():
    cfg = PipelineConfig(seed=7, crfs=("gamma3", "filmic", "srgb"), noise=True)
    views = [draw_settings(i, "varying", cfg) for i in range(50)]
    assert views == [draw_settings(i, "varying", cfg) for i in range(50)]
    assert views != [draw_settings(i, "varying", PipelineConfig(seed=8, crfs=cfg.crfs)) for i in range(50)]
    assert {v.ev for v in views} == {-3.0, 0.0, 3.0}
    assert {v.crf for v in views} == {"gamma3", "filmic", "srgb"}
    assert all(sorted(v.wb_gains) == [1.0, 1.0, 1.25] for v in views)  # one channel x 1.25 per view
    static = {repr(draw_settings(i, "static", cfg).to_dict() | {"noise": None}) for i in range(50)}
    assert len(static) == 1
    d = views[3].to_dict()
    assert set(d) >= {"ev", "wb_gains", "crf", "crf_curve", "vignetting", "noise"}
    assert len(d["crf_curve"]) == 256
    radiance = scene_radiance(3)
    assert np.array_equal(capture(radiance, views[3]), capture(radiance, views[3]))


def test_exposure_sets():
    assert exposure_set(3) == (-3.0, 0.0, 3.0)
    assert exposure_set(6) == (-6.0, -3.0, 0.0, 3.0, 6.0)
    assert exposure_set(4) == (-4.0, -2.0, 0.0, 2.0, 4.0)


def test_auto_settings_meter_the_scene_as_a_phone_would():
    """Auto exposure brings the centre-weighted mean luminance to 18 % grey (up to the meter's noise), a
    4x brighter scene gets 2 stops less; white balance removes most of a colour cast, green's gain is 1;
    the draw is seeded."""
    rng = np.random.default_rng(5)
    scene = rng.uniform(0.5, 1.5, (30, 40, 3)).astype(np.float32) * np.array([2.0, 1.0, 0.5], np.float32)
    cfg = PipelineConfig()
    s = auto_settings(3, scene, cfg)
    assert s == auto_settings(3, scene, cfg)  # seeded by view
    bright = auto_settings(3, 4.0 * scene, cfg)
    assert bright.ev == pytest.approx(s.ev - 2.0, abs=1e-6)  # same noise draw, 2 stops less
    lum = (scene.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])).mean()
    assert abs(s.ev - np.log2(0.18 / lum)) < 4 * AE_METER_NOISE + 0.05  # centre weighting ~ flat here
    assert s.wb_gains[1] == pytest.approx(1.0)
    balanced = scene.reshape(-1, 3).mean(0) * np.asarray(s.wb_gains)
    cast_before = np.log2(scene.reshape(-1, 3).mean(0)).std()
    assert np.log2(balanced).std() < 0.35 * cast_before  # 80 % of the cast removed, bias and noise aside
    evs = {round(auto_settings(v, scene, cfg).ev, 6) for v in range(8)}
    assert len(evs) == 8  # the meter's noise differs per view


def test_the_auto_variant_is_captured_from_the_truth_by_metering(tmp_path):
    """`capture_dataset(..., "auto")` (what `synth --camera auto` adds): a view 4x brighter than another
    gets 2 stops less exposure, and both come out about equally bright, as auto exposure does."""
    import json

    from hdrplenoxels.data.image_io import read_image, write_exr
    from hdrplenoxels.synth.generate import capture_dataset

    rng = np.random.default_rng(2)
    base = rng.uniform(0.2, 0.6, (16, 20, 3)).astype(np.float32)
    frames = []
    for k, scale in enumerate((1.0, 4.0)):
        write_exr(tmp_path / "hdr" / f"view_{k:03d}.exr", base * scale)
        frames.append({"file_path": f"images/view_{k:03d}.png", "transform_matrix": np.eye(4).tolist()})
    (tmp_path / "hdr" / "transforms.json").write_text(json.dumps({"frames": frames}))
    capture_dataset(tmp_path, tmp_path / "auto", "auto", PipelineConfig())
    truth = json.loads((tmp_path / "auto" / "camera_truth.json").read_text())
    assert truth["variant"] == "auto"
    evs = [v["ev"] for v in truth["views"]]
    noise = [
        auto_settings(k, base, PipelineConfig()).ev - auto_settings(0, base, PipelineConfig()).ev
        for k in (0, 1)
    ]
    assert evs[0] - evs[1] == pytest.approx(2.0 - noise[1], abs=1e-5)
    means = [read_image(tmp_path / "auto" / "images" / f"view_{k:03d}.png").mean() for k in (0, 1)]
    assert abs(means[0] - means[1]) < 0.1 * means[0]
