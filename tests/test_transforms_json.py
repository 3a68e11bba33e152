"""transforms.json parsing: conventions, intrinsics, splits, Blender layout and malformed inputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import raises_naming
from PIL import Image

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.transforms_json import load_transforms

W, H = 8, 6
RNG = np.random.default_rng(1)


def _pose(t=(0.0, 0.0, 4.0)) -> list[list[float]]:
    m = np.eye(4)
    m[:3, 3] = t
    return m.tolist()


def _img(path: Path, w: int = W, h: int = H, rgba: bool = False) -> np.ndarray:
    a = RNG.integers(0, 256, size=(h, w, 4 if rgba else 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).save(path)
    return a


def _scene(root: Path, n: int = 3, top: dict | None = None, frame_extra=None, ext: str = ".png") -> Path:
    """A nerfstudio folder with n 8x6 images; returns the json path."""
    frames = []
    for i in range(n):
        _img(root / "images" / f"f{i:02d}{ext}")
        fr = {"file_path": f"images/f{i:02d}{ext}", "transform_matrix": _pose((i, 0.0, 4.0))}
        if frame_extra:
            fr.update(frame_extra(i))
        frames.append(fr)
    meta = {"camera_angle_x": 1.0, **(top or {}), "frames": frames}
    meta = {k: v for k, v in meta.items() if v is not None}  # top={"key": None} removes a default
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def _edit(json_path: Path, fn) -> None:
    meta = json.loads(json_path.read_text())
    fn(meta)
    json_path.write_text(json.dumps(meta))


# ---- conventions and intrinsics -------------------------------------------------------------------


def test_opengl_pose_becomes_opencv(tmp_path):
    load = load_transforms(_scene(tmp_path))
    c2w = load.cameras.c2w[0]
    # OpenGL camera at +z with identity rotation looks at the origin along -z; OpenCV's z (forward)
    # axis must therefore point to -z in world, y (down) to -y, x unchanged, position unchanged.
    np.testing.assert_allclose(c2w[:3, 2], [0, 0, -1])
    np.testing.assert_allclose(c2w[:3, 1], [0, -1, 0])
    np.testing.assert_allclose(c2w[:3, 0], [1, 0, 0])
    np.testing.assert_allclose(c2w[:3, 3], [0, 0, 4])
    towards_origin = -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
    np.testing.assert_allclose(c2w[:3, 2], towards_origin)


def test_focal_from_camera_angle_x(tmp_path):
    scene = load_transforms(_scene(tmp_path, top={"camera_angle_x": 0.8}))
    fx = 0.5 * W / math.tan(0.4)
    np.testing.assert_allclose(scene.cameras.intrinsics, [[fx, fx, W / 2, H / 2]] * 3)
    np.testing.assert_array_equal(scene.cameras.sizes, [[W, H]] * 3)
    assert scene.images[0].shape == (H, W, 3) and scene.images[0].dtype == np.uint8
    assert scene.source == tmp_path / "transforms.json"
    assert scene.scene_box is None and scene.near_far is None and scene.forward_facing is None


def test_focal_from_angles_and_fovs(tmp_path):
    s = load_transforms(_scene(tmp_path / "a", top={"camera_angle_x": 0.8, "camera_angle_y": 0.5}))
    expected = [0.5 * W / math.tan(0.4), 0.5 * H / math.tan(0.25)]
    np.testing.assert_allclose(s.cameras.intrinsics[0, :2], expected)
    s = load_transforms(_scene(tmp_path / "b", top={"camera_angle_x": None, "x_fov": 60.0, "y_fov": 50.0}))
    expected = [0.5 * W / math.tan(math.radians(30)), 0.5 * H / math.tan(math.radians(25))]
    np.testing.assert_allclose(s.cameras.intrinsics[0, :2], expected)
    s = load_transforms(_scene(tmp_path / "c", top={"camera_angle_x": None, "fl_y": 7.0}))
    np.testing.assert_allclose(s.cameras.intrinsics[0, :2], [7.0, 7.0])  # the one focal given serves both


def test_explicit_shared_intrinsics(tmp_path):
    top = dict(fl_x=10.0, fl_y=11.0, cx=3.5, cy=2.5, w=W, h=H, camera_model="OPENCV", k1=0.0, k2=0.0, p1=0.0)
    s = load_transforms(_scene(tmp_path, top=top))
    np.testing.assert_allclose(s.cameras.intrinsics, [[10.0, 11.0, 3.5, 2.5]] * 3)
    assert s.background_brightness == 0.5  # opaque photos: the HDR-Plenoxels background brightness
    top["background"] = 0.0
    assert load_transforms(_scene(tmp_path, top=top)).background_brightness == 0.0
    top["background"] = -1.0
    with pytest.raises(InputError, match="background"):
        load_transforms(_scene(tmp_path, top=top))


def test_per_frame_intrinsics_override_and_allow_mixed_sizes(tmp_path):
    j = _scene(tmp_path, n=2, top={"fl_x": 10.0}, frame_extra=lambda i: {"fl_x": 20.0 + i, "cx": 1.0})
    _img(tmp_path / "images" / "f01.png", w=10, h=4)
    _edit(j, lambda m: m["frames"][1].update({"w": 10, "h": 4}))
    s = load_transforms(j)
    np.testing.assert_allclose(s.cameras.intrinsics, [[20.0, 20.0, 1.0, H / 2], [21.0, 21.0, 1.0, 2.0]])
    np.testing.assert_array_equal(s.cameras.sizes, [[W, H], [10, 4]])


def test_extensionless_file_path_names_and_folder_or_file(tmp_path):
    j = _scene(tmp_path, n=2, ext=".jpg")
    _edit(j, lambda m: [f.update(file_path=f["file_path"][:-4]) for f in m["frames"]])
    for arg in (tmp_path, j, str(j)):
        s = load_transforms(arg)
        assert s.names == ["images/f00", "images/f01"]
    assert load_scene(tmp_path).names == s.names


def test_rgba_frames_composited_on_white(tmp_path):
    j = _scene(tmp_path, n=2)
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[0, 0, 3], rgba[0, 1, 3], rgba[0, 2, 3] = 0, 255, 128
    Image.fromarray(rgba).save(tmp_path / "images" / "f00.png")
    s = load_transforms(j)
    assert s.images[0].shape == (H, W, 3)
    np.testing.assert_array_equal(s.images[0][0, :3, 0], [255, 200, 227])
    assert s.extras["alpha_background"] == "white"
    assert s.background_brightness == 1.0  # rendered against the white it was composited on


def test_optional_scene_keys(tmp_path):
    top = {"aabb": [[-1, -2, -3], [1, 2, 3]], "near_far": [0.5, 9.0], "forward_facing": True}
    s = load_transforms(_scene(tmp_path, top=top))
    assert s.scene_box == ((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0))
    assert s.near_far == (0.5, 9.0)
    assert s.forward_facing is True


# ---- splits ----------------------------------------------------------------------------------------


def test_every_8th_listed_frame_is_test_without_sorting(tmp_path):
    j = _scene(tmp_path, n=10)
    _edit(j, lambda m: m["frames"].reverse())  # listed f09, f08, ..., f00: order must be kept
    s = load_transforms(j)
    assert s.test_ids == [0, 8]
    assert s.train_ids == [1, 2, 3, 4, 5, 6, 7, 9]
    assert s.names[0] == "images/f09.png" and s.names[8] == "images/f01.png"


def test_split_from_filename_lists(tmp_path):
    top = {"train_filenames": ["./images/f00.png", "images/f02.png"], "test_filenames": ["images/f01.png"]}
    s = load_transforms(_scene(tmp_path, n=4, top=top))
    assert (s.train_ids, s.test_ids) == ([0, 2], [1])  # f03 is in neither list
    s = load_transforms(_scene(tmp_path / "b", n=4, top={"test_filenames": ["images/f03.png"]}))
    assert (s.train_ids, s.test_ids) == ([0, 1, 2], [3])


def test_split_list_errors(tmp_path):
    j = _scene(tmp_path, n=3, top={"train_filenames": ["images/f00.png", "images/zzz.png"]})
    raises_naming("transforms.json", load_transforms, j, contains=("zzz.png",))
    _edit(j, lambda m: m.update(train_filenames=["images/f00.png"], test_filenames=["images/f00.png"]))
    raises_naming("transforms.json", load_transforms, j, contains=("both",))


# ---- Blender ---------------------------------------------------------------------------------------


def _blender(root: Path, n_train: int = 2, n_test: int = 1, val: bool = True) -> dict[str, np.ndarray]:
    images = {}
    for split, n in (("train", n_train), ("test", n_test), ("val", 1 if val else 0)):
        frames = []
        for i in range(n):
            images[f"./{split}/r_{i}"] = _img(root / split / f"r_{i}.png", rgba=True)
            pose = _pose((i, 1, 4))
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.1, "transform_matrix": pose})
        if n:
            meta = {"camera_angle_x": 0.7, "frames": frames}
            (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return images


def test_blender_layout(tmp_path):
    rgba = _blender(tmp_path)
    s = load_transforms(tmp_path)
    assert s.names == ["./train/r_0", "./train/r_1", "./test/r_0"]
    assert (s.train_ids, s.test_ids) == ([0, 1], [2])
    assert s.scene_box == ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
    assert s.forward_facing is False and s.background_brightness == 1.0
    fx = 0.5 * W / math.tan(0.35)
    np.testing.assert_allclose(s.cameras.intrinsics, [[fx, fx, W / 2, H / 2]] * 3)
    np.testing.assert_allclose(s.cameras.c2w[2][:3, 2], [0, 0, -1])
    for name, im in zip(s.names, s.images, strict=True):
        a = rgba[name].astype(np.float64)
        expected = np.round((a[..., :3] / 255 * (a[..., 3:] / 255) + (1 - a[..., 3:] / 255)) * 255)
        assert np.abs(im.astype(np.float64) - expected).max() <= 1  # float32 vs float64 at .5 ties
        assert im.dtype == np.uint8 and im.shape == (H, W, 3)
    assert load_transforms(tmp_path / "transforms_train.json").names == s.names
    assert load_scene(tmp_path).names == s.names


def test_blender_errors(tmp_path):
    _blender(tmp_path)
    (tmp_path / "transforms_test.json").unlink()
    raises_naming("transforms_test.json", load_transforms, tmp_path)
    _blender(tmp_path / "b")
    _edit(tmp_path / "b" / "transforms_train.json", lambda m: m.pop("camera_angle_x"))
    raises_naming("transforms_train.json", load_transforms, tmp_path / "b", contains=("camera_angle_x",))


# ---- camera models ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "top, needle",
    [
        ({"camera_model": "OPENCV", "k1": 0.1, "k4": 0.01}, "'k4'"),  # nerfstudio's r^8 term
        ({"k1": "0.1"}, "'k1'"),
        ({"is_fisheye": True}, "fisheye"),
        ({"camera_model": "OPENCV_FISHEYE"}, "OPENCV_FISHEYE"),
        ({"camera_model": "EQUIRECTANGULAR"}, "EQUIRECTANGULAR"),
    ],
)
def test_unsupported_cameras(tmp_path, top, needle):
    raises_naming("transforms.json", load_transforms, _scene(tmp_path, top=top), contains=(needle,))


DISTORTED_K = {"fl_x": 60.0, "fl_y": 62.0, "cx": 31.0, "cy": 25.0}
DISTORTION = {"k1": 0.25, "k2": 0.03, "p1": 0.002, "p2": -0.001, "k3": 0.005}


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth RGB scene as a function of normalised image coordinates (pinhole x/z, y/z)."""
    r = np.sin(5 * x + 0.3) * np.cos(4 * y)
    return 127.5 + 100 * np.stack([r, np.cos(3 * x - 2 * y), np.sin(6 * y + x)], axis=-1)


