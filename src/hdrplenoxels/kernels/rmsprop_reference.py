"""svox2's RMSProp step in PyTorch: the readable oracle of kernels/rmsprop_kernel.py, and the update
`optim.Svox2RMSProp.step` makes (docs/method.md, "Training")."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.rmsprop_rule import MEAN_SQUARE_FLOOR
from hdrplenoxels.kernels.torch_rmsprop_reference import descend_


@torch.no_grad()
def rmsprop_reference_(
    param: torch.Tensor,
    state: torch.Tensor,
    grad: torch.Tensor,
    lr: float | torch.Tensor,
    beta: float,
    eps: float,
    floor: float,
    pull: torch.Tensor | None = None,
) -> None:
    """One step of `param` and its mean squares `state` in place, from `grad` (same shape): per element
    `v <- g^2` where `v == 0`, else `v <- max(beta v + (1 - beta) g^2, MEAN_SQUARE_FLOOR)`, then
    `theta <- max(theta - lr g / (sqrt(v) + eps), floor)`. `pull` (C,), weights over the last axis, adds
    `pull * param` to the gradient (an L2 prior's). `lr` is a float or a one-element tensor on `param`'s
    device. The oracle of kernels/rmsprop_kernel.py."""
    g = grad.to(param.dtype)
    if pull is not None:
        g = g + pull.to(param.dtype) * param
    g2 = g.square()
    fresh = state == 0
    state.mul_(beta).add_(g2, alpha=1.0 - beta).clamp_(min=MEAN_SQUARE_FLOOR)
    torch.where(fresh, g2, state, out=state)
    denom = torch.sqrt(state, out=g2).add_(eps)  # reuse g2's memory: grids can be GBs
    descend_(param, g, denom, lr).clamp_(min=floor)
