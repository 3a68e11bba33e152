"""A video as `process` input: about N frames spread in time, the sharpest of each stretch, as photos.

The clip is cut into N stretches of equal duration and the frame with the highest sharpness (variance of
the Laplacian, on frames scaled by `SCORE_SCALE`) is kept from each: a frame blurred by a shaking hand
loses to its sharp neighbours, and frames of the same stretch see nearly the same content, so their
scores compare like with like. The video is decoded twice, once to score every frame and once to write
the chosen ones, so that only one frame is ever held in memory. The frames are written as JPEGs whose
EXIF carries the camera make, model and date the container states. Measurements: JOURNAL.md,
"Video input".
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
from PIL import Image

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.video import VideoInfo, frames
from hdrplenoxels.process.photos import Photo

DEFAULT_FRAMES = 150
SCORE_SCALE = 0.5  # frames are scored at this fraction of their size (a quarter of the pixels)
_EXIF_TAGS = {"make": 0x010F, "model": 0x0110, "creation_time": 0x0132}  # Make, Model, DateTime


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian: edges a blur smears out lower it."""
    g = grey.astype(np.float32)
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def choose_frames(times: np.ndarray, scores: np.ndarray, n: int) -> list[int]:
    """Indices of the best-scoring frame in each of `n` stretches of equal duration (all frames when
    there are no more than `n`); a stretch that holds no frame (a gap in the clip) gives none."""
    if len(times) <= n:
        return list(range(len(times)))
    edges = np.linspace(times[0], times[-1], n + 1)
    stretch = np.clip(np.searchsorted(edges, times, side="right") - 1, 0, n - 1)
    chosen = []
    for k in range(n):
        members = np.flatnonzero(stretch == k)
        if len(members):
            chosen.append(int(members[np.argmax(scores[members])]))
    return chosen


def _exif(info: VideoInfo) -> Image.Exif:
    """Make, model and date (EXIF's "YYYY:MM:DD HH:MM:SS") from the container's tags, where present."""
    exif = Image.Exif()
    for key in ("make", "model"):
        if key in info.tags:
            exif[_EXIF_TAGS[key]] = info.tags[key][:100]
    try:
        when = datetime.fromisoformat(info.tags["creation_time"])
        exif[_EXIF_TAGS["creation_time"]] = when.strftime("%Y:%m:%d %H:%M:%S")
    except (KeyError, ValueError):  # no date, or one in another form: leave it out
        pass
    return exif


def stage_video(source: Path, info: VideoInfo, staging: Path, n: int) -> tuple[list[Photo], dict]:
    """Write the chosen frames into `staging`; returns them as photos and what transforms.json records."""
    times, scores = [], []
    for frame in frames(source, "gray", scale=SCORE_SCALE):
        times.append(frame.time)
        scores.append(sharpness(frame.pixels))
    if not times:
        raise InputError(source, "holds no decodable video frame")
    times_a, scores_a = np.asarray(times), np.asarray(scores)
    if np.any(np.diff(times_a) <= 0):  # timestamps missing or out of order: frames in decoding order
        times_a = np.arange(len(times), dtype=float)
    chosen = choose_frames(times_a, scores_a, n)
    even = np.unique(np.linspace(0, len(times) - 1, len(chosen)).round().astype(int))
    staging.mkdir(parents=True, exist_ok=True)
    exif = _exif(info)
    photos = []
    for frame in frames(source, "rgb24", wanted=set(chosen)):
        name = f"frame_{frame.index:05d}.jpg"
        Image.fromarray(frame.pixels).save(staging / name, quality=95, exif=exif)
        h, w = frame.pixels.shape[:2]
        extra = {"video_time_s": round(frame.time, 4), "sharpness": round(scores[frame.index], 2)}
        photos.append(Photo(source, name, w, h, None, True, extra))
    facts = {
        "video": {"rotation_deg": info.rotation, "fps": info.fps} | info.tags,
        "frames_decoded": len(times),
        "sharpness_chosen_median": float(np.median(scores_a[chosen])),
        "sharpness_even_median": float(np.median(scores_a[even])),
    }
    return photos, facts
