"""Camera poses given by the user: read, checked as rigid, and put in OpenCV axes.

One convention for every pose a user gives, a file to `render --pose` or a matrix to `render_pose`:
camera-to-world in OpenGL axes (x right, y up, z back: nerfstudio, Blender, instant-ngp and this
package's own camera paths), unless told "opencv" (x right, y down, z forward: COLMAP, OpenCV). Inside,
cameras are OpenCV (`SceneData.cameras`), so a pose taken from a scene's cameras is given as "opencv".
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.npy_files import check_npy_file
from hdrplenoxels.geometry.cameras import opengl_to_opencv

PoseConvention = Literal["opengl", "opencv"]
DEFAULT_POSE_CONVENTION: PoseConvention = "opengl"


def to_opencv(c2w: np.ndarray, convention: PoseConvention) -> np.ndarray:
    """Camera-to-world poses (..., 4, 4) given in `convention`'s axes, in OpenCV's."""
    if convention not in ("opengl", "opencv"):
        raise ValueError(f"pose convention {convention!r}: use 'opengl' or 'opencv'")
    return opengl_to_opencv(c2w) if convention == "opengl" else c2w


def read_poses(path: Path, convention: PoseConvention) -> np.ndarray:
    """(N, 4, 4) OpenCV camera-to-world poses from .npy, .json or whitespace text in `convention`'s axes.

    Anything but rigid transforms is an InputError: a scaled or mirrored pose would render a distorted
    view without any other sign that the file was wrong.
    """
    try:
        if path.suffix == ".npy":
            check_npy_file(path)
            arr = np.load(path, allow_pickle=False)
            if arr.dtype.kind not in "iuf":
                raise InputError(path, f"poses must be real numbers, got an array of dtype {arr.dtype}")
        elif path.suffix == ".json":
            arr = json.loads(path.read_text())
            if not isinstance(arr, list):
                raise InputError(
                    path, f"expected a 4x4 matrix or a list of them (JSON arrays), got {type(arr).__name__}"
                )
        else:
            arr = np.loadtxt(path, dtype=np.float64)
        arr = np.asarray(arr, dtype=np.float64)
    except (ValueError, TypeError, OSError) as e:
        raise InputError(path, f"cannot read poses: {e}") from None
    if arr.size % 16 or arr.size == 0:
        raise InputError(path, f"expected one or more 4x4 matrices, got shape {arr.shape}")
    arr = arr.reshape(-1, 4, 4)
    if not np.isfinite(arr).all():
        raise InputError(path, "pose contains NaN or inf")
    rot = arr[:, :3, :3]
    if (
        np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() > 1e-3
        or np.abs(arr[:, 3] - [0, 0, 0, 1]).max() > 1e-6
    ):
        raise InputError(path, "pose is not a rigid camera-to-world transform (rotation not orthonormal)")
    if (np.linalg.det(rot) <= 0).any():
        raise InputError(path, "pose is not a rigid camera-to-world transform (rotation is a reflection)")
    return to_opencv(arr, convention)
