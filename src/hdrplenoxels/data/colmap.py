"""COLMAP models (binary or text) as a scene: cameras, poses, and bounds from the sparse points.

Accepted folders: `DATA/sparse/0/`, `DATA/sparse/` or `DATA/` itself holding `cameras.bin|txt`, with the
photos in `DATA/images/`. Only registered images are loaded, sorted by name (every 8th is a test view).
Distorted cameras are undistorted to pinhole at load time. Photos' EXIF exposure, when every image has
it, becomes `extras["exposure_init_ev"]`: what the EVs' scale is fitted to, never pinned (docs/method.md,
"Gauge"). The description (`describe_colmap`) reads the model and the photos' EXIF headers only;
`load_colmap` then reads the pixels with `images.load_images` (docs/design.md, "Data loading").
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_write_files
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.bounds import image_depth_bounds, point_box, scene_near_far, upright_frame
from hdrplenoxels.data.description import CameraDescription, Distortion, SceneDescription, ViewDescription
from hdrplenoxels.data.exif import read_exif_exposure
from hdrplenoxels.data.images import load_images
from hdrplenoxels.data.protocol import every_nth_split
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.data.undistort import is_pinhole, split_params
from hdrplenoxels.data.validate import check_pose
from hdrplenoxels.geometry.cameras import Cameras

MODEL_FILES = ("cameras.bin", "cameras.txt")
MODEL_SUBDIRS = ("sparse/0", "sparse", ".")
MIN_TRACK = 2  # a point seen by one view only is no triangulated point (and no evidence for the box)


def is_colmap_model(folder: Path) -> bool:
    return any((folder / f).is_file() for f in MODEL_FILES)


def find_colmap_model(path: Path) -> Path | None:
    """The model folder of a COLMAP dataset at `path`, or None when there is none."""
    for sub in MODEL_SUBDIRS:
        if is_colmap_model(path / sub):
            return (path / sub).resolve()
    return None


def _images_folder(root: Path, model_dir: Path) -> Path:
    """`images/` beside `sparse/` (COLMAP's own layout), searched upwards from the model folder."""
    for folder in (root, *model_dir.parents):
        if (folder / "images").is_dir():
            return folder / "images"
        if folder == root.resolve():
            break
    raise InputError(root, "COLMAP model found but no images/ folder beside it")


def read_reconstruction(model_dir: Path):
    """pycolmap.Reconstruction of a model folder; corrupt files become an InputError."""
    import pycolmap

    for name in ("cameras", "images", "points3D"):
        if not any((model_dir / f"{name}{ext}").is_file() for ext in (".bin", ".txt")):
            raise InputError(model_dir, f"COLMAP model is incomplete: no {name}.bin or {name}.txt")
    for name in BINARY_MIN_RECORD:
        if (model_dir / name).is_file():
            _check_binary_counts(model_dir / name)
    try:
        rec = pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises ValueError / RuntimeError with COLMAP's own message
        raise InputError(
            model_dir, f"cannot read the COLMAP model: {str(e).strip().splitlines()[-1]}"
        ) from None
    try:
        [im.name for im in rec.images.values()]  # pycolmap decodes a name only when it is read
    except UnicodeDecodeError:
        raise InputError(model_dir, "an image name in the COLMAP model is not UTF-8 text") from None
    return rec


# Smallest record of each binary model file. COLMAP reads as many records as a file's counts declare, even
# past its end: a damaged count makes it allocate without bound, so counts are checked against the size first.
BINARY_MIN_RECORD = {
    "cameras.bin": 24,
    "images.bin": 73,
    "points3D.bin": 51,
    "rigs.bin": 4,
    "frames.bin": 4,
}


def _check_binary_counts(path: Path) -> None:
    """Every count in `path` fits in the bytes that follow it, nested ones too (each record is walked)."""
    raw = path.read_bytes()

    def fail(what: str, at: int) -> InputError:
        return InputError(
            path, f"damaged COLMAP file: {what} at byte {at} runs past the end ({len(raw)} bytes)"
        )

    if len(raw) < 8:
        raise fail("the record count", 0)
    (count,) = struct.unpack_from("<Q", raw, 0)
    if count * BINARY_MIN_RECORD[path.name] > len(raw) - 8:
        raise fail(f"record count {count}", 0)
    at = 8
    walk = _RECORD_WALKS.get(path.name)
    for i in range(count if walk else 0):
        at = walk(raw, at, lambda what, where, i=i: fail(f"record {i}'s {what}", where))


def _need(raw: bytes, at: int, size: int, fail, what: str) -> int:
    if at + size > len(raw):
        raise fail(what, at)
    return at + size


def _walk_image(raw: bytes, at: int, fail) -> int:
    end = raw.find(b"\0", at + 64)  # id, pose and camera id (64 bytes), then the name up to a NUL
    at = _need(raw, end + 1 if end >= 0 else len(raw) + 1, 8, fail, "name or 2-D point count")
    return _need(raw, at, 24 * struct.unpack_from("<Q", raw, at - 8)[0], fail, "2-D points")


def _walk_point(raw: bytes, at: int, fail) -> int:
    at = _need(raw, at, 51, fail, "fixed part")  # id, xyz, rgb, error, track length
    return _need(raw, at, 8 * struct.unpack_from("<Q", raw, at - 8)[0], fail, "track")


def _walk_rig(raw: bytes, at: int, fail) -> int:
    at = _need(raw, at, 16, fail, "fixed part")  # id, sensor count, reference sensor
    for _ in range(max(struct.unpack_from("<I", raw, at - 12)[0] - 1, 0)):
        at = _need(raw, at, 9, fail, "sensor")  # type, id, has-pose flag, then the pose if it has one
        at = _need(raw, at, 56 * (raw[at - 1] != 0), fail, "sensor pose")
    return at


def _walk_frame(raw: bytes, at: int, fail) -> int:
    at = _need(raw, at, 68, fail, "fixed part")  # id, rig id, pose, data count
    return _need(raw, at, 16 * struct.unpack_from("<I", raw, at - 4)[0], fail, "data ids")


_RECORD_WALKS = {
    "images.bin": _walk_image,
    "points3D.bin": _walk_point,
    "rigs.bin": _walk_rig,
    "frames.bin": _walk_frame,
}


def _pose(image) -> np.ndarray:
    """OpenCV camera-to-world (4, 4) of a registered pycolmap image."""
    w2c = np.eye(4)
    w2c[:3, :4] = image.cam_from_world().matrix()
    return np.linalg.inv(w2c)


def _observed_points(rec, image, source: Path) -> np.ndarray:
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    try:
        return np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    except KeyError as e:  # pycolmap reads a text model whose images name points it does not hold
        raise InputError(
            source, f"damaged COLMAP model: image {image.name!r} observes 3-D point {e.args[0]}, not in it"
        ) from None


def _camera(cam) -> CameraDescription:
    """A COLMAP camera as stated: the image must have its size; a non-pinhole model is undone at load."""
    (fx, fy, cx, cy), coeffs = split_params(cam)
    distortion = None if is_pinhole(cam.model_name, coeffs) else Distortion(cam.model_name, coeffs)
    return CameraDescription(
        fx=fx, fy=fy, cx=cx, cy=cy, width=cam.width, height=cam.height, distortion=distortion
    )


def _tracked_ids(rec) -> list[int]:
    """Ids of the points seen by at least `MIN_TRACK` views, in the model's order."""
    return [i for i, p in rec.points3D.items() if p.track.length() >= MIN_TRACK]


def tracked_points(rec) -> np.ndarray:
    """(P, 3) positions of the points seen by at least `MIN_TRACK` views."""
    return np.array([rec.points3D[i].xyz for i in _tracked_ids(rec)], dtype=np.float64).reshape(-1, 3)


def _sight_lines(rec, registered: list) -> SightLines:
    """The tracked points (`tracked_points`) and which of the `registered` images saw each."""
    ids = _tracked_ids(rec)
    row = {pid: k for k, pid in enumerate(ids)}
    view, point = [], []
    for v, im in enumerate(registered):
        for p in im.points2D:
            if p.has_point3D() and p.point3D_id in row:
                view.append(v)
                point.append(row[p.point3D_id])
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    return SightLines(xyz, np.array(view, dtype=np.int64), np.array(point, dtype=np.int64))


def model_point_box(root: Path) -> tuple[tuple[tuple[float, ...], tuple[float, ...]], str] | None:
    """The robust box (`bounds.point_box`) of the COLMAP model kept in a dataset folder (LLFF and
    mip-NeRF 360 folders keep `sparse/0`), with its note; None without a model or enough points."""
    model_dir = next((root / d for d in MODEL_SUBDIRS[:2] if is_colmap_model(root / d)), None)
    if model_dir is None:
        return None
    points = tracked_points(read_reconstruction(model_dir))
    box = point_box(points)
    if box is None:
        return None
    return box, f"{_box_note(len(points))} of {model_dir.relative_to(root)}/"


def _box_note(n_points: int) -> str:
    return f"{n_points:,} sparse points seen by >= {MIN_TRACK} views (1-99th percentile, padded 10 %)"


def _bounds_notes(n_points: int, box: bool, near_far: bool) -> dict[str, str]:
    notes = {}
    if box:
        notes["box"] = _box_note(n_points)
    if near_far:
        notes["near_far"] = "the sparse points' depths in each view (0.1-99.9th percentile)"
    return notes


def describe_reconstruction(rec, images_dir: Path, source: Path, upright: bool = False) -> SceneDescription:
    """Every registered image of `rec` (photos in `images_dir`); with `upright`, in a frame turned upright
    and square with the points (see `bounds.upright_frame`)."""
    registered = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not registered:
        raise InputError(source, "the COLMAP model has no registered images")
    poses = np.stack([_pose(im) for im in registered])
    bounds = [
        image_depth_bounds(c2w, _observed_points(rec, im, source))
        for c2w, im in zip(poses, registered, strict=True)
    ]
    exif = [read_exif_exposure(images_dir / im.name) for im in registered]
    lines = _sight_lines(rec, registered)
    points = lines.points
    if upright:
        frame = upright_frame(poses, points)
        poses = frame @ poses
        points = points @ frame[:3, :3].T + frame[:3, 3]
        lines = SightLines(points, lines.view, lines.point)
    views = []
    for im, c2w in zip(registered, poses, strict=True):
        check_pose(source, f"image {im.name!r}: ", c2w)
        camera = _camera(rec.cameras[im.camera_id])
        views.append(
            ViewDescription(
                im.name, images_dir / im.name, c2w, camera, source, f"COLMAP camera {im.camera_id}"
            )
        )
    train, test = every_nth_split(len(views))
    known = all(e is not None for e in exif)
    box, near_far = point_box(points), scene_near_far(bounds)
    return SceneDescription(
        layout="colmap",
        source=source,
        views=views,
        train_ids=train,
        test_ids=test,
        scene_box=box,
        box_source="points",
        near_far=near_far,
        bounds_notes=_bounds_notes(len(points), box is not None, near_far is not None),
        exposure_init_ev=np.array([e.stops for e in exif]) if known else None,
        extras={"exif": [e.to_dict() for e in exif]} if known else {},
        sight_lines=lines,
    )


def scene_from_reconstruction(rec, images_dir: Path, source: Path, upright: bool = False) -> SceneData:
    """`describe_reconstruction` with its images loaded."""
    return load_images(describe_reconstruction(rec, images_dir, source, upright))


def describe_colmap(path: str | Path) -> SceneDescription:
    """Describe a COLMAP dataset folder (see the module docstring for the layouts found)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    model_dir = find_colmap_model(path)
    if model_dir is None:
        raise InputError(path, "no COLMAP model (cameras.bin or cameras.txt in sparse/0, sparse or here)")
    rec = read_reconstruction(model_dir)
    return describe_reconstruction(rec, _images_folder(path, model_dir), path)


def load_colmap(path: str | Path, downscale: int = 1) -> SceneData:
    """Load the scene `describe_colmap(path)` describes, images included (`downscale` times smaller)."""
    return load_images(describe_colmap(path), downscale)


def write_colmap(model_dir: str | Path, cameras: Cameras, names: list[str], text: bool = False) -> Path:
    """Write cameras (one PINHOLE camera per image) and poses as a COLMAP model without points (each file
    written beside the folder first, then moved in)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, name in enumerate(names):
        w, h = cameras.size(i)
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="PINHOLE", width=w, height=h, params=cameras.intrinsics[i].tolist(), camera_id=i + 1
            )
        )
        w2c = np.linalg.inv(cameras.c2w[i])
        image = pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    return atomic_write_files(model_dir, lambda tmp: rec.write_text(tmp) if text else rec.write_binary(tmp))
