"""torch.optim.RMSprop's step (no momentum, not centred) in PyTorch: the oracle of
kernels/torch_rmsprop_kernel.py, and the update `optim.TorchRMSProp.step` makes on a CPU."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.torch_rmsprop import TorchRMSPropStep


@torch.no_grad()
def torch_rmsprop_reference_(step: TorchRMSPropStep) -> None:
    """`step` (`TorchRMSPropStep`) in place on its parameter and mean squares. The oracle of
    kernels/torch_rmsprop_kernel.py."""
    s = step
    s.square_avg.mul_(s.alpha).addcmul_(s.grad, s.grad, value=1.0 - s.alpha)
    descend_(s.param, s.grad, s.square_avg.sqrt().add_(s.eps), s.lr)


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
