"""Camera-path videos of a trained model: H.264 MP4 through PyAV (a wheel that carries its own FFmpeg),
with an exposure and white balance per frame, and optional float EXR frames (linear radiance)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hdrplenoxels.core.atomic import atomic_path
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.camera_path import CameraPath, PathFrame
from hdrplenoxels.data.image_io import write_exr
from hdrplenoxels.geometry.paths import orbit, spiral, through_cameras
from hdrplenoxels.render import Backend
from hdrplenoxels.train.model import Model


@dataclass
class VideoFrame:
    """A camera in the grid's world frame (OpenCV c2w, fx fy cx cy) and the exposure and gains to show it
    with."""

    c2w: np.ndarray
    intrinsics: np.ndarray
    ev: float = 0.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)


def frame_ldr(
    model: Model,
    radiance: torch.Tensor,
    ev: float,
    wb: tuple[float, float, float],
    crf_from: int | None = None,
    tone: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """The picture of one frame in [0, 1]: through the learned tone with the frame's exposure and white
    balance (relative to the views' mean, or to `tone`'s gains: see `Model.to_ldr_controlled`) and view
    `crf_from`'s response (default: the reference's), or for a model without one, its radiance scaled and
    clipped."""
    if model.tonemapper is not None:
        return model.to_ldr_controlled(radiance, ev, wb, crf_from, tone=tone)
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
    tone: Callable[[torch.Tensor], torch.Tensor] | None = None,
    crf_from: int | None = None,
) -> Path:
    """Render `frames` at `size` (W, H, both even: H.264's 4:2:0 needs it) into `out` (written to a
    temporary file, then renamed). `quality` is x264's CRF (lower: closer to the renders, larger files).
    `tone`, `crf_from`: the tone each frame's EV and gains are relative to, and whose response (see
    `frame_ldr`): an `ExposureTracker` makes a video's auto exposure."""
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
            ldr = frame_ldr(model, radiance, frame.ev, frame.wb, crf_from, tone)
            picture = av.VideoFrame.from_ndarray(to_uint8(ldr))
            for packet in stream.encode(picture):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return Path(out)


def ramp(start: float, stop: float, frames: int) -> list[float]:
    """Evenly from `start` to `stop` over `frames` frames (an exposure sweep)."""
    return np.linspace(start, stop, frames).tolist() if frames > 1 else [start]


def path_frames(model: Model, camera_path: CameraPath) -> list[VideoFrame]:
    """A camera_path.json's frames (dataset frame) as cameras in the model's world frame."""
    poses = model.geometry.poses_to_world(np.stack([f.c2w for f in camera_path.frames]))
    return [
        VideoFrame(pose, camera_path.intrinsics(f), f.ev, f.wb) for pose, f in zip(poses, camera_path.frames)
    ]


def generated_frames(
    model: Model, kind: str, frames: int, size: tuple[int, int], evs: Sequence[float]
) -> list[VideoFrame]:
    """An orbit around the scene's centre, a spiral for forward-facing captures, or a path through the
    training cameras; intrinsics of the first test view, scaled to `size`; one EV per frame."""
    cams = model.cameras
    train = cams.c2w[sorted(model.train_ids)] if model.train_ids else cams.c2w
    centre = np.asarray(model.geometry.center, dtype=np.float64)
    if kind == "orbit":
        poses = orbit(train, centre, frames)
    elif kind == "spiral":
        focus = float(np.linalg.norm(centre - train[:, :3, 3].mean(0)))
        poses = spiral(train, focus if focus > 0 else 1.0, frames)
    elif kind == "interp":
        poses = through_cameras(train, frames)
    else:
        raise ValueError(f"unknown path {kind!r}; choose orbit, spiral or interp")
    view = model.test_ids[0] if model.test_ids else 0
    k = cams.intrinsics_at(view, size)
    return [VideoFrame(p, k, ev) for p, ev in zip(poses, evs)]


def camera_path_of(
    model: Model, frames: Sequence[VideoFrame], size: tuple[int, int], fps: float
) -> CameraPath:
    """Frames as a camera_path.json (dataset frame), to edit or to render again."""
    world = np.stack([f.c2w for f in frames])
    data = model.geometry.poses_to_data(world)
    fov = [math.degrees(2.0 * math.atan(0.5 * size[1] / f.intrinsics[1])) for f in frames]
    entries = [PathFrame(c2w, v, f.ev, f.wb) for c2w, v, f in zip(data, fov, frames)]
    return CameraPath(entries, size[0], size[1], fps)
