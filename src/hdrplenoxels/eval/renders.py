"""Rendering a trained model's views, or new poses, to float EXR (linear radiance) and PNG files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from hdrplenoxels.data.image_io import write_exr, write_png
from hdrplenoxels.data.poses import DEFAULT_POSE_CONVENTION, PoseConvention, to_opencv
from hdrplenoxels.render import Backend
from hdrplenoxels.render.nerf import Appearance
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.model import Model


@dataclass
class RenderJob:
    """One image to write: a camera, and the view whose learned tone maps its PNG."""

    name: str
    c2w: np.ndarray
    intrinsics: np.ndarray
    size: tuple[int, int]
    tone_view: int


@dataclass
class ChosenTone:
    """A user-chosen tone for every PNG instead of each view's own (see `Model.to_ldr_controlled`)."""

    ev: float = 0.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    crf_from: int | None = None
    source: ToneMapper | None = None  # whose response curves; None: the model's own
    auto: bool = False  # ev and wb relative to the controller's tone for each render, not the mean

    @property
    def suffix(self) -> str:
        """What a PNG's name gains: `_auto` (and its EV if not 0) or `_ev<EV>`."""
        if self.auto:
            return "_auto" + (f"_ev{self.ev:+g}" if self.ev else "")
        return f"_ev{self.ev:+g}"


def view_jobs(model: Model, views: Literal["test", "train", "all"]) -> list[RenderJob]:
    """The model's own training-scene views, each seen through its own learned tone."""
    ids = {"test": model.test_ids, "train": model.train_ids, "all": range(len(model.cameras))}[views]
    cams = model.cameras
    return [
        RenderJob(Path(model.names[i]).stem, cams.c2w[i], cams.intrinsics[i], cams.size(i), i) for i in ids
    ]


def pose_jobs(model: Model, c2w_data: np.ndarray) -> list[RenderJob]:
    """New OpenCV poses in the dataset's frame, with the first test view's intrinsics and size, seen through
    the reference image's tone (the one that fixes the radiance gauge)."""
    ref = model.test_ids[0] if model.test_ids else 0
    view = int(model.tonemapper.reference) if model.tonemapper is not None else ref
    poses = model.geometry.poses_to_world(c2w_data)
    intrinsics, size = model.cameras.intrinsics[ref], model.cameras.size(ref)
    return [RenderJob(f"pose_{k:03d}", pose, intrinsics, size, view) for k, pose in enumerate(poses)]


@dataclass
class Picture:
    """One rendered view: `hdr`, linear radiance (H, W, 3) with no upper bound (what an EXR holds), and
    `ldr`, the picture through a tone (H, W, 3) in [0, 1]."""

    hdr: torch.Tensor
    ldr: torch.Tensor


def render_pose(
    model: Model,
    c2w: np.ndarray,
    tone: str | int = "auto",
    ev: float = 0.0,
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0),
    backend: Backend = "warp",
    convention: PoseConvention = DEFAULT_POSE_CONVENTION,
) -> Picture:
    """The view from `c2w`, a 4x4 camera-to-world pose in the dataset's frame, in `convention`'s axes
    (OpenGL unless told "opencv", as `render --pose`: data/poses.py), at the first test view's
    intrinsics and size, seen through `tone`: "auto" (the tone controller's
    prediction for this view), "mean" (the mean learned tone), or a view's index (that photo's whole
    learned tone); `ev` stops and gains `wb` are relative to "auto" or "mean". A model trained without
    tone mapping has no tones: its `ldr` is the radiance clipped."""
    job = pose_jobs(model, to_opencv(np.asarray(c2w, dtype=np.float64).reshape(1, 4, 4), convention))[0]
    radiance = model.render_view(
        job.c2w, job.intrinsics, job.size, backend, model.default_appearance(job.tone_view)
    )
    if model.tonemapper is None:
        ldr = radiance.clamp(0.0, 1.0)
    elif isinstance(tone, int):
        if ev != 0.0 or tuple(wb) != (1.0, 1.0, 1.0):
            raise ValueError("a view's tone is that photo's whole tone: leave ev and wb as they are")
        ldr = model.to_ldr(radiance, tone)
    elif tone in ("auto", "mean"):
        predicted = model.auto_tone() if tone == "auto" else None
        ldr = model.to_ldr_controlled(radiance, ev, tuple(wb), tone=predicted)
    else:
        raise ValueError(f"tone {tone!r}: use 'auto', 'mean' or a view's index")
    return Picture(model.hdr(radiance).cpu(), ldr.cpu())


def write_renders(
    model: Model,
    jobs: list[RenderJob],
    out: Path,
    backend: Backend,
    chosen: ChosenTone | None = None,
    appearance: Appearance | None = None,
) -> None:
    """NAME.exr (linear radiance) and a PNG per job: NAME.png through the job's own view's tone, or
    NAME_ev<EV>.png (NAME_auto.png) through `chosen`. A NeRF-A renders each job with its view's appearance
    embedding, or with `appearance` when given."""
    suffix = chosen.suffix if chosen is not None else ""
    for job in jobs:
        job_appearance = appearance or model.default_appearance(job.tone_view)
        radiance = model.render_view(job.c2w, job.intrinsics, job.size, backend, job_appearance)
        write_exr(out / f"{job.name}.exr", model.hdr(radiance).cpu().numpy())
        if chosen is not None:
            predicted = model.auto_tone() if chosen.auto else None
            ldr = model.to_ldr_controlled(
                radiance, chosen.ev, chosen.wb, chosen.crf_from, chosen.source, predicted
            )
        else:
            ldr = model.to_ldr(radiance, job.tone_view)
        write_png(out / f"{job.name}{suffix}.png", ldr.cpu().numpy())
