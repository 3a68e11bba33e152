"""Camera paths (generated and nerfstudio's camera_path.json) and H.264 videos of a trained model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hdrplenoxels.cli.main import main
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.camera_path import CameraPath, PathFrame, read_camera_path, write_camera_path
from hdrplenoxels.eval.video import VideoFrame, frame_ldr, render_video, to_uint8
from hdrplenoxels.geometry.paths import interpolate, look_at, orbit, spiral, through_cameras
from hdrplenoxels.train.model import MODEL_FILE, Model


def _rotation_ok(poses: np.ndarray) -> bool:
    r = poses[:, :3, :3]
    return bool(
        np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-6) and np.allclose(np.linalg.det(r), 1)
    )


def _ring(n: int = 12, radius: float = 3.0, height: float = 1.0) -> np.ndarray:
    up = np.array([0.0, 0.0, 1.0])
    return np.stack(
        [
            look_at(np.array([radius * math.cos(a), radius * math.sin(a), height]), np.zeros(3), up)
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False)
        ]
    )


def test_look_at_gives_opencv_axes():
    """Looking along +z with up = -y is the identity camera (x right, y down, z forward)."""
    assert np.allclose(look_at(np.zeros(3), np.array([0, 0, 1.0]), np.array([0, -1.0, 0])), np.eye(4))
    pose = look_at(np.array([0, -5.0, 0]), np.zeros(3), np.array([0, 0, 1.0]))  # level, looking along +y
    assert np.allclose(pose[:3, 0], [1, 0, 0]) and np.allclose(pose[:3, 1], [0, 0, -1])


def test_orbit_keeps_the_cameras_distance_and_height_and_looks_at_the_centre():
    poses = orbit(_ring(), np.zeros(3), 30)
    assert poses.shape == (30, 4, 4) and _rotation_ok(poses)
    positions = poses[:, :3, 3]
    assert np.allclose(positions[:, 2], 1.0) and np.allclose(np.linalg.norm(positions[:, :2], axis=1), 3.0)
    to_centre = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
    assert np.allclose((poses[:, :3, 2] * to_centre).sum(1), 1.0)  # the optical axis hits the centre
    assert (poses[:, 2, 1] < 0).all()  # image down points down: the mean up is kept


def test_interpolation_passes_through_its_keyframes_and_slerps_rotations():
    keys = _ring(4)
    poses = interpolate(keys, 7)  # keyframes at frames 0, 2, 4, 6
    assert _rotation_ok(poses)
    for k in range(4):
        assert np.allclose(poses[2 * k], keys[k], atol=1e-9)
    halfway = poses[1][:3, :3].T @ keys[0][:3, :3]  # half of the 90-degree turn between keys 0 and 1
    assert math.isclose(math.degrees(math.acos((np.trace(halfway) - 1) / 2)), 45.0, abs_tol=1e-6)
    assert through_cameras(_ring(20), 5, stops=3).shape == (5, 4, 4)


def test_spiral_stays_near_the_forward_facing_cameras_and_looks_ahead():
    grid = [(-1, -0.5), (1, -0.5), (-1, 0.5), (1, 0.5), (0, 0)]
    ahead, up = np.array([0, 0, 10.0]), np.array([0, -1.0, 0])
    cams = np.stack([look_at(np.array([x, y, 0.0]), ahead, up) for x, y in grid])
    poses = spiral(cams, focus_depth=10.0, frames=24)
    assert _rotation_ok(poses)
    assert np.abs(poses[:, :2, 3]).max() <= 1.0 + 1e-6 and (poses[:, 2, 2] > 0.99).all()


def test_camera_path_json_round_trips_in_nerfstudios_layout(tmp_path):
    frames = [PathFrame(p, 50.0, ev, (1.0, 0.9, 1.2)) for p, ev in zip(_ring(3), (-1.0, 0.0, 2.0))]
    path = CameraPath(frames, 64, 48, 24.0, keyframes=frames[:2])
    write_camera_path(tmp_path / "camera_path.json", path)
    raw = json.loads((tmp_path / "camera_path.json").read_text())
    assert {"camera_path", "keyframes", "render_width", "render_height", "fps", "seconds"} <= raw.keys()
    assert len(raw["camera_path"][0]["camera_to_world"]) == 16 and isinstance(
        raw["keyframes"][0]["matrix"], str
    )
    # nerfstudio stores OpenGL axes: the camera looks down its -z column
    assert np.allclose(
        np.reshape(raw["camera_path"][0]["camera_to_world"], (4, 4))[:3, 2], -frames[0].c2w[:3, 2]
    )
    back = read_camera_path(tmp_path / "camera_path.json")
    assert (back.width, back.height, back.fps) == (64, 48, 24.0) and len(back.keyframes) == 2
    for a, b in zip(back.frames, frames):
        assert np.allclose(a.c2w, b.c2w) and (a.fov_y_deg, a.ev, a.wb) == (b.fov_y_deg, b.ev, b.wb)
    assert np.allclose(back.intrinsics(back.frames[0])[1], 24.0 / math.tan(math.radians(25.0)))


@pytest.mark.parametrize(
    "content, problem",
    [
        ("{", "not valid JSON"),
        ('{"camera_path": []}', "no camera_path"),
        ('{"camera_path": [{"fov": 50}], "render_width": 8, "render_height": 8}', "camera_to_world"),
        (
            '{"camera_path": [{"camera_to_world": [' + ",".join(["2"] * 16) + '], "fov": 50}], '
            '"render_width": 8, "render_height": 8}',
            "not a rigid transform",
        ),  # fmt: skip
    ],
)
def test_a_bad_camera_path_is_one_clear_error(tmp_path, content, problem):
    (tmp_path / "p.json").write_text(content)
    with pytest.raises(InputError, match=problem):
        read_camera_path(tmp_path / "p.json")


@pytest.fixture(scope="module")
def run(tonemapped_run) -> Path:
    return tonemapped_run


@pytest.fixture(scope="module")
def model(tonemapped_run) -> Model:
    return Model.load(tonemapped_run / MODEL_FILE)


def _decode(path) -> list[np.ndarray]:
    import av

    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def test_render_video_from_the_cli_saves_a_camera_path_that_renders_the_same_video(run, tmp_path):
    """`render --video` with a generated orbit and an EV ramp, `--save-camera-path`, then the saved
    camera_path.json rendered again: same frames (the path survives the dataset-frame round trip)."""
    first, again, path = tmp_path / "orbit.mp4", tmp_path / "again.mp4", tmp_path / "camera_path.json"
    args = ["--frames", "4", "--resolution", "48x40", "--ev-from", "-1", "--ev-to", "1", "--fps", "8"]
    main(["render", str(run), "--video", str(first), *args, "--save-camera-path", str(path)])
    main(["render", str(run), "--video", str(again), "--camera-path", str(path)])
    a, b = _decode(first), _decode(again)
    assert len(a) == len(b) == 4 and a[0].shape == (40, 48, 3)
    assert json.loads(path.read_text())["camera_path"][3]["hdrplenoxels"]["ev"] == 1.0
    for x, y in zip(a, b):
        assert np.abs(x.astype(int) - y.astype(int)).mean() < 1.0


def test_video_decodes_to_the_path_with_frame_zero_matching_a_still_render(model, tmp_path):
    cams = model.cameras
    poses = orbit(cams.c2w, np.zeros(3), 6)
    k = cams.intrinsics[0] * np.array([2, 2, 2, 2])  # 48 x 40 frames from the 24 x 20 views
    evs = [-1.0, 0.0, 0.5, 1.0, 1.5, 2.0]
    frames = [VideoFrame(p, k, ev) for p, ev in zip(poses, evs)]
    out = render_video(
        model, frames, (48, 40), tmp_path / "orbit.mp4", fps=12, exr_dir=tmp_path, progress=False
    )
    decoded = _decode(out)
    assert len(decoded) == 6 and decoded[0].shape == (40, 48, 3)
    still = to_uint8(frame_ldr(model, model.render_view(poses[0], k, (48, 40)), -1.0, (1.0, 1.0, 1.0)))
    mse = np.mean((decoded[0].astype(float) - still.astype(float)) ** 2)
    assert 10 * math.log10(255.0**2 / max(mse, 1e-12)) >= 35.0
    assert decoded[5].mean() > decoded[0].mean() + 10  # the exposure ramp brightens the frames
    assert len(list(tmp_path.glob("frame_*.exr"))) == 6
    with pytest.raises(InputError, match="even"):
        render_video(model, frames, (47, 40), tmp_path / "odd.mp4", fps=12, progress=False)
    assert not (tmp_path / "odd.mp4").exists()
