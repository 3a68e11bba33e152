"""torch.optim.RMSprop's step (no momentum, not centred) in PyTorch: the oracle of
train/torch_rmsprop_kernel.py, and the update `optim.TorchRMSProp.step` makes on a CPU."""

from __future__ import annotations

import torch

from hdrplenoxels.train.rmsprop_reference import descend_


@torch.no_grad()
def torch_rmsprop_reference_(
    param: torch.Tensor,
    square_avg: torch.Tensor,
    grad: torch.Tensor,
    lr: float | torch.Tensor,
    alpha: float,
    eps: float,
) -> None:
    """One step of `param` and its mean squares in place: `v <- alpha v + (1 - alpha) g^2`, then
    `theta <- theta - lr g / (sqrt(v) + eps)`; `lr` a float or a one-element tensor on `param`'s device.
    The oracle of train/torch_rmsprop_kernel.py."""
    square_avg.mul_(alpha).addcmul_(grad, grad, value=1.0 - alpha)
    descend_(param, grad, square_avg.sqrt().add_(eps), lr)
