"""Dataset layouts: a random scene written in each layout reads back the same; malformed LLFF-family files
fail with one line naming the file; `load_scene` finds the layout of a folder."""

from __future__ import annotations

import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from helpers import raises_naming

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.data.llff import (
    load_llff,
    write_hdrnerf,
    write_llff,
    write_llff_hwf_cxcy,
)
from hdrplenoxels.data.transforms_json import load_transforms
from hdrplenoxels.data.writers import write_blender, write_nerfstudio
from hdrplenoxels.geometry.cameras import Cameras

N = 5
SIZES = [(8, 6), (9, 7), (8, 6), (10, 6), (7, 5)]
NAMES = [f"view_{i:03d}.png" for i in range(N)]


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _intrinsics(rng: np.random.Generator, w: int, h: int, pinhole_only: bool) -> list[float]:
    """Random (fx, fy, cx, cy); LLFF-plain (fx == fy, centred) when `pinhole_only`."""
    fx, fy = rng.uniform(5, 15, size=2)
    if pinhole_only:
        return [fx, fx, w / 2, h / 2]
    return [fx, fy, rng.uniform(2, w - 2), rng.uniform(2, h - 2)]


def _cameras(seed: int, per_camera: bool, pinhole_only: bool) -> Cameras:
    """N random rigid poses with per-camera sizes and intrinsics, or one shared set."""
    rng = np.random.default_rng(seed)
    c2w = np.tile(np.eye(4), (N, 1, 1))
    for i in range(N):
        c2w[i, :3, :3] = _rotation(rng)
        c2w[i, :3, 3] = rng.normal(size=3) * 3
    sizes = SIZES if per_camera else [SIZES[0]] * N
    intrinsics = [_intrinsics(rng, w, h, pinhole_only) for w, h in (sizes if per_camera else sizes[:1])]
    return Cameras(c2w, intrinsics if per_camera else intrinsics * N, sizes)


def _images(cameras: Cameras, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8) for w, h in cameras.sizes]


def _bounds(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0.5, 1.0, N), rng.uniform(5.0, 10.0, N)], axis=1)


def _assert_same(scene, cameras: Cameras, images: list[np.ndarray], order=None) -> None:
    order = list(range(N)) if order is None else order
    np.testing.assert_allclose(scene.cameras.c2w, cameras.c2w[order], atol=1e-5)
    np.testing.assert_allclose(scene.cameras.intrinsics, cameras.intrinsics[order], atol=1e-5)
    np.testing.assert_array_equal(scene.cameras.sizes, cameras.sizes[order])
    for got, i in zip(scene.images, order, strict=True):
        np.testing.assert_array_equal(got, images[i])


# ---- round trips -----------------------------------------------------------------------------------


def test_llff_round_trip(tmp_path):
    cams, bounds = _cameras(1, per_camera=True, pinhole_only=True), _bounds(1)
    images = _images(cams, 1)
    write_llff(tmp_path, cams, bounds, images)
    scene = load_llff(tmp_path)
    _assert_same(scene, cams, images)
    assert scene.names == [f"images/{n}" for n in NAMES] and scene.source == tmp_path / "poses_bounds.npy"
    assert scene.near_far == (bounds[:, 0].min(), bounds[:, 1].max())
    assert (scene.train_ids, scene.test_ids) == ([1, 2, 3, 4], [0])
    assert scene.forward_facing is None and scene.extras["layout"] == "llff"
    assert "exposure_init_ev" not in scene.extras


@pytest.mark.parametrize("per_camera", [True, False])
def test_llff_hwf_cxcy_round_trip(tmp_path, per_camera):
    cams, bounds = _cameras(2, per_camera=per_camera, pinhole_only=False), _bounds(2)
    images = _images(cams, 2)
    write_llff_hwf_cxcy(tmp_path, cams, bounds, images)
    assert np.load(tmp_path / "poses_bounds.npy").shape == (N, 14)
    # One shared camera is stored as NeX / HDR-Plenoxels do; per-image rows only when they differ.
    assert np.load(tmp_path / "hwf_cxcy.npy").shape == ((N, 6) if per_camera else (6, 1))
    scene = load_llff(tmp_path)
    _assert_same(scene, cams, images)
    assert scene.extras["layout"] == "llff_hwf_cxcy"


def test_hdrnerf_round_trip_and_exposure_column(tmp_path):
    cams, bounds = _cameras(3, per_camera=False, pinhole_only=True), _bounds(3)
    images = _images(cams, 3)
    times = 2.0 ** np.array([-8.0, -6.0, -4.5, -2.0, 0.0])
    write_hdrnerf(tmp_path, cams, bounds, times, images)
    assert np.load(tmp_path / "poses_bounds_exps.npy").shape == (N, 18)
    assert (tmp_path / "input_images" / NAMES[0]).is_file()
    scene = load_llff(tmp_path)
    _assert_same(scene, cams, images)
    np.testing.assert_allclose(scene.extras["exposure_init_ev"], np.log2(times))
    assert scene.exposures is None and scene.extras["layout"] == "hdrnerf"  # an initial value, never pinned
    (tmp_path / "input_images").rename(tmp_path / "images")  # the tolerated alternative folder
    assert load_llff(tmp_path / "poses_bounds_exps.npy").names[0] == f"images/{NAMES[0]}"


