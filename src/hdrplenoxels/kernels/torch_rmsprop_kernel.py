"""torch.optim.RMSprop's step for the tone parameters in one Warp pass per tensor.

Through PyTorch a step of each tensor is seven small operators (the mean square's decay and add, its
root, the epsilon, the rate's product, the division and the add), each a kernel of a replayed step on a
GPU (JOURNAL.md, "Fused kernels"); here one thread per element does them, reading the rate
from its one-element device array. `optim.TorchRMSProp` takes it on CUDA (`kernels.dispatch.use_kernel`).

Oracle: `hdrplenoxels.kernels.torch_rmsprop_reference.torch_rmsprop_reference_`; parity: tests/test_optim.py.
"""

from __future__ import annotations

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, to_warp, warp_device, warp_struct
from hdrplenoxels.kernels.torch_rmsprop import TorchRMSPropStep


@wp.struct
class _Step:
    """`TorchRMSPropStep` as the kernel reads it: flat float32 arrays, the rate a one-element array."""

    param: wp.array(dtype=wp.float32)
    square_avg: wp.array(dtype=wp.float32)
    """The mean square, torch's state of that name."""
    grad: wp.array(dtype=wp.float32)
    lr: wp.array(dtype=wp.float32)
    """One element: the schedule writes it on the device, so a replayed step reads the new rate."""
    alpha: float
    """The mean square's decay."""
    eps: float


@KERNEL
def _torch_rmsprop(s: _Step):
    i = wp.tid()
    g = s.grad[i]
    v = s.square_avg[i] * s.alpha + (1.0 - s.alpha) * (g * g)
    s.square_avg[i] = v
    s.param[i] = s.param[i] + (g * -s.lr[0]) / (wp.sqrt(v) + s.eps)


def torch_rmsprop_(step: TorchRMSPropStep) -> None:
    """Exactly `torch_rmsprop_reference.torch_rmsprop_reference_`'s contract, for contiguous float32
    tensors of one shape. Inside a CUDA graph pass the rate as a tensor: a float becomes a tensor made
    at recording, whose value every replay would reuse."""
    param, square_avg, grad, lr = step.param, step.square_avg, step.grad, step.lr
    for name, t in (("param", param), ("square_avg", square_avg), ("grad", grad)):
        if t.dtype != torch.float32 or not t.is_contiguous() or t.shape != param.shape:
            raise ValueError(
                f"torch_rmsprop_: {name} must be contiguous float32 of shape {tuple(param.shape)}"
            )
    if not isinstance(lr, torch.Tensor):
        lr = torch.full((1,), float(lr), device=param.device)
    arrays = warp_struct(
        _Step,
        param=to_warp(param.detach().reshape(-1), "a tone parameter"),
        square_avg=to_warp(square_avg.reshape(-1), "its mean squares"),
        grad=to_warp(grad.reshape(-1), "its gradient"),
        lr=to_warp(lr.reshape(1).to(torch.float32), "the learning rate"),
        alpha=float(step.alpha),
        eps=float(step.eps),
    )
    launch_kernel(_torch_rmsprop, dim=param.numel(), inputs=[arrays], device=warp_device(param))
