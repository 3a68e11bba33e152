"""Scene bounds from structure-from-motion points, as LLFF and the HDR-Plenoxels captures take them.

Sparse SfM points include a few outliers (mismatches, far background), so every bound is a percentile,
never a min or max: per image, near/far are the 0.1 / 99.9 percentiles of the depths of the points it
sees (LLFF's rule); the bounding box is the 1 / 99 percentile of all points per axis, padded by 10 %.
"""

from __future__ import annotations

import numpy as np

NEAR_FAR_PERCENTILES = (0.1, 99.9)
BOX_PERCENTILES = (1.0, 99.0)
BOX_PADDING = 0.1
MIN_POINTS_PER_IMAGE = 4  # fewer observed points give no usable depth range


def image_depth_bounds(c2w: np.ndarray, points: np.ndarray) -> tuple[float, float] | None:
    """(near, far) depths along the optical axis of the points one camera sees (OpenCV c2w)."""
    if len(points) < MIN_POINTS_PER_IMAGE:
        return None
    depth = (points - c2w[:3, 3]) @ c2w[:3, 2]
    depth = depth[depth > 0]
    if len(depth) < MIN_POINTS_PER_IMAGE:
        return None
    near, far = np.percentile(depth, NEAR_FAR_PERCENTILES)
    return float(near), float(far)


def scene_near_far(per_image: list[tuple[float, float] | None]) -> tuple[float, float] | None:
    """The closest near and farthest far over the images that had a depth range."""
    known = [b for b in per_image if b is not None]
    if not known:
        return None
    return min(b[0] for b in known), max(b[1] for b in known)


def point_box(points: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """Robust axis-aligned box around the points, padded on every side by 10 % of its size."""
    if len(points) < MIN_POINTS_PER_IMAGE:
        return None
    lo, hi = np.percentile(points, BOX_PERCENTILES, axis=0)
    pad = BOX_PADDING * np.maximum(hi - lo, 1e-6)
    return tuple((lo - pad).tolist()), tuple((hi + pad).tolist())


def upright_frame(c2w: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A rigid world_from_data (4, 4) that puts SfM output upright and square with the scene.

    SfM returns an arbitrary frame; an axis-aligned box in it is loose and tilted against the walls,
    which wastes the grid's voxels. Up (+y) is the cameras' mean up direction (photos are taken mostly
    level); x is the points' main horizontal axis; the origin is the points' median.
    """
    up = -c2w[:, :3, 1].mean(0)  # OpenCV image y points down
    up /= np.linalg.norm(up)
    origin = np.median(points, axis=0) if len(points) else c2w[:, :3, 3].mean(0)
    flat = points - origin
    flat = flat - np.outer(flat @ up, up)
    if len(points) >= 3:
        x = np.linalg.eigh(flat.T @ flat)[1][:, -1]
    else:
        x = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
    x = x - (x @ up) * up
    x /= np.linalg.norm(x)
    z = np.cross(x, up)
    rot = np.stack([x, up, z])  # rows: new axes in data coordinates
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ origin
    return out
