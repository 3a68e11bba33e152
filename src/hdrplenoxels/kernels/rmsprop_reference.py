"""svox2's RMSProp step in PyTorch: the readable oracle of kernels/rmsprop_kernel.py (and of its variants
over listed rows, kernels/rmsprop_listed.py), and the update
`optim.Svox2RMSProp.step` makes (docs/method.md, "Training")."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.rmsprop import MEAN_SQUARE_FLOOR, RMSPropStep
from hdrplenoxels.kernels.torch_rmsprop_reference import descend_


@torch.no_grad()
def rmsprop_reference_(s: RMSPropStep) -> None:
    """`s`'s step (`RMSPropStep`), in place on its param and mean squares; the gradient parts are read,
    not cleared. The oracle of kernels/rmsprop_kernel.py and kernels/rmsprop_listed.py."""
    param, state = s.param, s.state
    g = (s.grads[0] if s.grads.shape[0] == 1 else s.grads.sum(0)).to(param.dtype)
    if s.pull is not None:
        g = g + s.pull.to(param.dtype) * param
    g2 = g.square()
    fresh = state == 0
    state.mul_(s.beta).add_(g2, alpha=1.0 - s.beta).clamp_(min=MEAN_SQUARE_FLOOR)
    torch.where(fresh, g2, state, out=state)
    denom = torch.sqrt(state, out=g2).add_(s.eps)  # reuse g2's memory: grids can be GBs
    descend_(param, g, denom, s.lr).clamp_(min=s.floor)
