"""torch.optim.RMSprop's step (no momentum, not centred) in PyTorch: the oracle of
kernels/torch_rmsprop_kernel.py, and the update `optim.TorchRMSProp.step` makes on a CPU."""

from __future__ import annotations

import torch


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
    The oracle of kernels/torch_rmsprop_kernel.py."""
    square_avg.mul_(alpha).addcmul_(grad, grad, value=1.0 - alpha)
    descend_(param, grad, square_avg.sqrt().add_(eps), lr)


def descend_(
    param: torch.Tensor, grad: torch.Tensor, denom: torch.Tensor, lr: float | torch.Tensor
) -> torch.Tensor:
    """`param <- param - lr * grad / denom` in place, `lr` a float or a one-element tensor on `param`'s
    device: a tensor is read where the arithmetic runs, so a step replayed from a CUDA graph uses its own
    rate (`train/step_graph.py`). On the CPU both round alike: torch's `addcdiv` computes
    (value * grad) / denom there (on CUDA it divides first, so the two part in the last bits)."""
    if isinstance(lr, torch.Tensor):
        return param.addcdiv_(grad * lr.neg(), denom)
    return param.addcdiv_(grad, denom, value=-float(lr))
