"""LLFF-family layouts, read and written: LLFF `poses_bounds.npy`, its NeX / HDR-Plenoxels `hwf_cxcy.npy`
variant and HDR-NeRF `poses_bounds_exps.npy`.

Conventions (bmild/nerf `load_llff.py`; postech-ami/HDR-Plenoxels `opt/util/load_llff.py` and
`llff_dataset.py`; xhuangcv/hdr-nerf `load_real_llff.py`):
- A row is a flattened (row-major) 3x5 `[R | t | (H, W, f)]` followed by near, far. R's columns are the
  camera's down, right and backwards axes in world coordinates and t its centre (camera-to-world), so
  OpenCV x = right, y = down, z = -backwards. The principal point is the image centre, cx = W/2, cy = H/2.
- With `hwf_cxcy.npy` beside it a row is a 3x4 `[R | t]` plus near, far (14 values; 17 is accepted too,
  its hwf column then ignored). NeX and HDR-Plenoxels store ONE camera there, `[h, w, fx, fy, cx, cy]` of
  shape (6,) or (6, 1), and HDR-Plenoxels also takes 3 values `[h, w, f]`. HDR-Plenoxels casts rays through
  `arange + 0.5` as `(x - cx) / fx` with OpenCV axes, and NeX writes COLMAP's principal point: both are our
  convention, so cx, cy are used unchanged. We also read (N, 6), one row per image: our extension, which
  `write_llff_hwf_cxcy` emits only when the cameras differ.
- HDR-NeRF: 18 values per row, the 17 of LLFF then the exposure time in seconds; images in `input_images/`
  (`images/` is accepted). The exposure becomes `extras["exposure_init_ev"]` = log2(t), the stated
  exposure the tone mapper's scale is fitted to, never pinned.
- Images are the files of the image folder in sorted name order, one per row. An image smaller or larger
  than the stored H, W (LLFF's `images_8` copied into `images/`) scales fx, cx by the width ratio and fy, cy
  by the height ratio. Alpha is dropped, as LLFF and HDR-Plenoxels do.
- Poses stay in the file's world frame: no `bd_factor` rescaling, no recentring (scene setup does its own).
  `near_far` is (min near, max far); `forward_facing` is left to auto-detection. A COLMAP model kept in
  `sparse/0` (LLFF and mip-NeRF 360 folders) gives the scene box from its points, in the poses' frame.
`describe_llff` reads only the .npy files and lists the image folder; `load_llff` then reads the images
with `images.load_images` (docs/design.md, "Data loading").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from hdrplenoxels.core.atomic import atomic_path
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.npy_files import check_npy_file
from hdrplenoxels.data.description import CameraDescription, SceneDescription, ViewDescription
from hdrplenoxels.data.images import load_images
from hdrplenoxels.data.protocol import every_nth_split
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.validate import check_pose
from hdrplenoxels.data.writers import check_image_names, write_images
from hdrplenoxels.geometry.cameras import Cameras

POSES_BOUNDS = "poses_bounds.npy"
HWF_CXCY = "hwf_cxcy.npy"
POSES_BOUNDS_EXPS = "poses_bounds_exps.npy"
LLFF_FILES = (POSES_BOUNDS_EXPS, POSES_BOUNDS)  # the HDR-NeRF file wins: it carries exposures too
IMAGE_DIRS = {POSES_BOUNDS: ("images",), POSES_BOUNDS_EXPS: ("input_images", "images")}
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
NPY_MAGIC = b"\x93NUMPY"
Images = Sequence[np.ndarray] | None
Names = Sequence[str] | None
CENTRED_TOLERANCE = 1e-9  # relative: plain LLFF can only state square pixels and a centred principal point


# ---- conventions -----------------------------------------------------------------------------------


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """(3, 4) `[down, right, backwards | centre]` of an OpenCV camera-to-world (4, 4)."""
    return np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]], axis=1)


def llff_to_opencv(mat: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (4, 4) of an LLFF (3, 4) `[down, right, backwards | centre]`."""
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = mat[:, 1], mat[:, 0], -mat[:, 2], mat[:, 3]
    return c2w


# ---- writers ---------------------------------------------------------------------------------------


def _bounds_array(cameras: Cameras, bounds: ArrayLike) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (len(cameras), 2):
        raise ValueError(f"bounds must be (near, far) per camera, shape ({len(cameras)}, 2), got {b.shape}")
    return b


