"""The photo folder a user hands to `process`: find the images, check each one, stage them for COLMAP.

Every image is decoded once here, so a truncated or unsupported file fails before any SfM work with a
line naming it. Plain 8-bit RGB JPEG/PNG files stored upright are staged as symlinks (COLMAP still sees
their EXIF focal length). A photo whose EXIF orientation says it is shown turned or mirrored (a phone held
upright) is staged as an upright copy, a JPEG keeping its EXIF, so COLMAP and training see the pixels a
viewer shows; so is a HEIC/HEIF photo (an iPhone's default), which COLMAP cannot read. Anything else we
can convert safely (greyscale, 16-bit greyscale, RGBA composited on white, TIFF/BMP) is staged as an
8-bit RGB PNG. EXIF exposure settings are read from the originals.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.exif import ExifExposure, exif_exposure
from hdrplenoxels.data.image_io import composite_on_white, read_image_with_alpha, write_png

PHOTO_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".heic", ".heif")
AS_IS_EXTENSIONS = (".jpg", ".jpeg", ".png")
HEIF_EXTENSIONS = (".heic", ".heif")
ORIENTATION = 0x0112  # EXIF: 1 upright; 2-8 mirrored and/or turned by quarter turns


@dataclass
class Photo:
    source: Path  # the user's file
    name: str  # file name in the staging folder (what COLMAP and transforms.json call it)
    width: int  # of the staged (upright) image
    height: int
    exif: ExifExposure | None
    converted: bool  # staged as a converted or turned copy rather than a link to the original
    extra: dict = field(default_factory=dict)  # more per-frame facts for transforms.json (a video's time)


def find_photos(folder: Path) -> list[Path]:
    """Image files directly inside `folder`, sorted by name."""
    if not folder.exists():
        raise InputError(folder, "no such folder")
    if not folder.is_dir():
        raise InputError(folder, "is not a folder: give the folder that holds the photos, or a video")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_EXTENSIONS)
    if not photos:
        raise InputError(folder, f"no photos found (looked for {', '.join(PHOTO_EXTENSIONS)})")
    return photos


def _header(path: Path) -> tuple[str, Image.Exif]:
    """Pillow mode and EXIF, read once from the file header (a broken EXIF block counts as none)."""
    with Image.open(path) as img:
        try:
            exif = img.getexif()
        except Exception:  # EXIF is optional metadata: it must never stop processing
            exif = Image.Exif()
        return img.mode, exif


def _orientation(exif: Image.Exif) -> int:
    """The EXIF orientation, 1 (as stored) when absent or not one of the eight defined values."""
    value = exif.get(ORIENTATION)
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def _upright(rgb: np.ndarray, orientation: int) -> np.ndarray:
    """The pixels as a viewer shows them (Pillow's reading of the eight EXIF orientations)."""
    img = Image.fromarray(rgb)
    img.getexif()[ORIENTATION] = orientation
    return np.asarray(ImageOps.exif_transpose(img))


def stage_photos(paths: list[Path], staging: Path) -> list[Photo]:
    """Check every photo and link, turn or convert it into `staging` (names there are unique)."""
    staging.mkdir(parents=True, exist_ok=True)
    photos, seen = [], set()
    for path in paths:
        rgb, alpha = read_image_with_alpha(path)  # raises InputError naming the file
        mode, exif = _header(path)
        orientation = _orientation(exif)
        suffix = path.suffix.lower()
        plain = alpha is None and mode == "RGB" and suffix in AS_IS_EXTENSIONS
        # a JPEG copy keeps the EXIF (COLMAP's focal prior): for a turned JPEG, and for HEIC
        as_jpeg = alpha is None and (suffix in HEIF_EXTENSIONS or (plain and suffix in (".jpg", ".jpeg")))
        name = path.name if plain else path.stem + (".jpg" if as_jpeg else ".png")
        if name in seen:
            raise InputError(path, f"two photos would both be called {name!r}; rename one of them")
        seen.add(name)
        target = staging / name
        if alpha is not None:
            rgb = composite_on_white(rgb, alpha)
        if orientation != 1:
            rgb = _upright(rgb, orientation)
        if plain and orientation == 1:
            os.symlink(path.resolve(), target)
        elif as_jpeg:
            exif.pop(ORIENTATION, None)
            Image.fromarray(rgb).save(target, quality=95, subsampling=0, exif=exif)
        else:
            write_png(target, rgb)
        converted = not plain or orientation != 1
        photos.append(Photo(path, name, rgb.shape[1], rgb.shape[0], exif_exposure(exif), converted))
    return photos
