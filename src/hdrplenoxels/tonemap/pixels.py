"""The photo pixels a training batch's rays were drawn from: the one argument structure the tone mapper's
training loss (`ToneMapper.training_loss`), its kernel (`tonemap/loss_kernel.py`) and its oracle
(`tonemap/loss_reference.py`) take besides the radiance."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class PixelTargets:
    """Each ray's photo (`image_ids` (B,)), pixel (`rows`, `cols` (B,), for the vignetting) and that
    pixel's value (`target` (B, 3) in [0, 1])."""

    image_ids: torch.Tensor
    rows: torch.Tensor
    cols: torch.Tensor
    target: torch.Tensor
