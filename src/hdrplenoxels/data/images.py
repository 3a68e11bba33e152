"""The one image loader: a `SceneDescription` in, a `SceneData` out (docs/design.md, "Data loading").

For each view, in order: read the file, check its size against the stated camera (or scale a resized
copy's intrinsics), complete the intrinsics from that size, composite alpha onto the layout's background
or drop it, undistort to pinhole, and reduce it `downscale` times (`downscale.py`), or read the layout's
own reduced copy instead when it has one of the right size. Every error names the image file, or the
file describing the view.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.description import Intrinsics, SceneDescription, ViewDescription
from hdrplenoxels.data.downscale import (
    block_average,
    copy_intrinsics,
    header_size,
    is_copy_size,
    prescaled_copy,
    scaled_intrinsics,
)
from hdrplenoxels.data.image_io import composite_on_white, read_image_with_alpha
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.undistort import undistort
from hdrplenoxels.data.validate import check_intrinsics
from hdrplenoxels.geometry.cameras import Cameras

Size = tuple[int, int]  # (W, H)


def _focal(pixels: float | None, fov: float | None, size: int) -> float | None:
    """A focal length in pixels: as stated, or from a field of view (radians) over `size` pixels."""
    if pixels is not None or fov is None:
        return pixels
    return 0.5 * size / math.tan(0.5 * fov)


def _resized(view: ViewDescription, iw: int, ih: int, stated: Intrinsics) -> Intrinsics:
    """Intrinsics of an image that is a resized copy of the stated size (same aspect ratio, to a pixel)."""
    cam = view.camera
    w, h = cam.width, cam.height
    assert w is not None and h is not None  # parsers that allow resized copies state the size
    sx, sy = iw / w, ih / h
    if abs(ih - h * sx) > 1.0 or abs(iw - w * sy) > 1.0:
        raise InputError(
            view.image_path,
            f"image is {iw}x{ih} (WxH) but {view.where} states {w}x{h} for it, and it is not a "
            "resized copy (the aspect ratio differs)",
        )
    fx, fy, cx, cy = stated
    return fx * sx, fy * sy, cx * sx, cy * sy


def _intrinsics(view: ViewDescription, iw: int, ih: int) -> Intrinsics:
    """(fx, fy, cx, cy) of the view for its image as found (`iw` x `ih`)."""
    cam = view.camera
    fx, fy = _focal(cam.fx, cam.fov_x, iw), _focal(cam.fy, cam.fov_y, ih)
    fx, fy = (fx if fx is not None else fy), (fy if fy is not None else fx)
    assert fx is not None and fy is not None, "parsers state a focal length or field of view per view"
    k = (fx, fy, cam.cx if cam.cx is not None else iw / 2.0, cam.cy if cam.cy is not None else ih / 2.0)
    if cam.width in (None, iw) and cam.height in (None, ih):
        return k
    if cam.resized_copies:
        return _resized(view, iw, ih, k)
    stated = (
        f"w={cam.width if cam.width is not None else '?'}, h={cam.height if cam.height is not None else '?'}"
    )
    raise InputError(
        view.image_path,
        f"image is {iw}x{ih} (WxH) but {view.where} states {stated}; resize the image or fix the intrinsics",
    )


def _check_shared_size(
    view: ViewDescription, size: Size, first: dict[Path, tuple[ViewDescription, Size]]
) -> None:
    """Views sharing one file's set of intrinsics must share one image size too (`first`: per file)."""
    other, (w, h) = first.setdefault(view.described_in, (view, size))
    if size != (w, h):
        raise InputError(
            view.described_in,
            f"images have different sizes ({other.name} is {w}x{h}, {view.name} is {size[0]}x{size[1]}) but "
            "share one set of intrinsics; give each frame its own 'w', 'h', 'fl_x', 'fl_y', 'cx', 'cy' or "
            "resize the images",
        )


def _read_view(
    view: ViewDescription, downscale: int
) -> tuple[np.ndarray, np.ndarray | None, Intrinsics, int, Size]:
    """The view's pixels, alpha and intrinsics as read, the factor still to apply after undistortion, and
    the image's full size: the layout's `images_N` copy (factor 1 left) when it exists and has the full
    size over N, else the full-size image (factor N left)."""
    copy = prescaled_copy(view.image_path, downscale)
    full = header_size(view.image_path) if copy is not None else None
    if copy is not None and full is not None:
        rgb, alpha = read_image_with_alpha(copy)
        size = (rgb.shape[1], rgb.shape[0])
        if is_copy_size(full, size, downscale):
            return rgb, alpha, copy_intrinsics(_intrinsics(view, *full), full, size), 1, full
    rgb, alpha = read_image_with_alpha(view.image_path)
    ih, iw = rgb.shape[:2]
    return rgb, alpha, _intrinsics(view, iw, ih), downscale, (iw, ih)


def load_images(description: SceneDescription, downscale: int = 1) -> SceneData:
    """Read every view's image and resolve its camera: the `SceneData` the description stands for, with
    images `downscale` times smaller on each side (module docstring)."""
    if downscale < 1:
        raise InputError(
            description.source, f"the downscale factor must be a whole number >= 1, not {downscale}"
        )
    images, intrinsics, sizes = [], [], []
    composited = False
    first_shared: dict[Path, tuple[ViewDescription, Size]] = {}
    for view in description.views:
        rgb, alpha, k, factor, full = _read_view(view, downscale)
        if view.camera.shared:
            _check_shared_size(view, full, first_shared)
        if alpha is not None and description.alpha == "white":
            rgb = composite_on_white(rgb, alpha)
            composited = True
        if view.camera.distortion is not None:
            try:
                rgb, k = undistort(rgb, k, view.camera.distortion)
            except ValueError as e:
                model = view.camera.distortion.model
                raise InputError(view.image_path, f"cannot undistort ({view.where}, {model}): {e}") from None
        try:
            rgb, k = block_average(rgb, factor), scaled_intrinsics(k, factor)
        except ValueError as e:
            raise InputError(view.image_path, f"cannot downscale: {e}") from None
        size = (rgb.shape[1], rgb.shape[0])
        check_intrinsics(view.described_in, f"image {view.name!r}: ", np.asarray(k), size)
        images.append(rgb)
        intrinsics.append(k)
        sizes.append(size)
    extras: dict[str, Any] = {"layout": description.layout, "downscale": downscale}
    if description.white_background or composited:
        extras["alpha_background"] = "white"
    if description.background_brightness is not None:
        extras["background"] = description.background_brightness
    if description.exposure_init_ev is not None:
        extras["exposure_init_ev"] = description.exposure_init_ev
    extras.update(description.extras)
    return SceneData(
        images=images,
        cameras=Cameras(
            np.stack([v.c2w for v in description.views]), np.asarray(intrinsics), np.asarray(sizes)
        ),
        names=description.names,
        train_ids=description.train_ids,
        test_ids=description.test_ids,
        source=description.source,
        scene_box=description.scene_box,
        box_source=description.box_source,
        aabb_scale=description.aabb_scale,
        forward_facing=description.forward_facing,
        near_far=description.near_far,
        extras=extras,
        bounds_notes=dict(description.bounds_notes),
        sight_lines=description.sight_lines,
    )
