"""Undistorting photos taken through any COLMAP lens model (OpenCV radial-tangential included) to pinhole.

Everything downstream assumes pinhole cameras, so distorted photos are resampled once, at load time.
COLMAP keeps the focal lengths and crops to the largest image with no pixel outside the photo
(`blank_pixels = 0`): a black border would otherwise be learnt as scene content. COLMAP puts pixel centres
at +0.5, as we do, so its intrinsics are used unchanged.
"""

from __future__ import annotations

import numpy as np

from hdrplenoxels.data.description import Distortion, Intrinsics

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
# Perspective lens models that are a pinhole when every coefficient is 0 (fisheye models never are); COLMAP's
# undistorter leaves such a camera as it is, so a model it "undistorted" may still name one.
PERSPECTIVE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def is_pinhole(model_name: str, coeffs: tuple[float, ...]) -> bool:
    """Whether a COLMAP camera of this model with these distortion coefficients projects as a pinhole."""
    return model_name in PINHOLE_MODELS or (model_name in PERSPECTIVE_MODELS and not any(coeffs))


def split_params(camera) -> tuple[Intrinsics, tuple[float, ...]]:
    """(fx, fy, cx, cy) and the remaining (distortion) parameters of a pycolmap camera, any model."""
    p = [float(v) for v in camera.params]
    focal = camera.focal_length_idxs()
    cx, cy = (p[i] for i in camera.principal_point_idxs())
    return (p[focal[0]], p[focal[-1]], cx, cy), tuple(p[i] for i in camera.extra_params_idxs())


def undistort(
    image: np.ndarray, intrinsics: Intrinsics, distortion: Distortion
) -> tuple[np.ndarray, Intrinsics]:
    """The uint8 (H', W', 3) pinhole image and its (fx, fy, cx, cy), for a photo with `intrinsics` seen
    through `distortion`. Raises ValueError when COLMAP finds no valid image."""
    import pycolmap  # slow to import: only when a distorted camera is loaded (JOURNAL.md)

    h, w = image.shape[:2]
    camera = pycolmap.Camera(model=distortion.model, width=w, height=h)
    focal, extra = camera.focal_length_idxs(), camera.extra_params_idxs()
    params = np.zeros(len(focal) + 2 + len(extra))
    fx, fy, cx, cy = intrinsics
    params[focal] = (fx, fy)[: len(focal)]
    params[camera.principal_point_idxs()] = (cx, cy)
    params[extra] = distortion.coeffs
    camera.params = params
    bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(image, dtype=np.uint8))
    out, pinhole = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, camera)
    rgb = out.to_array()
    if rgb.ndim != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"undistortion produced no image (shape {rgb.shape}); are the coefficients right?")
    return np.ascontiguousarray(rgb), split_params(pinhole)[0]
