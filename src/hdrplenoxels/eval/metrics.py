"""Image-quality metrics used to report novel-view results: PSNR, SSIM and LPIPS (VGG and AlexNet).

Conventions follow the NeRF/Plenoxels papers so that numbers are comparable with published tables:
images are (H, W, 3) float tensors in [0, 1]; SSIM is the scikit-image / NeRF one (11x11 Gaussian window,
sigma 1.5, K1 0.01, K2 0.03, data range 1, statistics over the *valid* region only, mean over channels);
LPIPS is v0.1 with inputs mapped to [-1, 1] (the ``lpips`` package's ``normalize=True``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from typing import Any

import pytorch_msssim
import torch

from .lpips import LPIPS, NETS, Net, weights_available, weights_path

# PSNR of identical images is infinite; a finite cap keeps per-scene averages meaningful. Any value above
# it (MSE < 1e-10, far below 8-bit or float16 quantisation) is reported as the cap.
PSNR_CAP = 100.0

SSIM_WIN_SIZE = 11
SSIM_SIGMA = 1.5
SSIM_K = (0.01, 0.03)


def _as_pair(pred: Any, gt: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as tensors, checked to be matching (H, W, 3) so errors name the real problem."""
    pred_t, gt_t = torch.as_tensor(pred), torch.as_tensor(gt)
    if pred_t.shape != gt_t.shape:
        raise ValueError(f"image shapes differ: pred {tuple(pred_t.shape)} vs gt {tuple(gt_t.shape)}")
    if pred_t.ndim != 3 or pred_t.shape[-1] != 3:
        raise ValueError(f"images must be (H, W, 3), got {tuple(pred_t.shape)}")
    if not (pred_t.is_floating_point() and gt_t.is_floating_point()):
        raise ValueError(f"images must be float tensors in [0, 1], got {pred_t.dtype} and {gt_t.dtype}")
    return pred_t, gt_t.to(pred_t.device)


def _nchw(img: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return img.to(dtype).permute(2, 0, 1).unsqueeze(0)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB for data range 1: ``-10 log10(MSE)``, capped at PSNR_CAP.

    The MSE is taken over all pixels and channels in float64 (float32 sums lose digits on large images).
    """
    pred, gt = _as_pair(pred, gt)
    mse = torch.mean((pred.double() - gt.double()) ** 2).item()
    if mse <= 0.0:
        return PSNR_CAP
    return min(-10.0 * math.log10(mse), PSNR_CAP)


def ssim(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Structural similarity, scikit-image/NeRF convention (see module docstring), via pytorch_msssim.

    Computed in float64: SSIM subtracts nearly equal local moments (E[x^2] - E[x]^2), which float32
    resolves only to about 1e-4 on smooth regions.
    """
    pred, gt = _as_pair(pred, gt)
    h, w = pred.shape[:2]
    if min(h, w) < SSIM_WIN_SIZE:
        # pytorch_msssim would silently skip the blur along that axis and return a different metric.
        raise ValueError(f"SSIM needs images at least {SSIM_WIN_SIZE} px on a side, got {h}x{w}")
    value = pytorch_msssim.ssim(
        _nchw(pred, torch.float64),
        _nchw(gt, torch.float64),
        data_range=1.0,  # the package default is 255
        size_average=True,
        win_size=SSIM_WIN_SIZE,
        win_sigma=SSIM_SIGMA,
        K=SSIM_K,
    )
    return float(value.item())


def lpips_available(net: Net | None = None) -> bool:
    """True if LPIPS weights for ``net`` (None: both nets) are installed. Loads nothing."""
    return weights_available(net)


@functools.cache
def _lpips_model(net: Net, device: str) -> LPIPS:
    """One pretrained model per (net, device): loading VGG16 takes a noticeable fraction of a second."""
    return LPIPS.pretrained(net).to(device)


def lpips(pred: torch.Tensor, gt: torch.Tensor, net: Net = "vgg") -> float:
    """LPIPS v0.1 distance (lower is more similar) with the ``net`` backbone, on pred's device.

    Raises LPIPSWeightsError, whose message says how to install them, if the weights are missing.
    """
    if net not in NETS:
        raise ValueError(f"unknown LPIPS net {net!r}; expected one of {NETS}")
    pred, gt = _as_pair(pred, gt)
    weights_path(net)  # fail with the install hint before building anything
    model = _lpips_model(net, str(pred.device))
    with torch.no_grad():
        value = model(_nchw(pred, torch.float32) * 2 - 1, _nchw(gt, torch.float32) * 2 - 1)
    return float(value.item())


def image_metrics(
    pred: torch.Tensor, gt: torch.Tensor, lpips_nets: Iterable[Net] = ("vgg", "alex")
) -> dict[str, float]:
    """All metrics for one image pair: ``psnr``, ``ssim`` and ``lpips_<net>`` for each of ``lpips_nets``."""
    out = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    for net in lpips_nets:
        out[f"lpips_{net}"] = lpips(pred, gt, net)
    return out
