"""Scoring a trained model on its test views under the stated protocol."""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.eval.metrics import image_metrics, lpips_available
from hdrplenoxels.render import Backend
from hdrplenoxels.train.model import Model

PROTOCOLS = {
    "right-half": "every 8th view is a test view; its left half (columns [0, W//2)) is in the training "
    "pool and only its right half (columns [W//2, W)) is scored",
    "full": "every 8th view is a test view, held out entirely and scored on all pixels",
}
METRIC_KEYS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")


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


def evaluate(model: Model, scene: SceneData, backend: Backend = "warp", lpips: bool = True) -> dict:
    """Metrics per test view and averaged: PSNR, SSIM (11x11 Gaussian, valid), LPIPS (VGG and Alex)."""
    check_same_scene(model, scene)
    holdout = model.config.get("holdout", "right-half")
    nets = ("vgg", "alex") if lpips and lpips_available() else ()
    views = []
    for i in model.test_ids:
        pred = model.to_ldr(model.render_camera(i, backend), i).cpu()
        gt = torch.tensor(scene.images[i], dtype=torch.float32) / 255.0
        scores = image_metrics(scored_region(pred, holdout), scored_region(gt, holdout), lpips_nets=nets)
        views.append({"view": model.names[i], "index": i, **scores})
    summary = {k: float(np.mean([v[k] for v in views])) for k in METRIC_KEYS if views and k in views[0]}
    return {
        "protocol": PROTOCOLS[holdout],
        "holdout": holdout,
        "num_test_views": len(views),
        **summary,
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
    return "\n".join(lines)
