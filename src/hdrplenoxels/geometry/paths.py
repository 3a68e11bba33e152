"""Camera paths for videos: an orbit, a forward-facing spiral, and a path through the training cameras.

Every function takes and returns OpenCV camera-to-world poses (…, 4, 4) in one frame (the grid's world
frame, in practice) and makes no assumption about which axis is up: "up" is the training cameras' mean up.
"""

from __future__ import annotations

import numpy as np


def _normalise(v: np.ndarray) -> np.ndarray:
    return v / (np.linalg.norm(v, axis=-1, keepdims=True) + 1e-12)


def mean_up(c2w: np.ndarray) -> np.ndarray:
    """The cameras' mean up direction (OpenCV: image y points down, so up is -column 1)."""
    return _normalise(-c2w[:, :3, 1].mean(0))


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world at `position` looking at `target`, image up as close to `up` as it can be."""
    forward = _normalise(target - position)
    right = _normalise(np.cross(-up, forward))  # x = y cross z for OpenCV's (right, down, forward)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, position
    return c2w


def orbit(c2w: np.ndarray, center: np.ndarray, frames: int) -> np.ndarray:
    """A full circle around `center` about the cameras' mean up axis, at their mean distance and height."""
    up = mean_up(c2w)
    offsets = c2w[:, :3, 3] - center
    height = float((offsets @ up).mean())
    flat = offsets - np.outer(offsets @ up, up)
    radius = float(np.linalg.norm(flat, axis=1).mean())
    start = _normalise(flat.mean(0)) if np.linalg.norm(flat.mean(0)) > 1e-6 * radius else _normalise(flat[0])
    side = np.cross(up, start)
    poses = []
    for angle in np.linspace(0.0, 2.0 * np.pi, frames, endpoint=False):
        position = center + up * height + radius * (np.cos(angle) * start + np.sin(angle) * side)
        poses.append(look_at(position, center, up))
    return np.stack(poses)


def spiral(c2w: np.ndarray, focus_depth: float, frames: int, rotations: float = 2.0) -> np.ndarray:
    """LLFF's spiral for forward-facing captures: around the mean camera, in its image plane, with radii
    from the cameras' 90th-percentile spread, always looking at a point `focus_depth` ahead."""
    forward = _normalise(c2w[:, :3, 2].mean(0))
    up = mean_up(c2w)
    center = c2w[:, :3, 3].mean(0)
    mean = look_at(center, center + forward, up)
    local = (c2w[:, :3, 3] - center) @ mean[:3, :3]  # positions in the mean camera's axes
    radii = np.percentile(np.abs(local), 90, axis=0)
    target = center + focus_depth * forward
    poses = []
    for angle in np.linspace(0.0, 2.0 * np.pi * rotations, frames, endpoint=False):
        offset = np.array([np.cos(angle), -np.sin(angle), -np.sin(0.5 * angle)]) * radii
        poses.append(look_at(center + mean[:3, :3] @ offset, target, up))
    return np.stack(poses)


def _slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Rotation matrices a -> b, a fraction t of the way, about their relative rotation's axis."""
    relative = a.T @ b
    angle = np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-8:
        return a
    axis = np.array(
        [relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0], relative[1, 0] - relative[0, 1]]
    )
    axis /= 2.0 * np.sin(angle)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    theta = t * angle
    return a @ (np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * k @ k)


def interpolate(keyframes: np.ndarray, frames: int) -> np.ndarray:
    """`frames` poses through `keyframes` in order, evenly in time: positions linear, rotations slerped;
    the first and last frames are the first and last keyframes."""
    if len(keyframes) == 1 or frames == 1:
        return np.repeat(keyframes[:1], frames, axis=0)
    poses = []
    for u in np.linspace(0.0, len(keyframes) - 1.0, frames):
        i = min(int(u), len(keyframes) - 2)
        t = u - i
        a, b = keyframes[i], keyframes[i + 1]
        pose = np.eye(4)
        pose[:3, :3] = _slerp(a[:3, :3], b[:3, :3], t)
        pose[:3, 3] = (1.0 - t) * a[:3, 3] + t * b[:3, 3]
        poses.append(pose)
    return np.stack(poses)


def through_cameras(c2w: np.ndarray, frames: int, stops: int = 8) -> np.ndarray:
    """A path through up to `stops` training cameras picked evenly in their order."""
    picks = np.unique(np.linspace(0, len(c2w) - 1, min(stops, len(c2w))).round().astype(int))
    return interpolate(c2w[picks], frames)