def _check_plain_llff(cameras: Cameras) -> None:
    """Plain LLFF stores one focal and no principal point: refuse cameras it would misdescribe."""
    for i in range(len(cameras)):
        fx, fy, cx, cy = cameras.intrinsics[i]
        w, h = cameras.size(i)
        if not np.allclose([fy, cx, cy], [fx, w / 2, h / 2], rtol=CENTRED_TOLERANCE, atol=0.0):
            raise ValueError(
                f"camera {i} has fx={fx}, fy={fy}, cx={cx}, cy={cy} for {w}x{h}: plain LLFF needs fx == fy "
                "and a centred principal point; use write_llff_hwf_cxcy"
            )


def llff_poses_bounds(cameras: Cameras, bounds: ArrayLike) -> np.ndarray:
    """(N, 17): 3x5 [R | t | (H, W, f)] with LLFF's [down, right, backwards] columns, then near, far."""
    _check_plain_llff(cameras)
    b = _bounds_array(cameras, bounds)
    rows = []
    for i in range(len(cameras)):
        w, h = cameras.size(i)
        hwf = np.array([h, w, cameras.intrinsics[i, 0]])
        mat = np.concatenate([opencv_to_llff(cameras.c2w[i]), hwf[:, None]], axis=1)
        rows.append(np.concatenate([mat.ravel(), b[i]]))
    return np.asarray(rows, dtype=np.float64)


def _hwf_cxcy_rows(cameras: Cameras) -> np.ndarray:
    """(N, 6) h, w, fx, fy, cx, cy per camera."""
    hw = cameras.sizes[:, ::-1].astype(np.float64)
    return np.concatenate([hw, cameras.intrinsics], axis=1)


