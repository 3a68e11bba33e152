"""Scoring a trained model on its test views under the stated protocol."""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.eval.metrics import image_metrics, lpips_available, psnr
from hdrplenoxels.render import Backend
from hdrplenoxels.train.model import Model

PROTOCOLS = {
    "right-half": "every 8th view is a test view; its left half (columns [0, W//2)) is in the training "
    "pool and only its right half (columns [W//2, W)) is scored",
    "full": "every 8th view is a test view, held out entirely and scored on all pixels",
}
METRIC_KEYS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")
TONES = {
    "own": "each test view through its own learned tone",
    "auto": "each test view through the tone the tone controller predicts from its render",
    "mean": "each test view through the mean of the learned tones (of the views that trained one)",
    "cc": "colour-corrected: the mean tone's picture with a per-image affine colour fit to the photo's "
    "scored pixels (the metric of Zip-NeRF / BilaRF / PPISP tables)",
}


def colour_corrected(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """`pred` (H, W, 3) through the affine colour map (3 x 3 plus offset) that best fits it to `gt` by
    least squares, clipped to [0, 1]."""
    x = torch.cat([pred.reshape(-1, 3), pred.new_ones(pred.shape[0] * pred.shape[1], 1)], 1).double()
    a = torch.linalg.lstsq(x, gt.reshape(-1, 3).double()).solution
    return (x @ a).float().reshape(pred.shape).clamp(0.0, 1.0)


def test_view_picture(model: Model, radiance: torch.Tensor, i: int, tone: str) -> torch.Tensor:
    """Test view `i`'s picture (H, W, 3) in [0, 1] through the tone `tone` names (TONES; "cc" returns
    the mean tone's, corrected by the caller against the photo)."""
    if tone == "own":
        return model.to_ldr(radiance, i)
    if tone == "auto":
        return model.to_ldr_controlled(radiance, tone=model.auto_tone())
    return model.to_ldr_controlled(radiance)


def scored_region(img: torch.Tensor, holdout: str) -> torch.Tensor:
    return img[:, left_width(img.shape[1]) :] if holdout == "right-half" else img


def run_downscale(model: Model) -> int:
    """The factor the model's images were reduced by in training (1 for runs from before the option):
    its test views are scored against images reduced the same way."""
    return int(model.config.get("data", {}).get("downscale", 1))


def check_same_scene(model: Model, scene: SceneData) -> None:
    if list(scene.names) != list(model.names):
        raise InputError(
            scene.source,
            f"these images do not match the trained model ({len(scene.names)} views here, "
            f"{len(model.names)} in the model, or different file names)",
        )


def scored_picture(
    model: Model, radiance: torch.Tensor, gt: torch.Tensor, i: int, tone: str, holdout: str
) -> torch.Tensor:
    """Test view `i`'s scored pixels through `tone` (TONES), "cc" fitted to the photo's (`gt`, already
    cut to the scored region)."""
    pred = scored_region(test_view_picture(model, radiance, i, tone).cpu(), holdout)
    return colour_corrected(pred, gt) if tone == "cc" else pred


def novel_view_tones(model: Model) -> tuple[str, ...]:
    """The tones a view no photo was taken from can be seen through: the mean one and colour-corrected
    with learned tones, and the predicted one with a tone controller besides."""
    if model.tonemapper is None:
        return ()
    return ("mean", "cc") + (("auto",) if model.controller is not None else ())


@torch.no_grad()
def evaluate(
    model: Model,
    scene: SceneData,
    backend: Backend = "warp",
    lpips: bool = True,
    tone: str = "own",
    also: tuple[str, ...] = (),
) -> dict:
    """Metrics per test view and averaged: PSNR, SSIM (11x11 Gaussian, valid), LPIPS (VGG and Alex), each
    view seen through `tone` (TONES); with `also`, the mean PSNR through each of those tones too, from
    the same renders (`tones` in the result)."""
    check_same_scene(model, scene)
    for c in (tone, *also):
        if c not in TONES:
            raise ValueError(f"unknown tone {c!r}; choose one of {', '.join(TONES)}")
        if c != "own" and model.tonemapper is None:
            raise ValueError(f"tone {c!r} needs a model trained with tone mapping")
    holdout = model.config.get("holdout", "right-half")
    nets = ("vgg", "alex") if lpips and lpips_available() else ()
    views, others = [], {c: [] for c in also}
    for i in model.test_ids:
        radiance = model.render_camera(i, backend)
        gt = scored_region(torch.tensor(scene.images[i], dtype=torch.float32) / 255.0, holdout)
        pred = scored_picture(model, radiance, gt, i, tone, holdout)
        views.append({"view": model.names[i], "index": i, **image_metrics(pred, gt, lpips_nets=nets)})
        for c in also:
            others[c].append(psnr(scored_picture(model, radiance, gt, i, c, holdout), gt))
    summary = {k: float(np.mean([v[k] for v in views])) for k in METRIC_KEYS if views and k in views[0]}
    extra = {"tones": {c: float(np.mean(v)) for c, v in others.items() if v}} if also else {}
    return {
        "protocol": PROTOCOLS[holdout],
        "holdout": holdout,
        "tone": tone,
        "tone_protocol": TONES[tone],
        "num_test_views": len(views),
        **summary,
        **extra,
        "views": views,
    }


def format_table(result: dict) -> str:
    keys = [k for k in METRIC_KEYS if k in result]
    head = f"{'view':<28}" + "".join(f"{k:>12}" for k in keys)
    lines = [head, "-" * len(head)]
    for v in result["views"]:
        lines.append(f"{v['view'][-28:]:<28}" + "".join(f"{v[k]:>12.4f}" for k in keys))
    lines.append("-" * len(head))
    lines.append(f"{'mean':<28}" + "".join(f"{result[k]:>12.4f}" for k in keys))
    lines.append(f"protocol: {result['protocol']}")
    if result.get("tone", "own") != "own":
        lines.append(f"tone: {result['tone_protocol']}")
    return "\n".join(lines)
