"""Mitsuba truth: our camera model lands where Mitsuba renders, and `synth` writes a consistent dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.image_io import read_exr, read_image
from hdrplenoxels.eval.metrics import PSNR_CAP
from hdrplenoxels.experiments.common import captured, right_half
from hdrplenoxels.experiments.median import median_camera, median_targets
from hdrplenoxels.experiments.robustness import noise_floor_psnr
from hdrplenoxels.geometry.cameras import Cameras, opengl_to_opencv
from hdrplenoxels.geometry.rigs import look_at
from hdrplenoxels.synth.generate import SynthOptions, capture_dataset, synthesize
from hdrplenoxels.synth.mitsuba_render import load_scene_dict, render_view
from hdrplenoxels.synth.pipeline import (
    CRFS,
    SEED_RENDER,
    CameraSettings,
    PipelineConfig,
    capture,
    view_seed,
    vignetting_factor,
)
from hdrplenoxels.synth.scenes import SCENES, transform


def project(c2w: np.ndarray, intr: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Our pinhole model: continuous pixel coordinates (pixel centres at +0.5)."""
    x = np.linalg.inv(c2w) @ np.append(point, 1.0)
    return np.array([intr[0] * x[0] / x[2] + intr[2], intr[1] * x[1] / x[2] + intr[3]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projected_point_lands_on_mitsubas_emissive_sphere(seed):
    rng = np.random.default_rng(seed)
    width, height = 96, 64  # non-square
    intr = np.array([80.0, 80.0, 45.3 + 4 * rng.uniform(), 35.9 - 4 * rng.uniform()])  # off-centre
    c2w = look_at(rng.normal(0, 0.3, 3) + np.array([0.0, 0.0, -2.5]), rng.normal(0, 0.1, 3))
    c2w[:3, :3] = c2w[:3, :3] @ transform(rotate_deg=(0, 0, rng.uniform(-40, 40)))[:3, :3]  # roll
    # Off-axis points (towards the image corners), where a focal or principal-point error shows most.
    cam_points = [np.array([x * 0.8, y * 0.6, 2.5]) for x, y in [(-1, -1), (1, 0.7), (0.6, -0.9)]]
    points = [(c2w @ np.append(p, 1.0))[:3] for p in cam_points]
    dots = {
        f"dot{k}": {
            "type": "sphere",
            "center": p.tolist(),
            "radius": 0.03,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 5.0, 5.0]}},
        }
        for k, p in enumerate(points)
    }
    scene = load_scene_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2}, **dots})
    img = render_view(scene, Cameras(c2w[None], intr[None], [[width, height]]), 0, spp=64).sum(-1)
    rows, cols = np.mgrid[0:height, 0:width]
    for p in points:
        u, v = project(c2w, intr, p)
        near = (np.abs(cols + 0.5 - u) < 5) & (np.abs(rows + 0.5 - v) < 5)  # this dot's neighbourhood
        lum = np.where(near, img, 0.0)
        centroid = np.array([(lum * (cols + 0.5)).sum(), (lum * (rows + 0.5)).sum()]) / lum.sum()
        assert np.linalg.norm(centroid - (u, v)) <= 0.25  # a half-pixel convention slip is 0.7


@pytest.fixture(scope="module")
def tiny_synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    pipeline = PipelineConfig(seed=3, crfs=("gamma3", "filmic"), vignetting=(-0.3, 0.0))
    summary = synthesize("room", out, SynthOptions(n_views=16, width=32, height=24, spp=4), pipeline)
    return out, summary, pipeline


def test_synth_writes_the_documented_layout(tiny_synth):
    out, summary, _ = tiny_synth
    assert len(list((out / "hdr").glob("*.exr"))) == 16
    assert summary["resolution"] == [32, 24] and summary["test_views"] == [0, 8]
    assert summary["dynamic_range_stops"] > 3
    assert set(summary["saturated_fraction_by_ev"]) == {"-3", "+0", "+3"}
    for variant in ("varying", "static"):
        folder = out / variant
        scene = load_scene(folder)
        assert len(scene.images) == 16 and scene.test_ids == [0, 8] and scene.forward_facing
        assert scene.near_far[0] > 0 and scene.near_far[1] > scene.near_far[0]
        truth = json.loads((folder / "camera_truth.json").read_text())
        assert len(truth["views"]) == 16 and len(truth["views"][0]["crf_curve"]) == 256
        assert (folder / "poses_bounds.npy").exists()


