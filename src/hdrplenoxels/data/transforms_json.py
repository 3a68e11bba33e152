"""Parser for `transforms.json` layouts: nerfstudio / instant-ngp, and the Blender NeRF-synthetic folders.

Poses in these files are camera-to-world in OpenGL axes; they are converted to OpenCV here, so the rest
of the code sees one convention. Everything a user could get wrong raises `InputError` naming the file.

Lens distortion: OpenCV radial-tangential coefficients k1, k2, k3, p1, p2 (top level or per frame; also in
instant-ngp files without a camera_model) are undone at load time: each such image is resampled onto a
pinhole camera with COLMAP (`undistort.py`), which changes its size and principal point. Fisheye,
equirectangular and other models, and nerfstudio's r^8 term k4, are refused.

Split rules (documented because results depend on them):
- nerfstudio: top-level `train_filenames` / `test_filenames` when present (matched on `file_path`; a missing
  list is the complement of the other); otherwise every 8th frame (index % 8 == 0) *in the order the
  frames are listed* is a test view. Frames are deliberately not sorted: the file's order is the user's.
  Frames in neither list are loaded but belong to no split.
- Blender: the files' own split; train frames first, then test frames; `transforms_val.json` is ignored.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.image_io import composite_on_white, read_image_with_alpha
from hdrplenoxels.data.protocol import every_nth_split
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.undistort import undistort_opencv
from hdrplenoxels.data.validate import check_cameras
from hdrplenoxels.geometry.cameras import Cameras, opengl_to_opencv

NERFSTUDIO_FILE = "transforms.json"
BLENDER_FILES = ("transforms_train.json", "transforms_test.json")
BLENDER_BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))  # svox2: radius 1 after scaling by 2/3
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV radial-tangential, in COLMAP's parameter order
FOCAL_X_KEYS = ("fl_x", "camera_angle_x", "x_fov")
FOCAL_Y_KEYS = ("fl_y", "camera_angle_y", "y_fov")
# A frame carrying any of these has its own intrinsics (exempt from the shared-size check).
INTRINSIC_KEYS = (*FOCAL_X_KEYS, *FOCAL_Y_KEYS, "cx", "cy", "w", "h")


@dataclass
class _Frame:
    """One parsed frame before its image is loaded; focal/centre/size entries are None when unstated."""

    index: int
    name: str
    image_path: Path
    c2w: np.ndarray  # OpenCV
    focal: dict[str, Any]  # the dict (frame or top level) that states the focal length
    focal_where: str  # "frame i: " or "" (top level), for error messages
    cx: float | None
    cy: float | None
    w: int | None
    h: int | None
    own_intrinsics: bool
    distortion: tuple[float, ...] | None  # DISTORTION_KEYS, when any is non-zero


def _read_json(path: Path) -> dict:
    """Parsed top-level object of a JSON file; InputError with line/column on syntax errors."""
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read file: {e}") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(path, f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(meta, dict):
        raise InputError(path, f"expected a JSON object at the top level, got {type(meta).__name__}")
    return meta


def _number(path: Path, where: str, key: str, value: Any) -> float:
    """A finite float from JSON (bools and strings are refused: they are always a mistake here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"{where}'{key}' must be a finite number, got {value!r}")
    return float(value)


def _positive(path: Path, where: str, key: str, value: Any) -> float:
    v = _number(path, where, key, value)
    if v <= 0:
        raise InputError(path, f"{where}'{key}' must be positive, got {value!r}")
    return v


def _size(path: Path, where: str, key: str, value: Any) -> int:
    v = _positive(path, where, key, value)
    if v != int(v):
        raise InputError(path, f"{where}'{key}' must be a whole number of pixels, got {value!r}")
    return int(v)


def _check_camera_model(path: Path, where: str, d: dict) -> None:
    """Refuse camera models and distortion terms we would otherwise silently render wrongly."""
    model = d.get("camera_model")
    if model is not None and (not isinstance(model, str) or model.upper() not in SUPPORTED_MODELS):
        raise InputError(
            path,
            f"{where}camera_model {model!r} is not supported (only {', '.join(SUPPORTED_MODELS)}); "
            "convert the images to pinhole (undistorted, perspective) first",
        )
    if d.get("is_fisheye"):
        raise InputError(path, f"{where}fisheye cameras ('is_fisheye') are not supported")
    if "k4" in d and _number(path, where, "k4", d["k4"]) != 0.0:
        raise InputError(
            path,
            f"{where}'k4' = {d['k4']} (nerfstudio's r^8 radial term) is not supported, only k1, k2, k3, "
            "p1, p2; undistort the images first (e.g. COLMAP image_undistorter)",
        )


