"""Training on smaller images: an exact area filter, and a layout's own `images_N` copies when present.

`block_average` averages each N x N block of pixels (a box filter, the area filter for an integer factor).
An image whose size is not a multiple of N loses its last W mod N columns and H mod N rows first, so that
every output pixel is a whole block: output pixel j covers input pixels [jN, jN + N), whose centre
jN + N/2 = N (j + 0.5) is the output pixel's centre under the +0.5 convention of `geometry.cameras`.
The intrinsics then scale exactly, fx/N, fy/N, cx/N, cy/N, and every output pixel's ray is the ray
through its block's centre at full size. Lens distortion is undone at full size before this, so the
pinhole intrinsics are the ones scaled.

LLFF (`images_8/`), nerfstudio (`images_2/`) and mip-NeRF 360 datasets ship such copies beside `images/`;
`prescaled_copy` finds the copy of one image. A copy's size is the full size over N, rounded either way
by the tool that made it, so its intrinsics scale by its actual size ratio per axis (LLFF's rule).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from hdrplenoxels.data.description import Intrinsics

COPY_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".JPEG")
COPY_SIZE_TOLERANCE = 1.0  # pixels: a copy's size is the full size over N, rounded by its maker


def block_average(image: np.ndarray, factor: int) -> np.ndarray:
    """The (H // N, W // N, C) mean of each N x N block; uint8 in, rounded uint8 out (floats stay float)."""
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    if h < 1 or w < 1:
        raise ValueError(f"a {image.shape[1]}x{image.shape[0]} image is smaller than the factor {factor}")
    blocks = image[: h * factor, : w * factor].reshape(h, factor, w, factor, *image.shape[2:])
    mean = blocks.astype(np.float64).mean(axis=(1, 3))
    if image.dtype == np.uint8:
        return np.rint(mean).astype(np.uint8)
    return mean.astype(image.dtype)


def scaled_intrinsics(k: Intrinsics, factor: int) -> Intrinsics:
    """Intrinsics of `block_average(image, factor)` for an image with intrinsics `k` (exact, see above)."""
    fx, fy, cx, cy = k
    return fx / factor, fy / factor, cx / factor, cy / factor


def copy_intrinsics(k: Intrinsics, full: tuple[int, int], copy: tuple[int, int]) -> Intrinsics:
    """Intrinsics of a resized copy (W', H') of a (W, H) image with intrinsics `k`: per-axis size ratios."""
    sx, sy = copy[0] / full[0], copy[1] / full[1]
    fx, fy, cx, cy = k
    return fx * sx, fy * sy, cx * sx, cy * sy


def prescaled_copy(image_path: Path, factor: int) -> Path | None:
    """`<dir>_<N>/<same stem>.*` beside the image's folder `<dir>/` (e.g. images_4/IMG_01.png for
    images/IMG_01.JPG), or None. LLFF's `images_N` are PNG conversions, hence any extension."""
    folder = image_path.parent.parent / f"{image_path.parent.name}_{factor}"
    if factor == 1 or not folder.is_dir():
        return None
    for ext in (image_path.suffix, *COPY_EXTENSIONS):
        candidate = folder / f"{image_path.stem}{ext}"
        if candidate.is_file():
            return candidate
    return None


def header_size(path: Path) -> tuple[int, int] | None:
    """(W, H) from an image file's header without decoding it; None when Pillow cannot tell."""
    try:
        with Image.open(path) as img:
            return img.size
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError):
        return None


def is_copy_size(full: tuple[int, int], copy: tuple[int, int], factor: int) -> bool:
    """Whether a `copy`-sized image is the `full`-sized one reduced `factor` times (to a pixel)."""
    return all(abs(c - f / factor) <= COPY_SIZE_TOLERANCE for c, f in zip(copy, full, strict=True))
