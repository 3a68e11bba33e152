"""Camera exposure settings from a photo's EXIF: exposure time, aperture and ISO.

They are only ever an *initial value* for the tone mapper's per-view exposure (photos without EXIF,
or with a setting missing, work the same, just from a data-derived start). The exposure in stops of a
photo is log2(t * ISO / 100 / N^2): brighter images have larger values, and only differences between
views matter.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

from PIL import Image, TiffImagePlugin

EXIF_IFD = 0x8769
EXPOSURE_TIME = 0x829A
F_NUMBER = 0x829D
ISO_SPEED = 0x8827  # ISOSpeedRatings / PhotographicSensitivity
FOCAL_35MM = 0xA405  # FocalLengthIn35mmFilm: what a phone states of its lens, and COLMAP's focal prior
FRAME_DIAGONAL_MM = 43.27  # the 35 mm frame's diagonal, over which COLMAP reads a 35 mm-equivalent focal


@dataclass(frozen=True)
class ExifExposure:
    exposure_time: float  # seconds
    f_number: float
    iso: float

    @property
    def stops(self) -> float:
        """Exposure in stops relative to 1 s, f/1, ISO 100 (larger = brighter image)."""
        return math.log2(self.exposure_time * self.iso / 100.0 / self.f_number**2)

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def _positive(value) -> float | None:
    """A positive finite float from an EXIF value (rational, int, or a tuple whose first entry counts)."""
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
    try:
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def read_exif_exposure(path: str | Path) -> ExifExposure | None:
    """The photo's exposure time, f-number and ISO, or None when any of them is absent or unreadable."""
    try:
        with Image.open(path) as img:
            return exif_exposure(img.getexif())
    except Exception:  # EXIF is optional metadata: a broken block must never stop processing
        return None


def exif_exposure(exif: Image.Exif) -> ExifExposure | None:
    """`read_exif_exposure` for EXIF already read (e.g. by a caller that also copies it elsewhere)."""
    try:
        tags = {**exif, **exif.get_ifd(EXIF_IFD)}
    except Exception:  # a broken EXIF sub-directory: treat as absent
        return None
    t, n, iso = (_positive(tags.get(k)) for k in (EXPOSURE_TIME, F_NUMBER, ISO_SPEED))
    if t is None or n is None or iso is None:
        return None
    return ExifExposure(t, n, iso)


def exif_block(exposure: ExifExposure, focal_35mm: int | None = None) -> Image.Exif:
    """An EXIF block stating `exposure` and, where given, the lens's 35 mm-equivalent focal length: what a
    phone writes into each photo, for photos made in code (`synth.photos`, tests)."""
    exif = Image.Exif()
    ifd = exif.get_ifd(EXIF_IFD)
    ifd[EXPOSURE_TIME] = TiffImagePlugin.IFDRational(exposure.exposure_time)
    ifd[F_NUMBER] = TiffImagePlugin.IFDRational(exposure.f_number)
    ifd[ISO_SPEED] = round(exposure.iso)
    if focal_35mm:
        ifd[FOCAL_35MM] = focal_35mm
    return exif