def _distortion(path: Path, where: str, d: dict) -> tuple[float, ...] | None:
    """(k1, k2, p1, p2, k3) when any is non-zero, else None (a pinhole camera)."""
    coeffs = tuple(_number(path, where, k, d[k]) if k in d else 0.0 for k in DISTORTION_KEYS)
    return coeffs if any(coeffs) else None


def _focal(path: Path, where: str, d: dict, w: int, h: int) -> tuple[float, float]:
    """(fx, fy) in pixels from fl_x/fl_y, camera_angle_x/y (radians) or x_fov/y_fov (degrees)."""

    def from_keys(keys: tuple[str, str, str], size: int) -> float | None:
        fl, angle, fov = keys
        if fl in d:
            return _positive(path, where, fl, d[fl])
        if angle in d:
            a = _positive(path, where, angle, d[angle])
            if a >= math.pi:
                raise InputError(path, f"{where}'{angle}' is in radians and must be < pi, got {a}")
            return 0.5 * size / math.tan(0.5 * a)
        if fov in d:
            a = _positive(path, where, fov, d[fov])
            if a >= 180.0:
                raise InputError(path, f"{where}'{fov}' is in degrees and must be < 180, got {a}")
            return 0.5 * size / math.tan(math.radians(0.5 * a))
        return None

    fx = from_keys(FOCAL_X_KEYS, w)
    fy = from_keys(FOCAL_Y_KEYS, h)
    if fx is None and fy is None:
        raise InputError(path, f"{where}missing key 'fl_x' (or 'camera_angle_x' / 'x_fov'): no focal length")
    return (fx if fx is not None else fy), (fy if fy is not None else fx)  # type: ignore[return-value]


