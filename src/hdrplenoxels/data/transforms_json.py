"""Parser for `transforms.json` layouts: nerfstudio / instant-ngp, and the Blender NeRF-synthetic folders.

Poses in these files are camera-to-world in OpenGL axes; they are converted to OpenCV here, so the rest
of the code sees one convention. Everything a user could get wrong raises `InputError` naming the file.
`describe_transforms` reads only the JSON files; `load_transforms` then reads the images with
`images.load_images` (docs/design.md, "Data loading").

Lens distortion: OpenCV radial-tangential coefficients k1, k2, k3, p1, p2 (top level or per frame; also in
instant-ngp files without a camera_model) are undone at load time: each such image is resampled onto a
pinhole camera with COLMAP (`undistort.py`), which changes its size and principal point. Fisheye,
equirectangular and other models, and nerfstudio's r^8 term k4, are refused. Images with alpha are
composited onto white.

Scene bounds: 'aabb' ([[min], [max]], ours and instant-ngp's) is the box; else sdfstudio / nerfstudio's
'scene_box'; else, with instant-ngp's 'aabb_scale', NGP's unit cube (its 'scale' and 'offset' keys
honoured), and an aabb_scale > 1 is noted as content beyond the box. Our key 'sparse_points' names the
sparse points and the views that saw them (`sight_lines.py`), written by `process`.

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
from pathlib import Path
from typing import Any

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.description import CameraDescription, Distortion, SceneDescription, ViewDescription
from hdrplenoxels.data.images import load_images
from hdrplenoxels.data.protocol import every_nth_split
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.sight_lines import POINTS_KEY, SightLines, read_sight_lines
from hdrplenoxels.data.validate import check_pose
from hdrplenoxels.geometry.cameras import opengl_to_opencv

NERFSTUDIO_FILE = "transforms.json"
BLENDER_FILES = ("transforms_train.json", "transforms_test.json")
BLENDER_BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))  # svox2: radius 1 after scaling by 2/3
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV radial-tangential, in COLMAP's parameter order
# COLMAP's FULL_OPENCV: k4..k6 form a denominator and stay 0, leaving the OpenCV model.
FULL_OPENCV = "FULL_OPENCV"
NGP_SCALE, NGP_OFFSET = 0.33, 0.5  # instant-ngp's default mapping of the file's frame onto its unit cube
FOCAL_X_KEYS = ("fl_x", "camera_angle_x", "x_fov")
FOCAL_Y_KEYS = ("fl_y", "camera_angle_y", "y_fov")
# A frame carrying any of these has its own intrinsics (exempt from the shared-size check).
INTRINSIC_KEYS = (*FOCAL_X_KEYS, *FOCAL_Y_KEYS, "cx", "cy", "w", "h")


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


def _distortion(path: Path, where: str, d: dict) -> Distortion | None:
    """The OpenCV lens (k1, k2, p1, p2, k3) when any is non-zero, else None (a pinhole camera)."""
    coeffs = tuple(_number(path, where, k, d[k]) if k in d else 0.0 for k in DISTORTION_KEYS)
    return Distortion(FULL_OPENCV, (*coeffs, 0.0, 0.0, 0.0)) if any(coeffs) else None


def _focal(path: Path, where: str, d: dict, keys: tuple[str, str, str]) -> tuple[float | None, float | None]:
    """(focal in pixels, field of view in radians) of one axis from fl_*, camera_angle_* (radians) or *_fov
    (degrees), the first found; the loader turns a field of view into pixels once it knows the image size."""
    fl, angle, fov = keys
    if fl in d:
        return _positive(path, where, fl, d[fl]), None
    if angle in d:
        a = _positive(path, where, angle, d[angle])
        if a >= math.pi:
            raise InputError(path, f"{where}'{angle}' is in radians and must be < pi, got {a}")
        return None, a
    if fov in d:
        a = _positive(path, where, fov, d[fov])
        if a >= 180.0:
            raise InputError(path, f"{where}'{fov}' is in degrees and must be < 180, got {a}")
        return None, math.radians(a)
    return None, None


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


def _parse_frames(json_path: Path, meta: dict) -> list[ViewDescription]:
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
        focal, focal_where = (fr, where) if own_focal else (meta, "")
        image_path = _image_path(json_path, where, name)
        c2w = opengl_to_opencv(_matrix(json_path, where, fr["transform_matrix"]))
        fx, fov_x = _focal(json_path, focal_where, focal, FOCAL_X_KEYS)
        fy, fov_y = _focal(json_path, focal_where, focal, FOCAL_Y_KEYS)
        camera = CameraDescription(
            fx=fx,
            fy=fy,
            cx=_number(json_path, where, "cx", merged["cx"]) if "cx" in merged else None,
            cy=_number(json_path, where, "cy", merged["cy"]) if "cy" in merged else None,
            fov_x=fov_x,
            fov_y=fov_y,
            width=_size(json_path, where, "w", merged["w"]) if "w" in merged else None,
            height=_size(json_path, where, "h", merged["h"]) if "h" in merged else None,
            shared=not any(k in fr for k in INTRINSIC_KEYS),
            distortion=_distortion(json_path, where, merged),
        )
        check_pose(json_path, f"image {name!r}: ", c2w)
        out.append(ViewDescription(name, image_path, c2w, camera, json_path, f"{json_path.name} frame {i}"))
    return out


def _norm_name(name: str) -> str:
    """Path spelling used to match split lists to frames ('./images/a.png' == 'images/a.png')."""
    return os.path.normpath(name.replace("\\", "/")).replace("\\", "/")


def _split(json_path: Path, meta: dict, frames: list[ViewDescription]) -> tuple[list[int], list[int]]:
    """(train_ids, test_ids): the file's own lists if any, else every 8th listed frame is a test view."""
    lists = {k: meta[k] for k in ("train_filenames", "test_filenames") if k in meta}
    if not lists:
        if len(frames) < 2:
            raise InputError(json_path, "only 1 frame: need at least 2 (the first frame is a test view)")
        return every_nth_split(len(frames))
    lookup: dict[str, int] = {}
    for i, fr in enumerate(frames):
        lookup.setdefault(_norm_name(fr.name), i)
        rel = os.path.relpath(fr.image_path, json_path.parent)
        lookup.setdefault(_norm_name(rel), i)
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


