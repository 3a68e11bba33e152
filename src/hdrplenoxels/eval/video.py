"""Camera-path videos of a trained model: H.264 MP4 through PyAV (a wheel that carries its own FFmpeg),
with an exposure and white balance per frame, and optional float EXR frames (linear radiance)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hdrplenoxels.core.atomic import atomic_path
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.image_io import write_exr
from hdrplenoxels.render import Backend
from hdrplenoxels.train.model import Model


@dataclass
class VideoFrame:
    """A camera in the grid's world frame (OpenCV c2w, fx fy cx cy) and the look to show it with."""

    c2w: np.ndarray
    intrinsics: np.ndarray
    ev: float = 0.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)


def frame_ldr(
    model: Model, radiance: torch.Tensor, ev: float, wb: tuple[float, float, float]
) -> torch.Tensor:
    """The picture of one frame in [0, 1]: through the learned camera with the frame's exposure and white
    balance (relative to the views' mean), or for a model without one, its radiance scaled and clipped."""
    if model.tonemapper is not None:
        return model.to_ldr_controlled(radiance, ev, wb)
    gains = torch.tensor(wb, dtype=radiance.dtype, device=radiance.device) * 2.0**ev
    return (radiance * gains).clamp(0.0, 1.0)


def to_uint8(ldr: torch.Tensor) -> np.ndarray:
    return (ldr.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def render_video(
    model: Model,
    frames: Sequence[VideoFrame],
    size: tuple[int, int],
    out: Path,
    fps: float,
    backend: Backend = "warp",
    exr_dir: Path | None = None,
    progress: bool = True,
    quality: int = 12,
) -> Path:
    """Render `frames` at `size` (W, H, both even: H.264's 4:2:0 needs it) into `out` (written to a
    temporary file, then renamed). `quality` is x264's CRF (lower: closer to the renders, larger files)."""
    import av

    width, height = size
    if width % 2 or height % 2 or width <= 0 or height <= 0:
        raise InputError(None, f"--resolution {width}x{height}: H.264 needs an even width and height")
    if not frames:
        raise InputError(None, "the camera path has no frames")
    with atomic_path(out, suffix=".mp4") as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": str(quality), "preset": "medium"}
        for k, frame in enumerate(tqdm(frames, disable=not progress, unit="frame")):
            radiance = model.render_view(frame.c2w, frame.intrinsics, size, backend)
            if exr_dir is not None:
                write_exr(Path(exr_dir) / f"frame_{k:04d}.exr", model.hdr(radiance).cpu().numpy())
            picture = av.VideoFrame.from_ndarray(to_uint8(frame_ldr(model, radiance, frame.ev, frame.wb)))
            for packet in stream.encode(picture):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return Path(out)


def ramp(start: float, stop: float, frames: int) -> list[float]:
    """Evenly from `start` to `stop` over `frames` frames (an exposure sweep)."""
    return np.linspace(start, stop, frames).tolist() if frames > 1 else [start]