@pytest.mark.parametrize("per_frame", [False, True])
def test_nerfstudio_round_trip(tmp_path, per_frame):
    cams = _cameras(4, per_camera=per_frame, pinhole_only=False)
    images = _images(cams, 4)
    write_nerfstudio(tmp_path, cams, images, extra={"near_far": [0.5, 9.0]})
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert ("fl_x" in meta) != per_frame and ("fl_x" in meta["frames"][0]) == per_frame
    scene = load_transforms(tmp_path)
    _assert_same(scene, cams, images)
    assert scene.near_far == (0.5, 9.0) and scene.names == [f"images/{n}" for n in NAMES]


def test_blender_round_trip(tmp_path):
    cams = _cameras(5, per_camera=False, pinhole_only=True)
    images = _images(cams, 5)
    write_blender(tmp_path, cams, [1, 2, 3, 4], [0], images)
    scene = load_transforms(tmp_path)
    _assert_same(scene, cams, images, order=[1, 2, 3, 4, 0])
    assert (scene.train_ids, scene.test_ids) == ([0, 1, 2, 3], [4])
    assert scene.names[0] == "./train/r_0" and scene.names[4] == "./test/r_0"


def test_writers_refuse_what_the_layout_cannot_state(tmp_path):
    general = _cameras(6, per_camera=True, pinhole_only=False)
    with pytest.raises(ValueError, match="hwf_cxcy"):
        write_llff(tmp_path, general, _bounds(6))
    with pytest.raises(ValueError, match="Blender"):
        write_blender(tmp_path, general, [1, 2, 3, 4], [0])
    with pytest.raises(ValueError, match="sorted"):
        write_llff(tmp_path, _cameras(6, True, True), _bounds(6), image_names=NAMES[::-1])
    with pytest.raises(ValueError, match="positive"):
        write_hdrnerf(tmp_path, _cameras(6, True, True), _bounds(6), [1.0, 0.0, 1.0, 1.0, 1.0])
    assert not any(tmp_path.iterdir())  # nothing half-written


def test_llff_images_resized_from_the_stored_size(tmp_path):
    """LLFF's images_8 copied into images/: the focal and principal point follow the image size."""
    c2w = np.tile(np.eye(4), (2, 1, 1))
    cams = Cameras(c2w, [[20.0, 20.0, 8.0, 6.0]] * 2, [[16, 12]] * 2)
    write_llff(tmp_path, cams, [(1.0, 5.0)] * 2, [np.zeros((6, 8, 3), np.uint8)] * 2)
    np.testing.assert_allclose(load_llff(tmp_path).cameras.intrinsics, [[10.0, 10.0, 4.0, 3.0]] * 2)
    write_png(tmp_path / "images" / NAMES[1], np.zeros((8, 8, 3), np.uint8))
    raises_naming(NAMES[1], load_llff, tmp_path, contains=("8x8", "16x12", "aspect"))


# ---- malformed LLFF-family inputs ------------------------------------------------------------------


def _llff(root: Path, kind: str) -> Path:
    """A valid scene of `kind` in root; returns the .npy file to corrupt."""
    cams, bounds = _cameras(7, per_camera=False, pinhole_only=kind != "hwf"), _bounds(7)
    images = _images(cams, 7)
    if kind == "llff":
        return write_llff(root, cams, bounds, images)
    if kind == "hwf":
        return write_llff_hwf_cxcy(root, cams, bounds, images)
    return write_hdrnerf(root, cams, bounds, np.full(N, 0.01), images)


def _edit_npy(path: Path, fn) -> None:
    arr = np.load(path)
    arr = fn(arr)
    np.save(path, arr)


def _nan(arr):
    arr[2, 3] = np.nan
    return arr


def _stretch(arr):  # scales the first rotation column of row 1: not a rotation any more
    arr[1, 0:15:5] *= 1.5
    return arr


def _far_before_near(arr):
    arr[3, -2:] = [4.0, 2.0]
    return arr


@pytest.mark.parametrize("kind, npy", [("llff", "poses_bounds.npy"), ("hdrnerf", "poses_bounds_exps.npy")])
@pytest.mark.parametrize(
    "mutate, needles",
    [
        (lambda a: a[:, :16], ("got shape (5, 16)",)),
        (lambda a: a[0], ("got shape",)),
        (_nan, ("row 2", "NaN")),
        (_stretch, ("images/", "not a rigid transform")),
    ],
)
def test_llff_family_bad_arrays(tmp_path, kind, npy, mutate, needles):
    path = _llff(tmp_path, kind)
    _edit_npy(path, mutate)
    raises_naming(npy, load_llff, tmp_path, contains=needles)


