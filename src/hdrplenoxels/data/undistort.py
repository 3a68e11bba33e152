"""Undistorting photos taken through OpenCV radial-tangential lenses into pinhole ones, with COLMAP.

Everything downstream assumes pinhole cameras, so distorted photos are resampled once, at load time.
COLMAP keeps the focal lengths and crops to the largest image with no pixel outside the photo
(`blank_pixels = 0`): a black border would otherwise be learnt as scene content. COLMAP puts pixel centres
at +0.5, as we do, so its intrinsics are used unchanged.
"""

from __future__ import annotations

import numpy as np


def undistort_opencv(
    image: np.ndarray, intrinsics: tuple[float, float, float, float], coeffs: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """The uint8 (H', W', 3) pinhole image and its (fx, fy, cx, cy), for a photo with OpenCV intrinsics
    and distortion `coeffs` = (k1, k2, p1, p2, k3). Raises ValueError when COLMAP finds no valid image."""
    k1, k2, p1, p2, k3 = coeffs
    params = [*intrinsics, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]  # FULL_OPENCV's k4..k6 form a denominator
    rgb, pinhole = undistort_to_pinhole(image, "FULL_OPENCV", params)
    return rgb, np.asarray(pinhole, dtype=np.float64)


PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")


def pinhole_intrinsics(model: str, params) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a COLMAP PINHOLE or SIMPLE_PINHOLE parameter vector."""
    p = [float(v) for v in params]
    if model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    if model == "PINHOLE":
        return p[0], p[1], p[2], p[3]
    raise ValueError(f"{model} is not a pinhole model")


def undistort_to_pinhole(
    image: np.ndarray, model: str, params
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Any COLMAP camera model (e.g. SIMPLE_RADIAL: f, cx, cy, k) resampled to pinhole, as above.
    Raises ValueError when COLMAP finds no valid image."""
    import pycolmap  # 0.14 s to import: only when a distorted camera is actually loaded

    h, w = image.shape[:2]
    camera = pycolmap.Camera(model=model, width=w, height=h, params=list(map(float, params)))
    bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(image, dtype=np.uint8))
    out, pinhole = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, camera)
    rgb = out.to_array()
    if rgb.ndim != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"undistortion produced no image (shape {rgb.shape}); are the coefficients right?")
    return np.ascontiguousarray(rgb), pinhole_intrinsics(pinhole.model_name, pinhole.params)
