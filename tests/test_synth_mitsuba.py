"""Mitsuba truth: our camera model lands where Mitsuba renders, and `synth` writes a consistent dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrplenoxels.cameras import Cameras, opengl_to_opencv
from hdrplenoxels.data import load_scene
from hdrplenoxels.image_io import read_exr, read_image
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.synth.mitsuba_render import load_scene_dict, render_view
from hdrplenoxels.synth.pipeline import CameraSettings, PipelineConfig, capture
from hdrplenoxels.synth.scenes import SCENES, look_at, transform


def project(c2w: np.ndarray, intr: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Our pinhole model: continuous pixel coordinates (pixel centres at +0.5)."""
    x = np.linalg.inv(c2w) @ np.append(point, 1.0)
    return np.array([intr[0] * x[0] / x[2] + intr[2], intr[1] * x[1] / x[2] + intr[3]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projected_point_lands_on_mitsubas_emissive_sphere(seed):
    rng = np.random.default_rng(seed)
    point = rng.uniform(-0.5, 0.5, 3)
    width, height = 96, 64  # non-square
    intr = np.array([80.0, 80.0, 45.3 + 4 * rng.uniform(), 35.9 - 4 * rng.uniform()])  # off-centre
    eye = point + rng.normal(0, 1, 3) * 0.2 + np.array([0.0, 0.0, -2.5])
    c2w = look_at(eye, point + rng.normal(0, 0.1, 3))
    c2w[:3, :3] = c2w[:3, :3] @ transform(rotate_deg=(0, 0, rng.uniform(-40, 40)))[:3, :3]  # roll
    scene = load_scene_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 2},
            "dot": {
                "type": "sphere",
                "center": point.tolist(),
                "radius": 0.02,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5.0, 5.0, 5.0]}},
            },
        }
    )
    img = render_view(scene, Cameras(c2w[None], intr[None], [[width, height]]), 0, spp=64)
    lum = img.sum(-1)
    rows, cols = np.mgrid[0:height, 0:width]
    centroid = np.array([(lum * (cols + 0.5)).sum(), (lum * (rows + 0.5)).sum()]) / lum.sum()
    assert np.linalg.norm(centroid - project(c2w, intr, point)) <= 0.5


@pytest.fixture(scope="module")
def tiny_synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    pipeline = PipelineConfig(seed=3, crfs=("gamma3", "filmic"))
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


def test_ldr_images_are_the_recorded_pipeline_applied_to_the_truth(tiny_synth):
    out, _, _ = tiny_synth
    for variant in ("varying", "static"):
        truth = json.loads((out / variant / "camera_truth.json").read_text())
        for view in truth["views"][:4]:
            settings = CameraSettings(
                view["ev"], tuple(view["wb_gains"]), view["crf"], tuple(view["vignetting"]), view["noise"]
            )
            hdr = read_exr((out / variant / view["hdr"]).resolve())
            assert np.array_equal(read_image(out / variant / view["file"]), capture(hdr, settings))
    varying = json.loads((out / "varying" / "camera_truth.json").read_text())["views"]
    static = json.loads((out / "static" / "camera_truth.json").read_text())["views"]
    assert len({v["ev"] for v in varying}) > 1 and {v["ev"] for v in static} == {0.0}


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
    from hdrplenoxels.cli import main

    main(["synth", "--list"])
    assert capsys.readouterr().out.split() == list(SCENES)
    main(["synth", "objects360", str(tmp_path), "--views", "8", "--resolution", "16x16", "--spp", "2"])
    summary = json.loads((tmp_path / "synth.json").read_text())
    assert summary["scene"] == "objects360" and summary["resolution"] == [16, 16]
    meta = json.loads((tmp_path / "varying" / "transforms.json").read_text())
    assert meta["aabb"] == [[-1.0] * 3, [1.0] * 3]
    # The sky is hidden from camera rays: a black background, which the grid renders as background 0.
    scene = load_scene(tmp_path / "varying")
    assert scene.background == 0.0 and all((img[0, 0] == 0).all() for img in scene.images)
    with pytest.raises(SystemExit) as exit_info:
        main(["synth", "no-such-scene", str(tmp_path / "x")])
    assert exit_info.value.code == 2
