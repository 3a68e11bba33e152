"""The tone mapper's training loss in plain PyTorch: the oracle of `tonemap/loss_kernel.py`, which
computes the same loss and its gradients in two passes (autograd gives this one's)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from hdrplenoxels.tonemap.pixels import PixelTargets

if TYPE_CHECKING:
    from hdrplenoxels.tonemap.module import ToneMapper


def training_loss_reference(
    tonemapper: ToneMapper, radiance: torch.Tensor, pixels: PixelTargets
) -> tuple[torch.Tensor, torch.Tensor]:
    """`loss_kernel.fused_training_loss`'s loss and plain MSE through the module's own forward and
    `ToneMapper.loss` (the oracle of `tonemap/loss_kernel.py`, and what `ToneMapper.training_loss` runs on
    a CPU)."""
    pred = tonemapper(radiance, pixels.image_ids, pixels.rows, pixels.cols, training=True)
    return tonemapper.loss(pred, pixels.target), torch.mean((pred.detach() - pixels.target) ** 2)
