"""What the tone parameters' RMSProp kernel (`kernels/torch_rmsprop_kernel.py`) and its oracle
(`kernels/torch_rmsprop_reference.py`) share: the one argument structure both take."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TorchRMSPropStep:
    """One tensor's step of torch.optim.RMSprop (no momentum, not centred): `v <- alpha v + (1 - alpha)
    g^2`, then `theta <- theta - lr g / (sqrt(v) + eps)`, in place on `param` and `square_avg`."""

    param: torch.Tensor
    square_avg: torch.Tensor
    """Its running mean of squared gradients, `v`."""
    grad: torch.Tensor
    lr: float | torch.Tensor
    """A float, or a one-element tensor on `param`'s device (read where the arithmetic runs, so that a
    step replayed from a CUDA graph uses its own rate)."""
    alpha: float
    eps: float