def test_llff_bad_bounds_and_unreadable_file(tmp_path):
    path = _llff(tmp_path, "llff")
    _edit_npy(path, _far_before_near)
    raises_naming("poses_bounds.npy", load_llff, tmp_path, contains=("row 3", "near"))
    path.write_bytes(b"not an array")
    raises_naming("poses_bounds.npy", load_llff, tmp_path, contains=("not a NumPy",))
    np.save(path, np.array([{"a": 1}], dtype=object))
    raises_naming("poses_bounds.npy", load_llff, tmp_path)


@pytest.mark.parametrize(
    "kind, npy, folder",
    [("llff", "poses_bounds.npy", "images"), ("hdrnerf", "poses_bounds_exps.npy", "input_images")],
)
def test_llff_family_image_folder_errors(tmp_path, kind, npy, folder):
    _llff(tmp_path, kind)
    (tmp_path / folder / NAMES[3]).unlink()
    raises_naming(npy, load_llff, tmp_path, contains=("5 poses", "4 images"))
    shutil.rmtree(tmp_path / folder)
    raises_naming(folder, load_llff, tmp_path, contains=("image folder not found",))


def test_hdrnerf_exposure_must_be_positive(tmp_path):
    path = _llff(tmp_path, "hdrnerf")
    _edit_npy(path, lambda a: np.concatenate([a[:, :17], np.array([[0.1], [0.1], [-1.0], [0.1], [0.1]])], 1))
    raises_naming("poses_bounds_exps.npy", load_llff, tmp_path, contains=("row 2", "exposure"))


@pytest.mark.parametrize(
    "hwf, needles",
    [
        (np.ones(5), ("got shape (5,)",)),
        (np.array([6.0, 8.0, 10.0, 10.0, 4.0, np.nan]), ("NaN",)),
        (np.array([6.0, 8.0, -10.0, 10.0, 4.0, 3.0]), ("focal",)),
        (np.array([6.5, 8.0, 10.0, 10.0, 4.0, 3.0]), ("whole",)),
    ],
)
def test_hwf_cxcy_errors(tmp_path, hwf, needles):
    _llff(tmp_path, "hwf")
    np.save(tmp_path / "hwf_cxcy.npy", hwf)
    raises_naming("hwf_cxcy.npy", load_llff, tmp_path, contains=needles)


def test_hwf_cxcy_shapes_accepted_and_pose_width(tmp_path):
    path = _llff(tmp_path, "hwf")
    np.save(tmp_path / "hwf_cxcy.npy", np.array([6.0, 8.0, 10.0]))  # HDR-Plenoxels' [h, w, f] form
    np.testing.assert_allclose(load_llff(tmp_path).cameras.intrinsics[0], [10.0, 10.0, 4.0, 3.0])
    _edit_npy(path, lambda a: a[:, 1:])
    raises_naming("poses_bounds.npy", load_llff, tmp_path, contains=("(N, 14)",))


def test_transforms_readers_refuse_non_rigid_poses(tmp_path):
    cams = _cameras(8, per_camera=False, pinhole_only=True)
    cams.c2w[2, :3, :3] *= 1.1
    write_nerfstudio(tmp_path / "ns", cams, _images(cams, 8))
    raises_naming("transforms.json", load_transforms, tmp_path / "ns", contains=("view_002", "rigid"))
    write_blender(tmp_path / "bl", cams, [1, 2, 3, 4], [0], _images(cams, 8))
    raises_naming("transforms_train.json", load_transforms, tmp_path / "bl", contains=("r_1", "rigid"))


# ---- dispatch --------------------------------------------------------------------------------------


def test_load_scene_finds_each_layout(tmp_path, monkeypatch):
    _llff(tmp_path / "llff", "llff")
    _llff(tmp_path / "hdrnerf", "hdrnerf")
    assert load_scene(tmp_path / "llff").extras["layout"] == "llff"
    assert load_scene(tmp_path / "hdrnerf").extras["layout"] == "hdrnerf"
    assert load_scene(tmp_path / "llff" / "poses_bounds.npy").extras["layout"] == "llff"
    cams = _cameras(9, per_camera=False, pinhole_only=True)
    write_nerfstudio(tmp_path / "llff", cams, _images(cams, 9))
    assert load_scene(tmp_path / "llff").extras["layout"] == "nerfstudio"  # transforms.json wins
    fake = types.ModuleType("hdrplenoxels.data.colmap")
    fake.load_colmap = lambda path, downscale: ("colmap", path)
    monkeypatch.setitem(sys.modules, "hdrplenoxels.data.colmap", fake)
    (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "colmap" / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    assert load_scene(tmp_path / "colmap") == ("colmap", tmp_path / "colmap")
    (tmp_path / "other").mkdir()
    raises_naming("other", load_scene, tmp_path / "other", contains=("poses_bounds.npy", "sparse/0"))
    np.save(tmp_path / "x.npy", np.zeros(3))
    raises_naming("x.npy", load_scene, tmp_path / "x.npy", contains=("unrecognised",))