def test_recapture_reproduces_the_datasets_and_applies_new_settings(tiny_synth, tmp_path):
    """Experiments render the truth once and capture it again with other cameras."""
    out, _, pipeline = tiny_synth
    again = tmp_path / "again"
    capture_dataset(out, again, "varying", pipeline)
    for name in ("view_003", "view_008"):
        assert np.array_equal(
            read_image(again / f"images/{name}.png"), read_image(out / f"varying/images/{name}.png")
        )
    wide = tmp_path / "wide"
    capture_dataset(out, wide, "varying", PipelineConfig(ev_set=(-6.0, 6.0), seed=3))
    views = json.loads((wide / "camera_truth.json").read_text())["views"]
    assert {v["ev"] for v in views} == {-6.0, 6.0}
    assert read_exr(wide / views[0]["hdr"]).shape == (24, 32, 3)  # the truth path resolves from the dataset
    assert load_scene(wide).forward_facing and (wide / "poses_bounds.npy").exists()


def test_median_camera_captures_are_the_median_experiments_targets(tiny_synth):
    """The median experiment's ceiling trains on every view captured with the scored median camera:
    0 EV, one white balance for all views, and test images identical to the targets."""
    out, _, pipeline = tiny_synth
    views = json.loads((out / "varying" / "camera_truth.json").read_text())["views"]
    cameras = [median_camera(views, i) for i in range(len(views))]
    folder = captured(out, "median_test", "median_camera", pipeline, cameras.__getitem__)
    recorded = json.loads((folder / "camera_truth.json").read_text())["views"]
    assert {v["ev"] for v in recorded} == {0.0}
    assert len({tuple(v["wb_gains"]) for v in recorded}) == 1 and recorded[0]["wb_gains"] != [1.0, 1.0, 1.0]
    assert [v["crf"] for v in recorded] == [v["crf"] for v in views]  # each view keeps its own response
    _, _, targets = median_targets(out, views, [0, 8])
    for i, target in zip((0, 8), targets):
        assert np.array_equal(read_image(folder / f"images/view_{i:03d}.png"), np.round(target * 255))
    # Kept while the pipeline matches: a second call does not capture again.
    stamp = (folder / "camera_truth.json").stat().st_mtime_ns
    captured(out, "median_test", "median_camera", pipeline, cameras.__getitem__)
    assert (folder / "camera_truth.json").stat().st_mtime_ns == stamp


def test_recorded_settings_invert_the_images_back_to_the_truth(tiny_synth):
    """Undo the recorded response, white balance, vignetting and exposure: the HDR truth comes back."""
    out, _, _ = tiny_synth
    for variant in ("varying", "static"):
        truth = json.loads((out / variant / "camera_truth.json").read_text())
        for view in truth["views"][:6]:
            ldr = read_image(out / variant / view["file"]).astype(np.float64) / 255.0
            hdr = read_exr((out / variant / view["hdr"]).resolve())
            inverse = CRFS[view["crf"]][1]
            gain = (
                2.0 ** view["ev"]
                * np.asarray(view["wb_gains"])
                * vignetting_factor(24, 32, *view["vignetting"])
            )
            ok = (ldr > 0.2) & (ldr < 0.9)
            recovered = inverse(ldr)[ok] / gain[ok]
            assert np.median(np.abs(recovered / hdr[ok] - 1.0)) < 0.02
    varying = json.loads((out / "varying" / "camera_truth.json").read_text())["views"]
    static = json.loads((out / "static" / "camera_truth.json").read_text())["views"]
    assert len({v["ev"] for v in varying}) > 1 and {v["ev"] for v in static} == {0.0}
    assert all(sorted(v["wb_gains"]) == [1.0, 1.0, 1.25] for v in varying)