def _box(json_path: Path, key: str, value: Any) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """A [[xmin, ymin, zmin], [xmax, ymax, zmax]] box, min < max on every axis."""
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        box = np.zeros(0)
    if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[0] < box[1]).all():
        raise InputError(json_path, f"'{key}' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], min < max")
    return tuple(float(v) for v in box[0]), tuple(float(v) for v in box[1])


def _ngp_unit_cube(json_path: Path, meta: dict) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """instant-ngp's unit cube in the file's frame: NGP maps a position p to p * scale + offset (defaults
    0.33 and 0.5 per axis) and models [0, 1]^3 at aabb_scale 1, so the cube is centred on
    (0.5 - offset) / scale with half-side 0.5 / scale."""
    scale = _positive(json_path, "", "scale", meta.get("scale", NGP_SCALE))
    offset = meta.get("offset", NGP_OFFSET)
    offsets = offset if isinstance(offset, list) else [offset] * 3
    if len(offsets) != 3:
        raise InputError(json_path, f"'offset' must be a number or [x, y, z], got {offset!r}")
    centre = np.array([(0.5 - _number(json_path, "", "offset", o)) / scale for o in offsets])
    half = 0.5 / scale
    return tuple((centre - half).tolist()), tuple((centre + half).tolist())


def _scene_bounds(json_path: Path, meta: dict) -> dict[str, Any]:
    """The scene box and where it came from: 'aabb' (ours and instant-ngp's: the box itself), else
    sdfstudio / nerfstudio's 'scene_box' ([[min], [max]] or {"aabb": ...}), else instant-ngp's unit cube
    when 'aabb_scale' is given; an aabb_scale > 1 says the content reaches that many times beyond it."""
    out: dict[str, Any] = {}
    notes: dict[str, str] = {}
    made_by_process = isinstance(meta.get("process"), dict)
    if "aabb" in meta:
        out["scene_box"] = _box(json_path, "aabb", meta["aabb"])
        if made_by_process:  # process records which points it fitted (older outputs do not)
            derived = meta["process"].get("box_from")
            older = "its sparse points (1-99th percentile, padded 10 %)"
            points = derived if isinstance(derived, str) else older
            notes["box"] = f"'aabb' that `process` derived from {points}"
            out["box_source"] = "points"
        else:
            notes["box"] = f"'aabb' in {json_path.name}"
    elif "scene_box" in meta:
        box = meta["scene_box"]
        out["scene_box"] = _box(json_path, "scene_box", box.get("aabb") if isinstance(box, dict) else box)
        notes["box"] = f"'scene_box' in {json_path.name}"
    if "aabb_scale" in meta:
        aabb_scale = _number(json_path, "", "aabb_scale", meta["aabb_scale"])
        if aabb_scale < 1:
            raise InputError(
                json_path, f"'aabb_scale' must be >= 1 (instant-ngp: 1, 2, 4, ... 128), got {aabb_scale}"
            )
        out["aabb_scale"] = aabb_scale
        if "scene_box" not in out:
            out["scene_box"] = _ngp_unit_cube(json_path, meta)
            notes["box"] = f"instant-ngp's unit cube ('aabb_scale' in {json_path.name})"
        if aabb_scale > 1:
            notes["beyond"] = f"aabb_scale {aabb_scale:g}: content reaches {aabb_scale:g}x beyond the box"
    if notes:
        out["bounds_notes"] = notes
    return out