def _save_npy(path: Path, arr: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        np.save(tmp, arr)
    return path


def _write_layout(
    folder: str | Path,
    npy_name: str,
    arr: np.ndarray,
    images: Images,
    image_names: Names,
    sidecar: np.ndarray | None = None,
) -> Path:
    """Images (into the layout's image folder), `hwf_cxcy.npy` when given, then the poses file last, so
    a poses file on disk means a complete dataset."""
    folder = Path(folder)
    names = check_image_names(len(arr), image_names)
    if names != sorted(names):
        raise ValueError(f"LLFF pairs rows with images in sorted name order: names must sort, got {names}")
    if images is not None:
        write_images(folder / IMAGE_DIRS[npy_name][0], names, images)
    if sidecar is not None:
        _save_npy(folder / HWF_CXCY, sidecar)
    return _save_npy(folder / npy_name, arr)


def write_llff(
    folder: str | Path, cameras: Cameras, bounds: ArrayLike, images: Images = None, image_names: Names = None
) -> Path:
    """Write `poses_bounds.npy` (and `images/` when `images` are given); returns the .npy path.

    `image_names` (default view_000.png, ...) must sort in camera order: LLFF pairs rows with the sorted
    file names. Raises ValueError for cameras plain LLFF cannot state (see `write_llff_hwf_cxcy`).
    """
    return _write_layout(folder, POSES_BOUNDS, llff_poses_bounds(cameras, bounds), images, image_names)


def write_llff_hwf_cxcy(
    folder: str | Path, cameras: Cameras, bounds: ArrayLike, images: Images = None, image_names: Names = None
) -> Path:
    """Write the HDR-Plenoxels variant: (N, 14) `poses_bounds.npy` plus `hwf_cxcy.npy`.

    `hwf_cxcy.npy` is the (6, 1) single camera NeX and HDR-Plenoxels read when all cameras share their
    intrinsics and size, else (N, 6) per image (which only this package reads). Returns the poses path.
    """
    b = _bounds_array(cameras, bounds)
    poses = np.stack([opencv_to_llff(c) for c in cameras.c2w]).reshape(len(cameras), 12)
    hwf = _hwf_cxcy_rows(cameras)
    sidecar = hwf[0].reshape(6, 1) if (hwf == hwf[0]).all() else hwf
    arr = np.concatenate([poses, b], axis=1)
    return _write_layout(folder, POSES_BOUNDS, arr, images, image_names, sidecar)


def write_hdrnerf(
    folder: str | Path,
    cameras: Cameras,
    bounds: ArrayLike,
    exposure_times: ArrayLike,
    images: Images = None,
    image_names: Names = None,
) -> Path:
    """Write HDR-NeRF's `poses_bounds_exps.npy` (LLFF rows + exposure time in seconds) and `input_images/`."""
    t = np.asarray(exposure_times, dtype=np.float64).reshape(-1)
    if t.shape != (len(cameras),) or not (t > 0).all():
        raise ValueError(f"exposure_times must be {len(cameras)} positive seconds, got {t.tolist()}")
    arr = np.concatenate([llff_poses_bounds(cameras, bounds), t[:, None]], axis=1)
    return _write_layout(folder, POSES_BOUNDS_EXPS, arr, images, image_names)


# ---- reader ----------------------------------------------------------------------------------------


def _read_npy(path: Path) -> np.ndarray:
    """A numeric float64 array from a .npy file (pickled objects are never loaded)."""
    try:
        with path.open("rb") as f:
            if f.read(len(NPY_MAGIC)) != NPY_MAGIC:
                raise InputError(path, "not a NumPy .npy file (no .npy header)")
        check_npy_file(path)
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise InputError(path, f"cannot read .npy array: {e}") from None
    if not isinstance(arr, np.ndarray) or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(path, f"expected a numeric array, got {getattr(arr, 'dtype', type(arr).__name__)}")
    return arr.astype(np.float64)


def _check_finite_rows(path: Path, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    if bad.any():
        raise InputError(path, f"row {int(np.argmax(bad))} contains NaN or infinity")


def _read_table(path: Path, widths: tuple[int, ...], layout: str) -> np.ndarray:
    """The (N, width) array of a poses file, with its shape and values checked."""
    arr = _read_npy(path)
    if arr.ndim != 2 or arr.shape[1] not in widths or len(arr) == 0:
        want = " or ".join(f"(N, {w})" for w in widths)
        raise InputError(path, f"expected a {want} array ({layout}), got shape {arr.shape}")
    _check_finite_rows(path, arr)
    return arr


def _check_stored_camera(path: Path, where: str, hwf: np.ndarray) -> None:
    """Whole positive h, w and positive focal lengths in a stored (h, w, fx, fy, cx, cy)."""
    h, w, fx, fy = hwf[:4]
    if h <= 0 or w <= 0 or h != int(h) or w != int(w):
        raise InputError(path, f"{where}image size must be whole positive pixels, got h={h}, w={w}")
    if fx <= 0 or fy <= 0:
        raise InputError(path, f"{where}focal lengths must be positive, got fx={fx}, fy={fy}")


def _read_hwf_cxcy(path: Path, n: int) -> np.ndarray:
    """(N, 6) h, w, fx, fy, cx, cy from `hwf_cxcy.npy`: one shared camera, or one row per image."""
    arr = _read_npy(path)
    if not np.isfinite(arr).all():
        raise InputError(path, "contains NaN or infinity")
    per_image = n > 1 and arr.shape == (n, 6)
    flat = arr.reshape(-1) if arr.ndim == 1 or (arr.ndim == 2 and 1 in arr.shape) else np.zeros(0)
    if per_image:
        rows = arr
    elif flat.size == 6:
        rows = np.tile(flat, (n, 1))
    elif flat.size == 3:
        h, w, f = flat
        rows = np.tile([h, w, f, f, w / 2, h / 2], (n, 1))
    else:
        raise InputError(
            path,
            f"expected [h, w, fx, fy, cx, cy] (shape (6,) or (6, 1)), [h, w, f], or one such row per image "
            f"(shape ({n}, 6)), got shape {arr.shape}",
        )
    for i in range(n if per_image else 1):
        _check_stored_camera(path, f"row {i}: " if per_image else "", rows[i])
    return rows


@dataclass
class _Table:
    """A poses file parsed: LLFF pose matrices, the cameras as stored, bounds, HDR-NeRF exposure times."""

    layout: str
    mats: np.ndarray  # (N, 3, 4) [down, right, backwards | centre]
    stored: np.ndarray  # (N, 6) h, w, fx, fy, cx, cy
    bounds: np.ndarray  # (N, 2) near, far
    exposure_times: np.ndarray | None = None


def _llff_rows(npy: Path, arr: np.ndarray, layout: str) -> _Table:
    """The 17 LLFF values per row: 3x5 [R | t | (H, W, f)], near, far."""
    poses = arr[:, :15].reshape(-1, 3, 5)
    h, w, f = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
    stored = np.stack([h, w, f, f, w / 2, h / 2], axis=1)
    for i, row in enumerate(stored):
        _check_stored_camera(npy, f"row {i}: ", row)
    return _Table(layout, poses[:, :, :4], stored, arr[:, 15:17])


def _exposure_times(npy: Path, t: np.ndarray) -> np.ndarray:
    bad = t <= 0
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(npy, f"row {i}: exposure time (last column) must be positive seconds, got {t[i]}")
    return t


def _parse(npy: Path) -> _Table:
    """Read the poses file (and `hwf_cxcy.npy` beside it, when present) of any of the three layouts."""
    if npy.name == POSES_BOUNDS_EXPS:
        arr = _read_table(npy, (18,), "HDR-NeRF: 3x5 [R | t | hwf] pose, near, far, exposure time")
        table = _llff_rows(npy, arr, "hdrnerf")
        table.exposure_times = _exposure_times(npy, arr[:, 17])
        return table
    hwf_path = npy.parent / HWF_CXCY
    if hwf_path.is_file():
        arr = _read_table(npy, (14, 17), f"3x4 [R | t] pose, near, far; the cameras are in {HWF_CXCY}")
        cols = 4 if arr.shape[1] == 14 else 5
        mats = arr[:, : 3 * cols].reshape(-1, 3, cols)[:, :, :4]
        return _Table("llff_hwf_cxcy", mats, _read_hwf_cxcy(hwf_path, len(arr)), arr[:, -2:])
    arr = _read_table(npy, (17,), "LLFF: 3x5 [R | t | hwf] pose, near, far")
    return _llff_rows(npy, arr, "llff")


def _check_bounds(npy: Path, bounds: np.ndarray) -> None:
    bad = ~((bounds[:, 0] > 0) & (bounds[:, 1] > bounds[:, 0]))
    if bad.any():
        i = int(np.argmax(bad))
        near, far = bounds[i]
        raise InputError(npy, f"row {i}: depth bounds must satisfy 0 < near < far, got {near}, {far}")


def _locate(path: Path) -> Path:
    """The poses file a folder (or that file itself) holds."""
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_file():
        if path.name in LLFF_FILES:
            return path
        raise InputError(path, f"not an LLFF poses file (expected {POSES_BOUNDS} or {POSES_BOUNDS_EXPS})")
    for name in LLFF_FILES:
        if (path / name).is_file():
            return path / name
    raise InputError(path, f"folder has neither {POSES_BOUNDS} (LLFF) nor {POSES_BOUNDS_EXPS} (HDR-NeRF)")


def _image_files(npy: Path) -> tuple[Path, list[Path]]:
    """The layout's image folder and its images in sorted name order (the order rows refer to)."""
    dirs = IMAGE_DIRS[npy.name]
    for d in dirs:
        folder = npy.parent / d
        if folder.is_dir():
            files = [
                p
                for p in folder.iterdir()
                if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file()
            ]
            return folder, sorted(files, key=lambda p: p.name)
    wanted = " or ".join(f"{d}/" for d in dirs)
    raise InputError(npy.parent / dirs[0], f"image folder not found: {npy.name} needs its images in {wanted}")


def _camera(stored: np.ndarray) -> CameraDescription:
    """The stored (h, w, fx, fy, cx, cy); an image of another size is a resized copy (module docstring)."""
    h, w, fx, fy, cx, cy = (float(v) for v in stored)
    return CameraDescription(fx=fx, fy=fy, cx=cx, cy=cy, width=int(w), height=int(h), resized_copies=True)


def _model_box(folder: Path):
    """The box of the sparse points of the COLMAP model an LLFF folder keeps (`sparse/0`), which is in
    the poses' frame: LLFF's poses are COLMAP's, with their rotation columns reordered."""
    from hdrplenoxels.data.colmap import model_point_box

    return model_point_box(folder)


def describe_llff(path: str | Path) -> SceneDescription:
    """Describe an LLFF, LLFF + `hwf_cxcy.npy` or HDR-NeRF scene: its folder, or its poses .npy file."""
    npy = _locate(Path(path))
    table = _parse(npy)
    _check_bounds(npy, table.bounds)
    image_dir, files = _image_files(npy)
    n = len(table.mats)
    if len(files) != n:
        raise InputError(
            npy,
            f"has {n} poses but {image_dir.name}/ holds {len(files)} images ({', '.join(IMAGE_EXTENSIONS)}); "
            "each row describes one image, in sorted file-name order",
        )
    if n < 2:
        raise InputError(npy, "only 1 image: need at least 2 (the first is a test view)")
    views = []
    for file, mat, stored in zip(files, table.mats, table.stored, strict=True):
        name = f"{image_dir.name}/{file.name}"
        c2w = llff_to_opencv(mat)
        check_pose(npy, f"image {name!r}: ", c2w)
        views.append(ViewDescription(name, file, c2w, _camera(stored), npy, npy.name))
    train, test = every_nth_split(n)
    notes = {"near_far": f"the near/far columns of {npy.name}"}
    box = _model_box(npy.parent)
    if box is not None:
        notes["box"] = box[1]
    return SceneDescription(
        layout=table.layout,
        source=npy,
        views=views,
        train_ids=train,
        test_ids=test,
        near_far=(float(table.bounds[:, 0].min()), float(table.bounds[:, 1].max())),
        scene_box=None if box is None else box[0],
        bounds_notes=notes,
        exposure_init_ev=None if table.exposure_times is None else np.log2(table.exposure_times),
    )


def load_llff(path: str | Path, downscale: int = 1) -> SceneData:
    """Load the scene `describe_llff(path)` describes, images included (`downscale` times smaller)."""
    return load_images(describe_llff(path), downscale)
