"""Reading a user's video file with PyAV: its frames as a viewer shows them, their times, and its tags.

Phones store a clip in the sensor's pixel grid and say in a display matrix how to turn it for viewing (a
portrait clip is stored landscape with a rotation of -90 degrees); frames come out turned as FFmpeg's own
player turns them, so that SfM and training see the same upright pixels. Every problem with the file
becomes one `InputError` naming it, and a frame size the header declares beyond 8K is refused before
anything that size is decoded.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from hdrplenoxels.core.errors import InputError

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v")
MAX_PIXELS = 7680 * 4320  # 8K UHD: larger declared frames are refused before decoding
# Container tags kept with the frames, by what they mean; the first tag present wins.
_TAGS = {
    "make": ("com.apple.quicktime.make", "com.android.manufacturer", "make"),
    "model": ("com.apple.quicktime.model", "com.android.model", "model"),
    "creation_time": ("com.apple.quicktime.creationdate", "creation_time"),
}


@dataclass(frozen=True)
class VideoFrame:
    index: int  # position among the decoded frames, in presentation order
    time: float  # seconds after the first frame
    pixels: np.ndarray  # (H, W) uint8 grey or (H, W, 3) uint8 RGB, upright


@dataclass(frozen=True)
class VideoInfo:
    width: int  # of the upright frames
    height: int
    rotation: int  # degrees the stored frames are turned counterclockwise for display: 0, 90, 180 or 270
    fps: float | None  # the stream's average frame rate, where it states one
    tags: dict[str, str]  # make, model and creation_time, where the container holds them


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_EXTENSIONS


def _quarter_turns(rotation: float | None) -> int:
    """Counterclockwise quarter turns from the display matrix's angle (FFmpeg's av_display_rotation_get)."""
    if rotation is None or not np.isfinite(rotation):
        return 0
    return int(round(rotation / 90.0)) % 4


def _open(path: Path):
    import av

    if not path.exists():
        raise InputError(path, "no such file")
    if not path.is_file():
        raise InputError(path, "is not a file")
    try:
        container = av.open(str(path), metadata_errors="replace")
    except (av.FFmpegError, UnicodeDecodeError, ValueError) as e:
        raise InputError(path, f"not a decodable video ({_reason(e)})") from None
    if not container.streams.video:
        container.close()
        raise InputError(path, "holds no video stream")
    stream = container.streams.video[0]
    if stream.codec_context is None:
        container.close()
        raise InputError(path, "its video stream's codec is unknown or cannot be decoded here")
    w, h = stream.codec_context.width, stream.codec_context.height
    if w * h > MAX_PIXELS:
        container.close()
        raise InputError(path, f"frames of {w} x {h} pixels are beyond 8K; scale the video down first")
    stream.thread_type = "AUTO"
    return container, stream


def _reason(e: Exception) -> str:
    text = getattr(e, "strerror", None) or str(e)
    return text.splitlines()[0] if text else type(e).__name__


def frames(
    path: str | Path, fmt: Literal["gray", "rgb24"], wanted: set[int] | None = None, scale: float = 1.0
) -> Iterator[VideoFrame]:
    """Every decoded frame (or those whose index is in `wanted`), upright, optionally scaled down first."""
    import av

    path = Path(path)
    container, stream = _open(path)
    first_time = None
    try:
        for index, frame in enumerate(container.decode(stream)):
            time = frame.time if frame.time is not None else index / float(stream.average_rate or 1)
            first_time = time if first_time is None else first_time
            if wanted is not None and index not in wanted:
                continue
            if frame.width * frame.height > MAX_PIXELS:  # a stream may change its size part way
                raise InputError(path, f"frame {index} is {frame.width} x {frame.height} pixels, beyond 8K")
            w, h = max(2, round(frame.width * scale)), max(2, round(frame.height * scale))
            pixels = frame.reformat(width=w, height=h, format=fmt).to_ndarray()
            pixels = np.ascontiguousarray(np.rot90(pixels, _quarter_turns(frame.rotation)))
            yield VideoFrame(index, time - first_time, pixels)
    except (av.FFmpegError, ValueError, MemoryError) as e:
        raise InputError(path, f"cannot decode video ({_reason(e)})") from None
    finally:
        container.close()


def video_info(path: str | Path) -> VideoInfo:
    """Size and turn of the upright frames and the tags worth keeping; decodes the first frame (so a file
    that opens but holds no decodable picture fails here)."""
    import av

    path = Path(path)
    container, stream = _open(path)
    try:
        tags = {**dict(container.metadata), **dict(stream.metadata)}
        fps = float(stream.average_rate) if stream.average_rate else None
        frame = next(container.decode(stream), None)
    except (av.FFmpegError, ValueError, MemoryError) as e:
        raise InputError(path, f"cannot decode video ({_reason(e)})") from None
    finally:
        container.close()
    if frame is None:
        raise InputError(path, "holds no decodable video frame")
    turns = _quarter_turns(frame.rotation)
    w, h = (frame.height, frame.width) if turns % 2 else (frame.width, frame.height)
    kept = {key: next((tags[t] for t in names if tags.get(t)), None) for key, names in _TAGS.items()}
    return VideoInfo(w, h, 90 * turns, fps, {k: v for k, v in kept.items() if v is not None})
