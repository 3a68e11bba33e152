"""A captured dataset's images as a phone writes them: JPEGs whose EXIF states each photo's exposure and the
lens, from the camera truth, so that `process` can be tested and measured on photos with a known answer.

The exposure time is 1/100 s at EV 0, doubled per stop of the view's EV, at f/2.4 and ISO 100 (a phone's
aperture is fixed); the 35 mm-equivalent focal follows from the true focal over the frame's diagonal, as
COLMAP reads it back, rounded to the whole millimetre EXIF holds. `focal_error` makes the stated lens wrong
on purpose, as a cropped sensor's or an adapter's EXIF is.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from PIL import Image

from hdrplenoxels.core.atomic import atomic_path
from hdrplenoxels.data.exif import FRAME_DIAGONAL_MM, ExifExposure, exif_block

PHONE_JPEG_QUALITY = 85  # what phones' cameras save at (their default sits at 85-95)
EXPOSURE_AT_EV0_S = 0.01
F_NUMBER = 2.4
ISO = 100.0
PHOTOS = "photos"  # the folder `write_photos` fills beside a dataset's images/


def focal_35mm(focal_px: float, width: int, height: int) -> int:
    """The whole-millimetre 35 mm-equivalent focal of a focal length in pixels."""
    return round(focal_px * FRAME_DIAGONAL_MM / math.hypot(width, height))


def write_photos(
    dataset: Path, out: Path | None = None, quality: int = PHONE_JPEG_QUALITY, focal_error: float = 0.0
) -> Path:
    """`out/<view>.jpg` (`out` by default `dataset/photos`) for each image of `dataset` (a
    `capture_dataset` folder): JPEG at `quality`, EXIF from `dataset/camera_truth.json` and
    `dataset/transforms.json`, the stated focal (1 + `focal_error`) times the true one. Returns `out`."""
    dataset = Path(dataset)
    meta = json.loads((dataset / "transforms.json").read_text())
    truth = json.loads((dataset / "camera_truth.json").read_text())["views"]
    lens = focal_35mm(meta["fl_x"] * (1.0 + focal_error), meta["w"], meta["h"])
    out = dataset / PHOTOS if out is None else Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for frame, view in zip(meta["frames"], truth):
        name = Path(frame["file_path"]).stem
        exposure = ExifExposure(EXPOSURE_AT_EV0_S * 2.0 ** view["ev"], F_NUMBER, ISO)
        with Image.open(dataset / frame["file_path"]) as img:
            rgb = img.convert("RGB")
        with atomic_path(out / f"{name}.jpg") as path:
            rgb.save(path, format="JPEG", quality=quality, exif=exif_block(exposure, lens))
    return out