def test_noise_settings_are_recorded_and_reproduce_the_image(tmp_path):
    pipeline = PipelineConfig(seed=5, noise=True)
    synthesize("objects360", tmp_path, SynthOptions(n_views=8, width=24, height=24, spp=4), pipeline)
    view = json.loads((tmp_path / "varying" / "camera_truth.json").read_text())["views"][1]
    hdr = read_exr(tmp_path / "hdr" / "view_001.exr")
    settings = CameraSettings(
        view["ev"], tuple(view["wb_gains"]), view["crf"], tuple(view["vignetting"]), None
    )
    image = read_image(tmp_path / "varying" / view["file"])
    assert not np.array_equal(image, capture(hdr, settings))  # the noise is really there
    settings.noise = view["noise"]
    assert np.array_equal(image, capture(hdr, settings))  # and the record is enough to reproduce it


def test_test_views_render_with_their_own_sample_count(tmp_path):
    """`test_spp` renders every 8th view (the scored ones) with more samples, the others as before."""
    synthesize("objects360", tmp_path, SynthOptions(n_views=9, width=16, height=16, spp=1, test_spp=16))
    assert json.loads((tmp_path / "synth.json").read_text())["test_spp"] == 16
    rig = SCENES["objects360"].build(9, 16, 16)
    scene = load_scene_dict(rig.scene)
    for i, spp in [(0, 16), (1, 1), (8, 16)]:
        written = read_exr(tmp_path / "hdr" / f"view_{i:03d}.exr")
        seed = view_seed(0, SEED_RENDER, i)
        np.testing.assert_allclose(written, render_view(scene, rig.cameras, i, spp, seed=seed), atol=1e-4)
        other = 1 if spp == 16 else 16
        assert np.abs(written - render_view(scene, rig.cameras, i, other, seed=seed)).max() > 1e-3


def test_scene_exposure_properties():
    """The room's window clips at 0 EV but not at -3 EV; the extreme scene spans more than 12 stops."""
    from hdrplenoxels.synth.generate import dynamic_range_stops, saturation_by_ev

    def renders(name):
        rig = SCENES[name].build(3, 40, 30)
        scene = load_scene_dict(rig.scene)
        return [render_view(scene, rig.cameras, i, 16) for i in range(3)]

    room = saturation_by_ev(renders("room"), (-3.0, 0.0))
    assert room["+0"] > 0.02 and room["-3"] == 0.0
    assert dynamic_range_stops(renders("extreme")) > 12.0


def test_llff_poses_bounds_match_the_transforms(tiny_synth):
    out, _, _ = tiny_synth
    arr = np.load(out / "static" / "poses_bounds.npy")
    assert arr.shape == (16, 17)
    meta = json.loads((out / "static" / "transforms.json").read_text())
    for i, frame in enumerate(meta["frames"]):
        c2w = opengl_to_opencv(np.asarray(frame["transform_matrix"]))
        mat = arr[i, :15].reshape(3, 5)
        down, right, back = mat[:, 0], mat[:, 1], mat[:, 2]
        np.testing.assert_allclose(np.stack([right, down, -back], 1), c2w[:3, :3], atol=1e-9)
        np.testing.assert_allclose(mat[:, 3], c2w[:3, 3], atol=1e-9)
        assert mat[:, 4].tolist() == [24, 32, pytest.approx(meta["fl_x"])]
        assert 0 < arr[i, 15] < arr[i, 16]


def test_every_scene_builds_with_its_rig():
    for name, spec in SCENES.items():
        rig = spec.build(8, 16, 12)
        assert len(rig.cameras) == 8 and (rig.aabb is None) == rig.forward_facing, name
        load_scene_dict(rig.scene)