def _scene_extras(json_path: Path, meta: dict) -> dict[str, Any]:
    """Our own optional keys: the scene box (`_scene_bounds`), 'near_far', 'forward_facing', 'background'."""
    out: dict[str, Any] = _scene_bounds(json_path, meta)
    if "near_far" in meta:
        nf = meta["near_far"]
        if not isinstance(nf, list) or len(nf) != 2:
            raise InputError(json_path, "'near_far' must be [near, far]")
        near = _number(json_path, "", "near_far", nf[0])
        far = _number(json_path, "", "near_far", nf[1])
        if not 0.0 <= near < far:
            raise InputError(json_path, f"'near_far' must satisfy 0 <= near < far, got {nf}")
        out["near_far"] = (near, far)
        out.setdefault("bounds_notes", {})["near_far"] = (
            "'near_far' that `process` derived from its sparse points' depths"
            if isinstance(meta.get("process"), dict)
            else f"'near_far' in {json_path.name}"
        )
    if "forward_facing" in meta:
        ff = meta["forward_facing"]
        if not isinstance(ff, bool):
            raise InputError(json_path, f"'forward_facing' must be true or false, got {ff!r}")
        out["forward_facing"] = ff
    if "background" in meta:  # the radiance seen where rays leave the scene
        value = _number(json_path, "", "background", meta["background"])
        if value < 0:
            raise InputError(json_path, f"'background' must be >= 0, got {value}")
        out["background_brightness"] = value
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


def _sight_lines(json_path: Path, meta: dict, views: list[ViewDescription]) -> SightLines | None:
    """The sparse points file our key 'sparse_points' names (relative to the JSON's folder), if any."""
    if POINTS_KEY not in meta:
        return None
    name = meta[POINTS_KEY]
    if not isinstance(name, str) or not name:
        raise InputError(json_path, f"'{POINTS_KEY}' must name a file, got {name!r}")
    return read_sight_lines(json_path.parent / name, [v.image_path.name for v in views])


def _describe_nerfstudio(json_path: Path) -> SceneDescription:
    """One `transforms.json`: its frames, split and our optional scene keys; alpha goes onto white."""
    meta = _read_json(json_path)
    views = _parse_frames(json_path, meta)
    train, test = _split(json_path, meta, views)
    return SceneDescription(
        sight_lines=_sight_lines(json_path, meta, views),
        layout="nerfstudio",
        source=json_path,
        views=views,
        train_ids=train,
        test_ids=test,
        alpha="white",
        exposure_init_ev=_initial_exposures(json_path, meta["frames"]),
        **_scene_extras(json_path, meta),
    )


def _describe_blender(folder: Path) -> SceneDescription:
    """The train and test files as one scene: train frames first, rendered on white in svox2's box."""
    parts = []
    for fname in BLENDER_FILES:
        p = folder / fname
        if not p.exists():
            raise InputError(p, "file not found (a Blender scene needs transforms_train.json and _test.json)")
        meta = _read_json(p)
        if "camera_angle_x" not in meta:
            raise InputError(p, "missing key 'camera_angle_x'")
        parts.append(_parse_frames(p, meta))
    n_train, n_test = len(parts[0]), len(parts[1])
    return SceneDescription(
        layout="blender",
        source=folder,
        views=parts[0] + parts[1],
        train_ids=list(range(n_train)),
        test_ids=list(range(n_train, n_train + n_test)),
        alpha="white",
        white_background=True,
        scene_box=BLENDER_BOX,
        forward_facing=False,
        bounds_notes={"box": "the Blender scenes' box (svox2's)"},
    )


def describe_transforms(path: str | Path) -> SceneDescription:
    """Describe a nerfstudio / instant-ngp `transforms.json` (file or folder) or a Blender synthetic folder.

    A folder with `transforms.json` is nerfstudio; with `transforms_train.json` it is Blender. A path to
    `transforms_train.json` / `_test` / `_val` itself also means the Blender folder it lives in.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_dir():
        if (path / NERFSTUDIO_FILE).is_file():
            return _describe_nerfstudio(path / NERFSTUDIO_FILE)
        if (path / BLENDER_FILES[0]).is_file():
            return _describe_blender(path)
        raise InputError(path, f"folder has neither {NERFSTUDIO_FILE} nor {BLENDER_FILES[0]}")
    blender_names = (*BLENDER_FILES, "transforms_val.json")
    if path.name in blender_names and (path.parent / BLENDER_FILES[0]).is_file():
        return _describe_blender(path.parent)
    return _describe_nerfstudio(path)


def load_transforms(path: str | Path, downscale: int = 1) -> SceneData:
    """Load the scene `describe_transforms(path)` describes, images included (`downscale` times smaller)."""
    return load_images(describe_transforms(path), downscale)
