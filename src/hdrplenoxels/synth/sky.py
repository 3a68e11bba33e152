"""A procedural HDR sky for the open-air scenes: an equirectangular array of linear radiance, made in code.

Layout is Mitsuba 3's `envmap`: row `i` is the polar angle from +y (up) at `(i + 0.5) / H * pi`, column `j`
the azimuth `phi = (j + 0.5) / W * 2 pi` with direction `(sin(theta) sin(phi), cos(theta),
-sin(theta) cos(phi))`. The sky is a horizon-to-zenith gradient with soft clouds, a glow around the sun
and the sun's disk, whose radiance is hundreds of times the sky's, as outdoors; below the horizon it is a
dim ground colour (the scene's terrain covers it in practice). Clouds are sums of sinusoids whole in azimuth,
so the map has no seam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SkySpec:
    sun_azimuth_deg: float = 200.0  # phi of the sun (the envmap's azimuth convention, above)
    sun_elevation_deg: float = 9.0
    sun_radius_deg: float = 2.0  # ~4x the real sun, so the disk covers pixels at CPU resolutions
    sun_radiance: tuple[float, float, float] = (1600.0, 1350.0, 1000.0)  # a low, warm sun
    horizon: tuple[float, float, float] = (2.2, 2.0, 1.8)
    zenith: tuple[float, float, float] = (0.15, 0.25, 0.5)
    glow: tuple[float, float, float] = (6.0, 4.2, 2.4)  # added at the sun's rim, falling off with angle
    glow_width_deg: float = 10.0
    clouds: float = 0.5  # brightness of clouds above the clear sky, as a multiple of it
    ground: tuple[float, float, float] = (0.06, 0.055, 0.045)
    seed: int = 7


def directions(height: int, width: int) -> np.ndarray:
    """Unit directions (H, W, 3) of the envmap's pixel centres (module docstring)."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    st, up = np.sin(theta)[:, None], np.broadcast_to(np.cos(theta)[:, None], (height, width))
    return np.stack([st * np.sin(phi)[None, :], up, -st * np.cos(phi)[None, :]], axis=-1)


def sun_direction(spec: SkySpec) -> np.ndarray:
    e, a = np.deg2rad(spec.sun_elevation_deg), np.deg2rad(spec.sun_azimuth_deg)
    return np.array([np.cos(e) * np.sin(a), np.sin(e), -np.cos(e) * np.cos(a)])


def cloud_cover(height: int, width: int, seed: int) -> np.ndarray:
    """Soft cloud banks in [0, 1] (H, W): whole azimuthal frequencies (seamless), denser near the horizon."""
    rng = np.random.default_rng(seed)
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    field = np.zeros((height, width))
    for octave in range(5):
        for _ in range(4):
            k = int(rng.integers(2, 6)) * 2**octave
            m = rng.uniform(3.0, 8.0) * 2**octave
            field += np.sin(k * phi[None, :] + m * theta[:, None] + rng.uniform(0, 2 * np.pi)) / 1.7**octave
    field = (field - field.mean()) / field.std()
    return np.clip((field - 0.3) / 1.2, 0.0, 1.0) ** 1.5


def sky_radiance(spec: SkySpec = SkySpec(), height: int = 512, width: int = 1024) -> np.ndarray:
    """The sky as float32 (H, W, 3) linear radiance (module docstring)."""
    d = directions(height, width)
    up = d[..., 1]
    t = np.clip(up, 0.0, 1.0)[..., None]  # 0 at the horizon, 1 at the zenith
    clear = (1.0 - t) * np.asarray(spec.horizon) + t * np.asarray(spec.zenith)
    sky = clear * (1.0 + spec.clouds * cloud_cover(height, width, spec.seed)[..., None])
    angle = np.degrees(np.arccos(np.clip(d @ sun_direction(spec), -1.0, 1.0)))[..., None]
    rim = np.clip(angle - spec.sun_radius_deg, 0.0, None)
    sky = sky + np.asarray(spec.glow) * np.exp(-rim / spec.glow_width_deg)
    sky = np.where(angle <= spec.sun_radius_deg, np.asarray(spec.sun_radiance), sky)
    below = np.broadcast_to(np.asarray(spec.ground), sky.shape)
    return np.where((up < 0.0)[..., None], below, sky).astype(np.float32)
