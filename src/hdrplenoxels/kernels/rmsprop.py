"""What every implementation of svox2's RMSProp rule shares (the Warp kernels of
kernels/rmsprop_kernel.py and their PyTorch oracle, kernels/rmsprop_reference.py), kept apart so that
neither imports the other: the one argument structure both take, and the floor of a mean square."""

from __future__ import annotations

from dataclasses import dataclass

import torch

MEAN_SQUARE_FLOOR = 1.1754944e-38
"""The smallest normal float32: where a positive mean square's decay stops, in every implementation of
the rule (dense, owed, the PyTorch oracle), with or without subnormals flushed. It must not reach 0: the
row would read as fresh (`v <- g^2`) and take a first step 4.5x smaller (at beta 0.95) than from the
decayed state; and below it every product is subnormal, many times slower on x86 (JOURNAL.md,
"Why that pass is slow here: frozen subnormal SH")."""


@dataclass(frozen=True)
class RMSPropStep:
    """One array's step of svox2's RMSProp, as `rmsprop_kernel.fused_rmsprop_` and its oracle
    `rmsprop_reference.rmsprop_reference_` both take it: per element `v <- g^2` where `v == 0`, else
    `v <- max(beta v + (1 - beta) g^2, MEAN_SQUARE_FLOOR)`, then `theta <- max(theta - lr g / (sqrt(v) +
    eps), floor)`, in place on `param` and `state`."""

    param: torch.Tensor
    state: torch.Tensor
    """Its running mean squares, `v`."""
    grads: torch.Tensor
    """The gradient in parts (P, *param.shape), summed (the kernel also clears them)."""
    lr: float | torch.Tensor
    """A float, or a one-element float32 tensor on `param`'s device (read where the arithmetic runs, so
    that a step replayed from a CUDA graph uses its own rate)."""
    beta: float
    eps: float
    floor: float
    """No value drops below it."""
    pull: torch.Tensor | None = None
    """(C,) weights over the last axis of a (M, C) param: `pull * param` joins the gradient (an L2 prior's,
    which holds every row, touched by the step's rays or not)."""
