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
CAMERAS = {
    "own": "each test view through its own learned camera",
    "auto": "each test view through the camera the camera controller predicts from its render",
    "mean": "each test view through the mean of the learned cameras (of the views that trained one)",
    "cc": "colour-corrected: the mean camera's picture with a per-image affine colour fit to the photo's "
    "scored pixels (the metric of Zip-NeRF / BilaRF / PPISP tables)",
}


def colour_corrected(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """`pred` (H, W, 3) through the affine colour map (3 x 3 plus offset) that best fits it to `gt` by
    least squares, clipped to [0, 1]."""
    x = torch.cat([pred.reshape(-1, 3), pred.new_ones(pred.shape[0] * pred.shape[1], 1)], 1).double()
    a = torch.linalg.lstsq(x, gt.reshape(-1, 3).double()).solution
    return (x @ a).float().reshape(pred.shape).clamp(0.0, 1.0)


def test_view_picture(model: Model, radiance: torch.Tensor, i: int, camera: str) -> torch.Tensor:
    """Test view `i`'s picture (H, W, 3) in [0, 1] through the camera `camera` names (CAMERAS; "cc"
    returns the mean camera's, corrected by the caller against the photo)."""
    if camera == "own":
        return model.to_ldr(radiance, i)
    if camera == "auto":
        return model.to_ldr_controlled(radiance, camera=model.auto_camera())
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


def evaluate(
    model: Model, scene: SceneData, backend: Backend = "warp", lpips: bool = True, camera: str = "own"
) -> dict:
    """Metrics per test view and averaged: PSNR, SSIM (11x11 Gaussian, valid), LPIPS (VGG and Alex), each
    view seen through `camera` (CAMERAS)."""
    check_same_scene(model, scene)
    if camera not in CAMERAS:
        raise ValueError(f"unknown camera {camera!r}; choose one of {', '.join(CAMERAS)}")
    if camera != "own" and model.tonemapper is None:
        raise ValueError(f"camera {camera!r} needs a model trained with tone mapping")
    holdout = model.config.get("holdout", "right-half")
    nets = ("vgg", "alex") if lpips and lpips_available() else ()
    views = []
    for i in model.test_ids:
        pred = test_view_picture(model, model.render_camera(i, backend), i, camera).cpu()
        gt = torch.tensor(scene.images[i], dtype=torch.float32) / 255.0
        pred, gt = scored_region(pred, holdout), scored_region(gt, holdout)
        if camera == "cc":
            pred = colour_corrected(pred, gt)
        views.append({"view": model.names[i], "index": i, **image_metrics(pred, gt, lpips_nets=nets)})
    summary = {k: float(np.mean([v[k] for v in views])) for k in METRIC_KEYS if views and k in views[0]}
    return {
        "protocol": PROTOCOLS[holdout],
        "holdout": holdout,
        "camera": camera,
        "camera_protocol": CAMERAS[camera],
        "num_test_views": len(views),
        **summary,
        "views": views,
    }


@torch.no_grad()
def camera_psnrs(model: Model, scene: SceneData, backend: Backend = "warp") -> dict[str, float]:
    """Mean PSNR of the test views' scored pixels through each camera of CAMERAS that the model has (its
    own learned one; with a controller the predicted one, the mean one and colour-corrected), each view
    rendered once: the protocol's score beside what a view no photo was taken from would get."""
    check_same_scene(model, scene)
    if model.tonemapper is None:
        return {}
    cameras = ["own", "mean", "cc"] + (["auto"] if model.controller is not None else [])
    holdout = model.config.get("holdout", "right-half")
    psnrs: dict[str, list[float]] = {camera: [] for camera in cameras}
    for i in model.test_ids:
        radiance = model.render_camera(i, backend)
        gt = scored_region(torch.tensor(scene.images[i], dtype=torch.float32) / 255.0, holdout)
        for camera in cameras:
            pred = scored_region(test_view_picture(model, radiance, i, camera).cpu(), holdout)
            if camera == "cc":
                pred = colour_corrected(pred, gt)
            psnrs[camera].append(image_metrics(pred, gt, lpips_nets=())["psnr"])
    return {camera: float(np.mean(values)) for camera, values in psnrs.items() if values}


def format_table(result: dict) -> str:
    keys = [k for k in METRIC_KEYS if k in result]
    head = f"{'view':<28}" + "".join(f"{k:>12}" for k in keys)
    lines = [head, "-" * len(head)]
    for v in result["views"]:
        lines.append(f"{v['view'][-28:]:<28}" + "".join(f"{v[k]:>12.4f}" for k in keys))
    lines.append("-" * len(head))
    lines.append(f"{'mean':<28}" + "".join(f"{result[k]:>12.4f}" for k in keys))
    lines.append(f"protocol: {result['protocol']}")
    if result.get("camera", "own") != "own":
        lines.append(f"camera: {result['camera_protocol']}")
    return "\n".join(lines)
