"""Controllable exposure, measured rather than assumed: view i rendered through view j's learned tone
(exposure, white balance, response), against what view j's camera would have photographed from view i's
place: the synthetic capture's true HDR of view i through view j's true camera settings (noise left out).

Where the tone mapper separates the scene from the cameras, re-exposing a view this way is as good as
rendering it through its own tone; where it has put part of a camera's setting into the scene (or the
reverse), the re-exposed picture is off by what was misplaced, and the further for tones far apart.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data.image_io import read_exr
from hdrplenoxels.eval.metrics import psnr
from hdrplenoxels.synth.pipeline import CameraSettings, capture
from hdrplenoxels.train.model import Model


@dataclass
class Reexposure:
    view: int  # the view rendered
    tone: int  # the view whose tone it is seen through
    stops: float  # how far apart their true exposures are (tone's EV minus view's)
    psnr: float  # against the truth of that view through that camera
    own_tone_psnr: float  # the view through its own tone against the same truth (no re-exposure at all)


def camera_settings(dataset: Path) -> list[CameraSettings]:
    """Each view's true camera, noise left out, from a synthetic capture's camera_truth.json."""
    names = {f.name for f in fields(CameraSettings)}
    views = json.loads((Path(dataset) / "camera_truth.json").read_text())["views"]
    return [
        CameraSettings(**({k: v for k, v in view.items() if k in names} | {"noise": None})) for view in views
    ]


def reexposure_target(dataset: Path, view: int, camera: CameraSettings) -> torch.Tensor:
    """View `view`'s true HDR photographed by `camera`: what that camera would have taken from there."""
    record = json.loads((Path(dataset) / "camera_truth.json").read_text())["views"][view]
    hdr = read_exr(Path(dataset) / record["hdr"])
    return torch.from_numpy(capture(hdr, camera).astype(np.float32) / 255.0)


def reexposure(model: Model, dataset: Path, pairs: list[tuple[int, int]]) -> list[Reexposure]:
    """For each (view, tone) pair: view rendered by `model` through tone's learned tone against the truth
    (module docstring); `dataset` is the synthetic capture the model trained on. Each view is rendered
    once, however many pairs it is in."""
    cameras = camera_settings(dataset)
    radiance: dict[int, torch.Tensor] = {}
    out = []
    for view, tone in pairs:
        target = reexposure_target(dataset, view, cameras[tone])
        with torch.no_grad():
            if view not in radiance:
                radiance[view] = model.render_camera(view)
            picture = model.to_ldr(radiance[view], tone).cpu()
            own = model.to_ldr(radiance[view], view).cpu()
        stops = cameras[tone].ev - cameras[view].ev
        out.append(
            Reexposure(view, tone, float(stops), float(psnr(picture, target)), float(psnr(own, target)))
        )
    return out
