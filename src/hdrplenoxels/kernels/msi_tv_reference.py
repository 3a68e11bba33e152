"""The MSI's dense TV gradient in closed form in PyTorch (`background_tv.msi_tv_grad_` over every
texel): the oracle of kernels/msi_tv_kernel.py, itself held to autograd through `background_tv.msi_tv` in
tests/test_background.py."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.tv import TV_EPS


def msi_tv_grad_reference_(values: torch.Tensor, grad: torch.Tensor, weight: float) -> None:
    """Add `weight` times the gradient of the MSI's TV over every texel into `grad` in place (both (L, H,
    W, C)): with u = 1 / sqrt(sum_a D_a^2 + eps) per texel and channel, the neighbour along a gets
    + (weight / n) u D_a and the texel itself - (weight / n) u sum_a D_a (the oracle of
    kernels/msi_tv_kernel.py)."""
    d_layer = torch.zeros_like(values)
    torch.sub(values[1:], values[:-1], out=d_layer[:-1])
    d_row = torch.zeros_like(values)
    torch.sub(values[:, 1:], values[:, :-1], out=d_row[:, :-1])
    d_col = torch.roll(values, shifts=-1, dims=2).sub_(values)
    u = (d_layer * d_layer).add_(d_row * d_row).addcmul_(d_col, d_col).add_(TV_EPS).rsqrt_()
    u.mul_(weight / values[..., 0].numel())
    for d in (d_layer, d_row, d_col):
        grad.sub_(d.mul_(u))
    grad[1:].add_(d_layer[:-1])
    grad[:, 1:].add_(d_row[:, :-1])
    grad.add_(torch.roll(d_col, shifts=1, dims=2))
