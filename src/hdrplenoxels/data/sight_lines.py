"""Lines of sight: the sparse structure-from-motion points and which views saw each of them.

A view that observed a point saw it through empty space, so the segment from its camera to the point
is evidence of free space that no photo's pixels alone give (the free-space prior of docs/method.md,
"Free space along lines of sight"). `process` writes them next to `transforms.json` as `sparse_points.npz`
(named by the file's `"sparse_points"` key); a COLMAP folder has them in its model. Views are named by
their image's file stem, so that a dataset whose frames were subset or re-encoded keeps them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_write
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.npy_files import read_npz

POINTS_FILE = "sparse_points.npz"
POINTS_KEY = "sparse_points"  # the transforms.json key naming the file
_ARRAYS = ("xyz", "images", "obs_image", "obs_point")


@dataclass(frozen=True)
class SightLines:
    """Observations of sparse points: view `view[k]` saw point `points[point[k]]` (dataset frame)."""

    points: np.ndarray  # (P, 3) float64, the scene's (dataset) frame
    view: np.ndarray  # (M,) int64, index of the observing view in the scene
    point: np.ndarray  # (M,) int64, index into `points`

    def __len__(self) -> int:
        return int(self.view.shape[0])

    def of_views(self, views: Sequence[int]) -> SightLines:
        """Only the observations made by `views` (e.g. the training views, never a test view's)."""
        keep = np.isin(self.view, np.asarray(list(views), dtype=np.int64))
        return SightLines(self.points, self.view[keep], self.point[keep])


def _stem(name: str) -> str:
    return Path(name).stem


def write_sight_lines(path: str | Path, lines: SightLines, view_names: Sequence[str]) -> Path:
    """`path` (.npz) holding `lines`, each view named by the stem of `view_names[view]`."""
    stems = np.array([_stem(n) for n in view_names])
    arrays = {
        "xyz": np.asarray(lines.points, dtype=np.float64),
        "images": stems,
        "obs_image": lines.view.astype(np.int32),
        "obs_point": lines.point.astype(np.int32),
    }

    def write(tmp: Path) -> None:
        with tmp.open("wb") as f:  # a file object: numpy would append ".npz" to a temporary name
            np.savez_compressed(f, **arrays)

    return atomic_write(path, write)


def read_sight_lines(path: str | Path, view_names: Sequence[str]) -> SightLines:
    """The observations in `path` of the views named `view_names` (matched by file stem; observations by
    views not among them are left out). Raises InputError naming the file for anything malformed."""
    path = Path(path)
    arrays = read_npz(path)
    missing = [k for k in _ARRAYS if k not in arrays]
    if missing:
        raise InputError(path, f"sparse points file lacks array(s) {', '.join(missing)}")
    xyz, names, obs_image, obs_point = (arrays[k] for k in _ARRAYS)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.issubdtype(xyz.dtype, np.floating):
        raise InputError(path, f"'xyz' must be (P, 3) floats, got {xyz.dtype} {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise InputError(path, "'xyz' contains NaN or infinity")
    if names.ndim != 1 or names.dtype.kind != "U":
        raise InputError(path, "'images' must be a list of image names")
    for key, arr, limit in (("obs_image", obs_image, len(names)), ("obs_point", obs_point, len(xyz))):
        if arr.ndim != 1 or arr.dtype.kind not in "iu" or arr.shape != obs_image.shape:
            raise InputError(path, f"'{key}' must be one integer per observation, like 'obs_image'")
        if arr.size and (arr.min() < 0 or arr.max() >= limit):
            raise InputError(path, f"'{key}' indexes outside its {limit} entries")
    index = {_stem(n): i for i, n in enumerate(view_names)}
    to_view = np.array([index.get(str(n), -1) for n in names], dtype=np.int64)
    view = to_view[obs_image.astype(np.int64)] if obs_image.size else np.zeros(0, dtype=np.int64)
    keep = view >= 0
    return SightLines(xyz.astype(np.float64), view[keep], obs_point.astype(np.int64)[keep])
