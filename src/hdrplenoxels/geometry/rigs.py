"""Camera rigs for generated scenes: look-at poses, 360-degree orbits and forward-facing grids.

All poses are OpenCV camera-to-world (x right, y down, z forward) in a y-up world.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hdrplenoxels.geometry.cameras import Cameras

Vec3 = Sequence[float]


def look_at(position: Vec3, target: Vec3, up: Vec3 = (0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world at `position` looking at `target`, image up along `up`."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    fwd = target - position
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
    m[:3, 3] = position
    return m


def pinhole_intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """(fx, fy, cx, cy) with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(np.deg2rad(fov_x_deg) / 2)
    return np.array([f, f, width / 2, height / 2])


def _cameras(c2w: np.ndarray, width: int, height: int, fov_x_deg: float) -> Cameras:
    n = len(c2w)
    return Cameras(
        c2w, np.tile(pinhole_intrinsics(width, height, fov_x_deg), (n, 1)), np.tile([width, height], (n, 1))
    )


def orbit_rig(
    n: int,
    width: int,
    height: int,
    fov_x_deg: float,
    radius: float,
    elev_range_deg: tuple[float, float],
    target: Vec3 = (0.0, 0.0, 0.0),
) -> Cameras:
    """Cameras on a sphere looking inward: golden-angle azimuths, golden-ratio elevations.

    Elevations follow a low-discrepancy sequence rather than a ramp, so that every 8th (test) view lies
    among training views instead of at the edge of the covered range.
    """
    k = np.arange(n)
    lo, hi = np.deg2rad(elev_range_deg)
    elev = lo + (hi - lo) * (((k + 0.5) * (np.sqrt(5) - 1) / 2) % 1.0)
    azim = k * np.pi * (3 - np.sqrt(5))
    pos = radius * np.stack([np.cos(elev) * np.sin(azim), np.sin(elev), np.cos(elev) * np.cos(azim)], -1)
    target = np.asarray(target, float)
    return _cameras(np.stack([look_at(p + target, target) for p in pos]), width, height, fov_x_deg)


def forward_facing_rig(
    n: int, width: int, height: int, fov_x_deg: float, centre: Vec3, spread: tuple[float, float], target: Vec3
) -> Cameras:
    """Cameras on a near-planar grid around `centre` (LLFF style), all looking at one focus point."""
    cols = int(np.ceil(np.sqrt(n * 2)))
    rows = int(np.ceil(n / cols))
    pos = []
    for k in range(n):
        r, c = divmod(k, cols)
        u = (c + 0.5) / cols - 0.5
        v = (r + 0.5) / rows - 0.5
        pos.append(np.asarray(centre) + np.array([u * spread[0], v * spread[1], 0.05 * np.sin(3.1 * k)]))
    return _cameras(np.stack([look_at(p, target) for p in pos]), width, height, fov_x_deg)


def arc_rig(
    n: int,
    width: int,
    height: int,
    fov_x_deg: float,
    radius: float,
    azimuth_range_deg: tuple[float, float],
    elev_range_deg: tuple[float, float],
    target: Vec3 = (0.0, 0.0, 0.0),
) -> Cameras:
    """Cameras walking an arc around `target` (a hand-held walk-around), elevation alternating in range."""
    k = np.arange(n)
    azim = np.deg2rad(np.linspace(*azimuth_range_deg, n))
    lo, hi = np.deg2rad(elev_range_deg)
    elev = np.where(k % 2 == 0, lo, hi)
    pos = radius * np.stack([np.cos(elev) * np.sin(azim), np.sin(elev), np.cos(elev) * np.cos(azim)], -1)
    target = np.asarray(target, float)
    return _cameras(np.stack([look_at(p + target, target) for p in pos]), width, height, fov_x_deg)


def walk_rig(n: int, width: int, height: int, fov_x_deg: float, length: float, eye: float) -> Cameras:
    """A walk straight along +z from the origin, `length` long, at height `eye`, held as in `_hand_held`."""
    path = np.stack([np.zeros(n), np.linspace(0.0, length, n)], -1)
    return _hand_held(path, np.zeros(n), width, height, fov_x_deg, eye)


def corner_walk_rig(
    n: int, width: int, height: int, fov_x_deg: float, legs: tuple[float, float], radius: float, eye: float
) -> Cameras:
    """A walk along +z for `legs[0]`, round a right-hand corner on a quarter circle of `radius` (the view
    turning with the path), then along +x for `legs[1]`: photos evenly spaced along the way, each held as
    in `_hand_held`. The turn is what a real walk between streets adds to a straight one."""
    first, second = legs
    turn = np.pi / 2 * radius
    s = np.linspace(0.0, first + turn + second, n)
    angle = np.clip((s - first) / radius, 0.0, np.pi / 2)  # heading: 0 along +z, pi/2 along +x
    x = np.where(s <= first, 0.0, radius * (1 - np.cos(angle))) + np.clip(s - first - turn, 0.0, None)
    z = np.minimum(s, first) + radius * np.sin(angle)
    return _hand_held(np.stack([x, z], -1), angle, width, height, fov_x_deg, eye)


def _hand_held(
    path: np.ndarray, heading: np.ndarray, width: int, height: int, fov_x_deg: float, eye: float
) -> Cameras:
    """Cameras at `path` (n, 2: x, z) facing `heading` (radians from +z towards +x) at height `eye`, each
    swayed sideways and up and down and turned a few degrees, as a hand-held phone is."""
    k = np.arange(len(path))
    side = 0.15 * np.sin(1.3 * k)
    y = eye + 0.04 * np.sin(2.1 * k + 0.5)
    yaw = heading + np.deg2rad(4.0 * np.sin(0.9 * k + 1.0))
    pitch = np.deg2rad(-3.0 + 2.0 * np.sin(1.7 * k))
    ahead = np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)
    pos = np.stack([path[:, 0] + side * np.cos(heading), y, path[:, 1] - side * np.sin(heading)], -1)
    return _cameras(np.stack([look_at(p, p + a) for p, a in zip(pos, ahead)]), width, height, fov_x_deg)
