"""Checks applied to every camera, so bad poses and intrinsics fail with one clear line.

A pose that is not a rigid transform (scaled, sheared or mirrored rotation) would silently warp every
ray; NaN or infinity would poison the grid on the first step. Parsers call `check_pose` on each view they
describe; the image loader calls `check_intrinsics` once a camera is resolved against its image.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hdrplenoxels.core.errors import InputError

ROTATION_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1|: files store poses rounded to about 6 digits


def rigidity_error(c2w: np.ndarray) -> tuple[float, float]:
    """(max |R^T R - I|, det R) of one (4, 4) or (3, 4) pose."""
    r = np.asarray(c2w, dtype=np.float64)[:3, :3]
    return float(np.abs(r.T @ r - np.eye(3)).max()), float(np.linalg.det(r))


def check_pose(path: Path, where: str, c2w: np.ndarray) -> None:
    """Refuse a camera-to-world pose with non-finite values or a rotation that is not a rotation."""
    m = np.asarray(c2w, dtype=np.float64)
    if not np.isfinite(m).all():
        raise InputError(path, f"{where}pose contains NaN or infinity")
    ortho, det = rigidity_error(m)
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        kind = "a mirror (determinant -1)" if det < 0 else f"scaled or sheared (|R^T R - I| = {ortho:.3g})"
        raise InputError(
            path,
            f"{where}pose is not a rigid transform: its rotation is {kind}; poses must be "
            "camera-to-world rotations plus a translation",
        )


def check_intrinsics(path: Path, where: str, k: np.ndarray, size: tuple[int, int]) -> None:
    """Finite intrinsics with positive focal lengths, and a positive image size (W, H)."""
    if not np.isfinite(k).all():
        raise InputError(path, f"{where}intrinsics contain NaN or infinity: {k.tolist()}")
    if (k[:2] <= 0).any():
        raise InputError(path, f"{where}focal lengths must be positive, got fx={k[0]}, fy={k[1]}")
    if min(size) <= 0:
        raise InputError(path, f"{where}image size must be positive, got {list(size)}")


def read_json(path: Path, cannot_read: str = "cannot read") -> Any:
    """A user's JSON file, or one InputError naming it: `cannot_read` begins the message when the file
    can't be read, "not valid JSON" when it can't be parsed."""
    try:
        return json.loads(Path(path).read_text())
    except OSError as e:
        raise InputError(path, f"{cannot_read}: {e.strerror or e}") from None
    except ValueError as e:
        raise InputError(path, f"not valid JSON: {e}") from None
