"""The median exposure (Table S2's task): a model trained on darker (-3 EV) and brighter (+3 EV) views
renders the exposure between them, scored against the true 0 EV captures of the test views.

Ours and NeRF + tone module render it through the learned tone at the midpoint of the two groups'
learned exposures; NeRF-A through its appearance embedding interpolated between the two groups' mean
embeddings, with a weight chosen on validation captures (`validated_weight`), never on test views.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from hdrplenoxels.data.image_io import read_exr
from hdrplenoxels.eval.evaluate import METRIC_KEYS
from hdrplenoxels.eval.truth import SynthTruth
from hdrplenoxels.experiments.common import (
    VALIDATION_SEED,
    ExperimentSettings,
    Method,
    captured,
    method_spec,
    right_half_metrics,
    validation_root,
)
from hdrplenoxels.render.nerf import Appearance
from hdrplenoxels.synth.pipeline import CameraSettings, PipelineConfig, capture
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.runs import RunSpec, train_spec

DARK_BRIGHT = PipelineConfig(ev_set=(-3.0, 3.0))
WEIGHTS = tuple(i / 10 for i in range(11))  # NeRF-A interpolation weights compared on validation captures
VALIDATION_NERF_A = Method("validation_nerf_a", "varying", False, "nerf", True)  # on validation captures


def median_ev(model: Model) -> float:
    """The median exposure, in stops relative to the mean of all views' white balance: halfway between
    the mean learned exposure of the darker and of the brighter views (trained on {t1, t5}; t3 between)."""
    level = model.tonemapper.linear_log_wb().mean(1) / math.log(2.0)
    dark, bright = level[level < level.mean()], level[level >= level.mean()]
    return float((dark.mean() + bright.mean()) / 2 - level.mean())


def median_camera(views: list[dict], view: int) -> CameraSettings:
    """The true median camera of a view (`views`: camera_truth.json's): 0 EV, all views' geometric-mean
    white balance (what the mean learned white balance estimates; the white balance itself is not what
    is being tested)."""
    gains = np.exp(np.log(np.array([v["wb_gains"] for v in views])).mean(0))
    return CameraSettings(0.0, tuple(float(g) for g in gains), views[view]["crf"])


def true_radiance(root: Path, views: list[dict], view: int) -> np.ndarray:
    """The view's rendered HDR truth (the captures were made from it)."""
    return read_exr(root / "hdr" / f"{Path(views[view]['file']).stem}.exr")


def median_targets(
    root: Path, views: list[dict], ids: list[int]
) -> tuple[list[np.ndarray], list[CameraSettings], list[np.ndarray]]:
    """Per test view: its HDR truth, its true median camera, and that camera's capture (the target)."""
    radiances = [true_radiance(root, views, i) for i in ids]
    cameras = [median_camera(views, i) for i in ids]
    truths = [(capture(r, c) / 255.0).astype(np.float32) for r, c in zip(radiances, cameras)]
    return radiances, cameras, truths


def score_against(preds: list[np.ndarray], truths: list[np.ndarray], lpips: bool) -> dict:
    per_view = [right_half_metrics(p, t, lpips) for p, t in zip(preds, truths)]
    return {k: float(np.mean([v[k] for v in per_view])) for k in METRIC_KEYS if k in per_view[0]}


def exposure_groups(model: Model, data: Path) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The training views captured darker and brighter than the median, by their capture exposure (what
    a camera records with each photo; no pixel of a test view is read)."""
    evs = SynthTruth.load(data).evs
    dark = tuple(i for i in model.train_ids if evs[i] < 0)
    bright = tuple(i for i in model.train_ids if evs[i] > 0)
    return dark, bright


def nerf_a_median(model: Model, data: Path, weight: float, backend: str) -> list[np.ndarray]:
    """NeRF-A's test views with the embedding `(1 - weight) dark + weight bright` (groups' means)."""
    appearance = Appearance(*exposure_groups(model, data), weight)
    return [model.render_camera(i, backend, appearance).clamp(0.0, 1.0).cpu().numpy() for i in model.test_ids]


def validation_data(scene: str, s: ExperimentSettings, out: Path) -> tuple[Path, Path]:
    """The validation truth of `scene` and its -3/+3 EV captures (other cameras, other capture seed)."""
    root = validation_root(scene, s, out)
    return root, captured(root, "dark_bright", "varying", replace(DARK_BRIGHT, seed=VALIDATION_SEED))


def validation_spec(scene: str, s: ExperimentSettings, out: Path) -> RunSpec:
    """The NeRF-A run on `scene`'s validation captures that chooses the interpolation weight."""
    _, data = validation_data(scene, s, out)
    return method_spec(data.parent, out / "runs" / scene, s, VALIDATION_NERF_A)


def validated_weight(scene: str, s: ExperimentSettings, out: Path) -> tuple[float, dict[str, float]]:
    """NeRF-A's interpolation weight for `scene`: a NeRF-A trained on the validation captures renders
    their test views at each of `WEIGHTS`; the weight with the best right-half PSNR against the true
    0 EV captures wins. Returns it and the PSNR per weight. Reads only validation data."""
    root, data = validation_data(scene, s, out)
    model, _ = train_spec(validation_spec(scene, s, out))
    views = json.loads((data / "camera_truth.json").read_text())["views"]
    _, _, truths = median_targets(root, views, model.test_ids)
    psnr = {
        f"{w:g}": score_against(nerf_a_median(model, data, w, s.backend), truths, False)["psnr"]
        for w in WEIGHTS
    }
    best = max(WEIGHTS, key=lambda w: psnr[f"{w:g}"])
    return best, psnr
