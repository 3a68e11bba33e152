"""Rendering options shared by every backend (docs/method.md, "Rendering")."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RenderOptions:
    step_size: float = 0.5  # in voxels ("half a voxel")
    sigma_thresh: float = 1e-8  # samples with interpolated density <= this are skipped (ReLU)
    stop_thresh: float = 1e-7  # early stop once transmittance falls below this
    background: float = 0.5  # constant background brightness, added in radiance space
    t_max: float = 2000.0  # far limit of the march, in grid units