def _distort(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The OpenCV radial-tangential model, forward: undistorted to distorted normalised coordinates."""
    k1, k2, p1, p2, k3 = (DISTORTION[k] for k in ("k1", "k2", "p1", "p2", "k3"))
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (
        r2 + 2 * y * y
    ) + 2 * p2 * x * y


def _pinhole_view(k: np.ndarray, w: int, h: int) -> np.ndarray:
    """The pattern through a pinhole camera (fx, fy, cx, cy), pixel centres at +0.5."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return _pattern((u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1])


def _distorted_photo(w: int = 64, h: int = 48) -> np.ndarray:
    """The pattern through the distorted camera: each pixel's undistorted point by fixed-point iteration."""
    fx, fy, cx, cy = DISTORTED_K.values()
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(60):
        dx, dy = _distort(x, y)
        x, y = x - (dx - xd), y - (dy - yd)
    return np.round(_pattern(x, y)).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("per_frame", [False, True])
def test_opencv_distortion_is_undone(tmp_path, per_frame):
    """Distorted photos load as pinhole images of the same scene (per-frame coefficients: that frame only)."""
    top = {"camera_model": "OPENCV", **DISTORTED_K, **({} if per_frame else DISTORTION)}
    j = _scene(tmp_path, n=2, top=top, frame_extra=lambda i: DISTORTION if per_frame and i == 1 else {})
    photo = _distorted_photo()
    for i in range(2):
        Image.fromarray(photo).save(tmp_path / "images" / f"f{i:02d}.png")
    s = load_transforms(j)
    if per_frame:
        np.testing.assert_array_equal(s.images[0], photo)
        np.testing.assert_allclose(s.cameras.intrinsics[0], list(DISTORTED_K.values()))
    k, (w, h) = s.cameras.intrinsics[1], s.cameras.sizes[1]
    assert s.images[1].shape == (h, w, 3) and (w, h) != (64, 48)  # cropped to valid pixels
    np.testing.assert_allclose(k[:2], [60.0, 62.0])  # COLMAP keeps the focal lengths
    err = np.abs(s.images[1] - _pinhole_view(k, w, h))
    # Bilinear resampling of this smooth pattern errs ~0.3 levels; half a pixel off would be ~2 on average.
    assert err.mean() < 0.6 and err.max() < 3.0, (err.mean(), err.max())


# ---- malformed inputs ------------------------------------------------------------------------------


def test_folder_without_transforms(tmp_path):
    (tmp_path / "empty_scene").mkdir()
    raises_naming("empty_scene", load_transforms, tmp_path / "empty_scene")
    raises_naming("empty_scene", load_scene, tmp_path / "empty_scene")
    raises_naming("missing.json", load_transforms, tmp_path / "missing.json")
    (tmp_path / "notes.txt").write_text("x")
    raises_naming("notes.txt", load_scene, tmp_path / "notes.txt")


def test_invalid_json_reports_line_and_column(tmp_path):
    (tmp_path / "transforms.json").write_text('{\n  "frames": [\n    {"file_path": }\n  ]\n}')
    err = raises_naming("transforms.json", load_transforms, tmp_path)
    assert "line 3" in err.problem and "column" in err.problem
    (tmp_path / "transforms.json").write_text("[1, 2]")
    raises_naming("transforms.json", load_transforms, tmp_path)


@pytest.mark.parametrize(
    "mutate, needles",
    [
        (lambda m: m.pop("frames"), ("'frames'",)),
        (lambda m: m.update(frames=[]), ("no frames",)),
        (lambda m: m["frames"][1].pop("transform_matrix"), ("frame 1", "'transform_matrix'")),
        (lambda m: m["frames"][2].pop("file_path"), ("frame 2", "'file_path'")),
        (lambda m: m["frames"][1].update(transform_matrix=np.eye(3).tolist()), ("frame 1", "4x4")),
        (lambda m: m["frames"][1].update(transform_matrix=[[1, 2], [3]]), ("frame 1", "4x4")),
        (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")), ("frame 0", "NaN")),
        (lambda m: m["frames"][0]["transform_matrix"][1].__setitem__(3, float("inf")), ("frame 0", "NaN")),
        (lambda m: m.pop("camera_angle_x"), ("frame 0", "fl_x")),
        (lambda m: m.update(camera_angle_x=-1), ("camera_angle_x", "positive")),
        (lambda m: m.update(w="eight"), ("'w'",)),
        (lambda m: m.update(aabb=[[1, 1, 1], [0, 0, 0]]), ("aabb",)),
        (lambda m: m.update(near_far=[5, 1]), ("near_far",)),
        (lambda m: m.update(forward_facing="yes"), ("forward_facing",)),
    ],
)
def test_malformed_json_fields(tmp_path, mutate, needles):
    j = _scene(tmp_path)
    _edit(j, mutate)
    raises_naming("transforms.json", load_transforms, j, contains=needles)


def test_missing_image_is_named(tmp_path):
    j = _scene(tmp_path)
    (tmp_path / "images" / "f01.png").unlink()
    raises_naming("f01.png", load_transforms, j, contains=("transforms.json", "frame 1"))


def test_image_size_must_match_stated_intrinsics(tmp_path):
    j = _scene(tmp_path, top={"w": W, "h": H})
    _img(tmp_path / "images" / "f02.png", w=9, h=H)
    raises_naming("f02.png", load_transforms, j, contains=("9x6", f"w={W}, h={H}", "transforms.json"))


def test_mixed_sizes_with_shared_intrinsics(tmp_path):
    j = _scene(tmp_path)
    _img(tmp_path / "images" / "f01.png", w=10, h=4)
    raises_naming("transforms.json", load_transforms, j, contains=("f00.png", "f01.png", "10x4"))


def test_unreadable_image_is_named(tmp_path):
    j = _scene(tmp_path)
    (tmp_path / "images" / "f01.png").write_bytes(b"garbage")
    raises_naming("f01.png", load_transforms, j)


def test_single_frame_without_split_lists(tmp_path):
    raises_naming("transforms.json", load_transforms, _scene(tmp_path, n=1), contains=("1 frame",))
