"""Rendering options shared by every backend (docs/method.md, "Rendering")."""

from __future__ import annotations

from dataclasses import dataclass

TINY_DIR = 1e-9  # a zero direction component is replaced by this in the slab test (both backends)
# A sample this close (in steps) before the far face of the box still counts. Rays parallel to an
# axis cross the box in a whole number of steps, where an exact count would hinge on the last ulp
# (CUDA fuses multiply-adds, the CPU may not): the slack moves that knife edge off the integers.
FAR_FACE_SLACK = 1e-3


@dataclass(frozen=True)
class RenderOptions:
    step_size: float = 0.5  # in voxels ("half a voxel")
    sigma_thresh: float = 1e-8  # samples with interpolated density <= this are skipped (ReLU)
    stop_thresh: float = 1e-7  # early stop once transmittance falls below this
    background_brightness: float = 0.5  # seen where rays leave the field with no background model
    t_max: float = 2000.0  # far limit of the march, in grid units
    # Training only: a sample's gradient is scaled by min(1, (t / (near_grad h))^2), t its distance from the
    # ray's origin and h the finest box's half-side (both in level-0 voxels), so that what lies just in
    # front of a camera, seen by few rays, learns slower than what many rays cross (Philip & Deschaintre
    # 2023, "Floaters No More"); 0: off. The forward is unchanged (docs/method.md, "Cascade").
    near_grad: float = 0.0


def near_distance(opt: RenderOptions, reso: tuple[int, int, int]) -> float:
    """`opt.near_grad` in level-0 voxels: times the finest box's half-side, half its widest resolution."""
    return opt.near_grad * max(reso) / 2.0
