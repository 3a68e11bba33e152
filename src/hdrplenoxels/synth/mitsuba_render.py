"""Mitsuba 3 as the source of HDR truth: variant choice, our cameras as Mitsuba sensors, rendering.

Camera mapping (checked by tests/test_synth_mitsuba.py against our own projection): Mitsuba's camera
looks along +Z with +Y up and +X to the image left, so `to_world = c2w_opencv @ diag(-1, -1, 1, 1)`;
`fov_x = 2 atan(W / (2 fx))` (square pixels); our principal point (cx, cy) is in continuous pixel
coordinates (pixel centres at +0.5), so Mitsuba's offsets are -(cx - W/2)/W and -(cy - H/2)/H.
"""

from __future__ import annotations

import functools
import math
import os
import subprocess
import sys

import numpy as np

from hdrplenoxels.geometry.cameras import Cameras

MITSUBA_FROM_OPENCV = np.diag([-1.0, -1.0, 1.0, 1.0])
VARIANT_ENV = "HDRPLENOXELS_MITSUBA_VARIANT"

_PROBE = """
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene", "i": {"type": "path"}, "s": {"type": "sphere"}, "e": {"type": "constant"},
    "c": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
})
mi.render(scene, spp=1)
"""


def _variant_works(variant: str) -> bool:
    try:
        probe = subprocess.run([sys.executable, "-c", _PROBE, variant], capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return probe.returncode == 0


@functools.cache
def select_variant() -> str:
    """The fastest Mitsuba variant that works here: CUDA, then LLVM (needs a recent libLLVM), else scalar.

    A missing driver or a too-old libLLVM can abort the whole process (exit 134) rather than raise, so
    each candidate is probed once in a subprocess. `HDRPLENOXELS_MITSUBA_VARIANT` overrides the choice.
    """
    forced = os.environ.get(VARIANT_ENV)
    if forced:
        return forced
    import torch

    candidates = (["cuda_ad_rgb"] if torch.cuda.is_available() else []) + ["llvm_ad_rgb"]
    return next((v for v in candidates if _variant_works(v)), "scalar_rgb")


def mitsuba():
    """The mitsuba module with the chosen variant set (imported lazily: it is only needed by `synth`)."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant(select_variant())
    return mi


def sensor_dict(c2w_opencv: np.ndarray, intrinsics, size: tuple[int, int], spp: int, seed: int = 0) -> dict:
    """A Mitsuba perspective sensor for one of our pinhole cameras (square pixels: fx must equal fy)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    w, h = size
    if abs(fx - fy) > 1e-6 * fx:
        raise ValueError(f"Mitsuba's perspective sensor needs square pixels, got fx={fx}, fy={fy}")
    mi = mitsuba()
    to_world = np.asarray(c2w_opencv, dtype=np.float64) @ MITSUBA_FROM_OPENCV
    return {
        "type": "perspective",
        "fov": math.degrees(2.0 * math.atan(w / (2.0 * fx))),
        "fov_axis": "x",
        "principal_point_offset_x": -(cx - w / 2.0) / w,
        "principal_point_offset_y": -(cy - h / 2.0) / h,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "film": {"type": "hdrfilm", "width": int(w), "height": int(h), "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
    }


def render_view(scene, cameras: Cameras, i: int, spp: int, seed: int = 0) -> np.ndarray:
    """Linear HDR radiance (H, W, 3) float32 of camera i."""
    mi = mitsuba()
    sensor = mi.load_dict(sensor_dict(cameras.c2w[i], cameras.intrinsics[i], cameras.size(i), spp, seed))
    image = mi.render(scene, sensor=sensor, spp=spp, seed=seed)
    return np.asarray(image, dtype=np.float32)[..., :3].copy()


def load_scene_dict(scene_dict: dict):
    """`mi.load_dict` with a fixed shape order, so renders are reproducible across processes."""
    return mitsuba().load_dict(scene_dict, optimize=False)