def _matrix(path: Path, where: str, value: Any) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{where}'transform_matrix' is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise InputError(path, f"{where}'transform_matrix' must be 4x4, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise InputError(path, f"{where}'transform_matrix' contains NaN or infinity")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        bottom = m[3].tolist()
        raise InputError(path, f"{where}'transform_matrix' bottom row must be [0, 0, 0, 1], got {bottom}")
    return m


def _image_path(json_path: Path, where: str, file_path: str) -> Path:
    """The image a `file_path` names (relative to the JSON's folder); tries common extensions if missing."""
    p = json_path.parent / file_path
    if p.is_file():
        return p
    for ext in IMAGE_EXTENSIONS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    tried = ", ".join(IMAGE_EXTENSIONS)
    raise InputError(p, f"image file not found ({where}of {json_path.name}; also tried adding {tried})")


def _parse_frames(json_path: Path, meta: dict) -> list[_Frame]:
    """Validate `frames` and resolve per-frame vs shared intrinsics (a frame's own keys win)."""
    if "frames" not in meta:
        raise InputError(json_path, "missing key 'frames'")
    frames = meta["frames"]
    if not isinstance(frames, list):
        raise InputError(json_path, "'frames' must be a list")
    if not frames:
        raise InputError(json_path, "no frames ('frames' is empty)")
    _check_camera_model(json_path, "", meta)
    out = []
    for i, fr in enumerate(frames):
        where = f"frame {i}: "
        if not isinstance(fr, dict):
            raise InputError(json_path, f"{where}expected an object, got {type(fr).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise InputError(json_path, f"{where}missing key '{key}'")
        name = fr["file_path"]
        if not isinstance(name, str) or not name:
            raise InputError(json_path, f"{where}'file_path' must be a non-empty string")
        merged = {**meta, **fr}
        _check_camera_model(json_path, where, fr)  # the top level was checked above
        own_focal = any(k in fr for k in (*FOCAL_X_KEYS, *FOCAL_Y_KEYS))
        if not own_focal and not any(k in meta for k in (*FOCAL_X_KEYS, *FOCAL_Y_KEYS)):
            raise InputError(
                json_path, f"{where}missing key 'fl_x' (or 'camera_angle_x' / 'x_fov'), here or at top level"
            )
        w = _size(json_path, where, "w", merged["w"]) if "w" in merged else None
        h = _size(json_path, where, "h", merged["h"]) if "h" in merged else None
        out.append(
            _Frame(
                index=i,
                name=name,
                image_path=_image_path(json_path, where, name),
                c2w=opengl_to_opencv(_matrix(json_path, where, fr["transform_matrix"])),
                focal=fr if own_focal else meta,
                focal_where=where if own_focal else "",
                cx=_number(json_path, where, "cx", merged["cx"]) if "cx" in merged else None,
                cy=_number(json_path, where, "cy", merged["cy"]) if "cy" in merged else None,
                w=w,
                h=h,
                own_intrinsics=any(k in fr for k in INTRINSIC_KEYS),
                distortion=_distortion(json_path, where, merged),
            )
        )
    return out


def _undistort(json_path: Path, fr: _Frame, rgb: np.ndarray, k: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The frame's image resampled to a pinhole camera, and that camera's (fx, fy, cx, cy)."""
    try:
        return undistort_opencv(rgb, k, fr.distortion)
    except ValueError as e:
        where = f"{json_path.name} frame {fr.index}"
        raise InputError(fr.image_path, f"cannot undistort ({where}): {e}") from None


def _load_frames(
    json_path: Path, frames: list[_Frame]
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, bool]:
    """Images (alpha composited on white), intrinsics (N,4), sizes (N,2) and whether any had alpha."""
    images, intrinsics, sizes = [], [], []
    any_alpha = False
    shared_size: tuple[int, int, _Frame] | None = None
    for fr in frames:
        where = f"frame {fr.index}: "
        rgb, alpha = read_image_with_alpha(fr.image_path)
        ih, iw = rgb.shape[:2]
        if (fr.w is not None and fr.w != iw) or (fr.h is not None and fr.h != ih):
            stated = f"w={fr.w if fr.w is not None else '?'}, h={fr.h if fr.h is not None else '?'}"
            raise InputError(
                fr.image_path,
                f"image is {iw}x{ih} (WxH) but {json_path.name} {where}states {stated}; "
                "resize the image or fix the intrinsics",
            )
        if not fr.own_intrinsics:
            if shared_size is None:
                shared_size = (iw, ih, fr)
            elif shared_size[:2] != (iw, ih):
                first = shared_size[2]
                raise InputError(
                    json_path,
                    f"images have different sizes ({first.name} is {shared_size[0]}x{shared_size[1]}, "
                    f"{fr.name} is {iw}x{ih}) but share one set of intrinsics; give each frame its own "
                    "'w', 'h', 'fl_x', 'fl_y', 'cx', 'cy' or resize the images",
                )
        if alpha is not None:
            rgb = composite_on_white(rgb, alpha)
            any_alpha = True
        fx, fy = _focal(json_path, fr.focal_where, fr.focal, iw, ih)
        k = (fx, fy, fr.cx if fr.cx is not None else iw / 2.0, fr.cy if fr.cy is not None else ih / 2.0)
        if fr.distortion is not None:
            rgb, k = _undistort(json_path, fr, rgb, k)
        images.append(rgb)
        intrinsics.append(tuple(k))
        sizes.append((rgb.shape[1], rgb.shape[0]))
    return images, np.asarray(intrinsics, dtype=np.float64), np.asarray(sizes, dtype=np.int64), any_alpha


def _norm_name(name: str) -> str:
    """Path spelling used to match split lists to frames ('./images/a.png' == 'images/a.png')."""
    return os.path.normpath(name.replace("\\", "/")).replace("\\", "/")


def _split(json_path: Path, meta: dict, frames: list[_Frame]) -> tuple[list[int], list[int]]:
    """(train_ids, test_ids): the file's own lists if any, else every 8th listed frame is a test view."""
    lists = {k: meta[k] for k in ("train_filenames", "test_filenames") if k in meta}
    if not lists:
        if len(frames) < 2:
            raise InputError(json_path, "only 1 frame: need at least 2 (the first frame is a test view)")
        return every_nth_split(len(frames))
    lookup: dict[str, int] = {}
    for fr in frames:
        lookup.setdefault(_norm_name(fr.name), fr.index)
        rel = os.path.relpath(fr.image_path, json_path.parent)
        lookup.setdefault(_norm_name(rel), fr.index)
    ids: dict[str, list[int]] = {}
    for key, names in lists.items():
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise InputError(json_path, f"'{key}' must be a list of file names")
        for n in names:
            if _norm_name(n) not in lookup:
                raise InputError(json_path, f"'{key}' lists {n!r}, which is no frame's file_path")
        ids[key] = sorted({lookup[_norm_name(n)] for n in names})
    everything = set(range(len(frames)))
    if "train_filenames" in ids:
        train = ids["train_filenames"]
        test = ids.get("test_filenames", sorted(everything - set(train)))
    else:
        test = ids["test_filenames"]
        train = sorted(everything - set(test))
    if not train:
        raise InputError(json_path, "no training views (the split lists leave no frame for training)")
    both = set(train) & set(test)
    if both:
        name = frames[min(both)].name
        raise InputError(json_path, f"frame {name!r} is in both train_filenames and test_filenames")
    return train, test


def _scene_extras(json_path: Path, meta: dict) -> dict[str, Any]:
    """Our own optional keys: 'aabb' -> scene_box, 'near_far', 'forward_facing' ('background': extras)."""
    out: dict[str, Any] = {}
    if "aabb" in meta:
        try:
            box = np.asarray(meta["aabb"], dtype=np.float64)
        except (TypeError, ValueError):
            box = np.zeros(0)
        if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[0] < box[1]).all():
            raise InputError(json_path, "'aabb' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], min < max")
        out["scene_box"] = (tuple(float(v) for v in box[0]), tuple(float(v) for v in box[1]))
    if "near_far" in meta:
        nf = meta["near_far"]
        if not isinstance(nf, list) or len(nf) != 2:
            raise InputError(json_path, "'near_far' must be [near, far]")
        near = _number(json_path, "", "near_far", nf[0])
        far = _number(json_path, "", "near_far", nf[1])
        if not 0.0 <= near < far:
            raise InputError(json_path, f"'near_far' must satisfy 0 <= near < far, got {nf}")
        out["near_far"] = (near, far)
    if "forward_facing" in meta:
        ff = meta["forward_facing"]
        if not isinstance(ff, bool):
            raise InputError(json_path, f"'forward_facing' must be true or false, got {ff!r}")
        out["forward_facing"] = ff
    return out


def _initial_exposures(json_path: Path, frames: list[dict]) -> np.ndarray | None:
    """Per-frame `exposure_init_ev` (our key, written by `process` from EXIF) when every frame has one."""
    if not all("exposure_init_ev" in fr for fr in frames):
        return None
    return np.array(
        [
            _number(json_path, f"frame {i}: ", "exposure_init_ev", fr["exposure_init_ev"])
            for i, fr in enumerate(frames)
        ]
    )


def _load_nerfstudio(json_path: Path) -> SceneData:
    meta = _read_json(json_path)
    frames = _parse_frames(json_path, meta)
    images, intrinsics, sizes, any_alpha = _load_frames(json_path, frames)
    train, test = _split(json_path, meta, frames)
    cameras = Cameras(np.stack([f.c2w for f in frames]), intrinsics, sizes)
    check_cameras(json_path, cameras, [f.name for f in frames])
    extras: dict[str, Any] = {"layout": "nerfstudio"}
    if any_alpha:
        extras["alpha_background"] = "white"
    if "background" in meta:  # our own key: the radiance seen where rays leave the scene
        value = _number(json_path, "", "background", meta["background"])
        if value < 0:
            raise InputError(json_path, f"'background' must be >= 0, got {value}")
        extras["background"] = value
    initial_ev = _initial_exposures(json_path, meta["frames"])
    if initial_ev is not None:
        extras["exposure_init_ev"] = initial_ev
    return SceneData(
        images=images,
        cameras=cameras,
        names=[f.name for f in frames],
        train_ids=train,
        test_ids=test,
        source=json_path,
        extras=extras,
        **_scene_extras(json_path, meta),
    )


def _load_blender(folder: Path) -> SceneData:
    parts = []
    for fname in BLENDER_FILES:
        p = folder / fname
        if not p.exists():
            raise InputError(p, "file not found (a Blender scene needs transforms_train.json and _test.json)")
        meta = _read_json(p)
        if "camera_angle_x" not in meta:
            raise InputError(p, "missing key 'camera_angle_x'")
        frames = _parse_frames(p, meta)
        loaded = _load_frames(p, frames)
        cameras = Cameras(np.stack([f.c2w for f in frames]), loaded[1], loaded[2])
        check_cameras(p, cameras, [f.name for f in frames])
        parts.append((p, frames, loaded))
    n_train = len(parts[0][1])
    n_test = len(parts[1][1])
    return SceneData(
        images=[im for _, _, loaded in parts for im in loaded[0]],
        cameras=Cameras(
            np.stack([f.c2w for _, frames, _ in parts for f in frames]),
            np.concatenate([loaded[1] for _, _, loaded in parts]),
            np.concatenate([loaded[2] for _, _, loaded in parts]),
        ),
        names=[f.name for _, frames, _ in parts for f in frames],
        train_ids=list(range(n_train)),
        test_ids=list(range(n_train, n_train + n_test)),
        source=folder,
        scene_box=BLENDER_BOX,
        forward_facing=False,
        extras={"layout": "blender", "alpha_background": "white"},
    )


def load_transforms(path: str | Path) -> SceneData:
    """Load a nerfstudio / instant-ngp `transforms.json` (file or folder) or a Blender synthetic folder.

    A folder with `transforms.json` is nerfstudio; with `transforms_train.json` it is Blender. A path to
    `transforms_train.json` / `_test` / `_val` itself also means the Blender folder it lives in.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_dir():
        if (path / NERFSTUDIO_FILE).is_file():
            return _load_nerfstudio(path / NERFSTUDIO_FILE)
        if (path / BLENDER_FILES[0]).is_file():
            return _load_blender(path)
        raise InputError(path, f"folder has neither {NERFSTUDIO_FILE} nor {BLENDER_FILES[0]}")
    blender_names = (*BLENDER_FILES, "transforms_val.json")
    if path.name in blender_names and (path.parent / BLENDER_FILES[0]).is_file():
        return _load_blender(path.parent)
    return _load_nerfstudio(path)