def test_cli_lists_scenes_and_synthesises(tmp_path, capsys):
    from hdrplenoxels.cli.main import main

    main(["synth", "--list"])
    assert capsys.readouterr().out.split() == list(SCENES)
    main(["synth", "objects360", str(tmp_path), "--views", "8", "--resolution", "16x16", "--spp", "2"])
    summary = json.loads((tmp_path / "synth.json").read_text())
    assert summary["scene"] == "objects360" and summary["resolution"] == [16, 16]
    meta = json.loads((tmp_path / "varying" / "transforms.json").read_text())
    assert meta["aabb"] == [[-1.0] * 3, [1.0] * 3]
    # The sky is hidden from camera rays: a black background, which the grid renders as background 0.
    scene = load_scene(tmp_path / "varying")
    assert scene.background_brightness == 0.0 and all((img[0, 0] == 0).all() for img in scene.images)
    for bad in (["no-such-scene", str(tmp_path / "x")], ["objects360", str(tmp_path)]):  # unknown; OUT taken
        with pytest.raises(SystemExit) as exit_info:
            main(["synth", *bad])
        assert exit_info.value.code == 2
    main(
        [
            "synth",
            "objects360",
            str(tmp_path),
            "--views",
            "8",
            "--resolution",
            "8x8",
            "--spp",
            "1",
            "--overwrite",
        ]
    )
    assert json.loads((tmp_path / "synth.json").read_text())["resolution"] == [8, 8]


def test_noise_floor_is_the_noisy_captures_psnr_against_the_clean_ones(tiny_synth, tmp_path):
    """The robustness report's ceiling for scores against noisy captures: noisy vs clean test captures."""
    out, _, _ = tiny_synth
    clean, noisy = tmp_path / "clean", tmp_path / "noisy"
    capture_dataset(out, clean, "varying", PipelineConfig(seed=3))
    capture_dataset(out, noisy, "varying", PipelineConfig(seed=3, noise=True, full_well=200.0))
    floor = noise_floor_psnr(noisy, clean)
    a, b = load_scene(noisy), load_scene(clean)
    expected = [
        -10 * np.log10(np.mean((right_half(a.images[i] / 255.0) - right_half(b.images[i] / 255.0)) ** 2))
        for i in b.test_ids
    ]
    assert floor == pytest.approx(np.mean(expected), abs=1e-3)
    assert 10.0 < floor < 45.0  # a 200-electron well is visibly noisy
    assert noise_floor_psnr(clean, clean) == PSNR_CAP


def test_courtyard_is_open_with_the_brightest_radiance_in_its_visible_sky(tmp_path):
    """The unbounded scene: only the objects lie in the box; the sky beyond it (radiance > 1, the sun's
    disk far above) fills the top of most views; transforms.json says content reaches beyond the box."""
    from hdrplenoxels.synth.generate import depth_scene, luminance

    summary = synthesize("courtyard", tmp_path, SynthOptions(n_views=8, width=32, height=24, spp=4))
    meta = json.loads((tmp_path / "varying" / "transforms.json").read_text())
    assert meta["aabb"] == [[-1.2, -1.1, -1.2], [1.2, 0.9, 1.2]] and meta["aabb_scale"] >= 16
    assert "background" not in meta  # the sky is seen, not a constant
    scene = load_scene(tmp_path / "static")
    assert scene.scene_box == ((-1.2, -1.1, -1.2), (1.2, 0.9, 1.2)) and "beyond" in scene.bounds_notes
    assert summary["beyond_box_fraction"] > 0.5
    rig = SCENES["courtyard"].build(8, 32, 24)
    depth = depth_scene(rig)
    bright_sky_views, sky_peak = 0, 0.0
    for i in range(8):
        lum = luminance(read_exr(tmp_path / "hdr" / f"view_{i:03d}.exr"))
        sky = render_view(depth, rig.cameras, i, 4)[..., 0] == 0.0  # rays that hit nothing
        bright_sky_views += int((sky & (lum > 1.0)).mean() > 0.05)
        sky_peak = max(sky_peak, float(lum[sky].max()))
    assert bright_sky_views >= 6
    # The sun's disk, seen in some view, is the brightest radiance in the scene.
    assert sky_peak > 100.0 and sky_peak == pytest.approx(summary["radiance_percentiles"]["max"], rel=1e-3)
