"""The MSI's dense TV gradient in one Warp pass, a thread per texel.

In PyTorch the closed form is 23 operators over dense temporaries of the MSI's size for each of the
density and the colour, each a kernel of a replayed step on a GPU (JOURNAL.md, "Fused
kernels"). Here each texel gathers what it receives: its own term's share and its three backward
neighbours' (whose terms it recomputes), so no two threads write one texel and no atomics are needed.
`background_tv.msi_tv_grad_` takes it on CUDA (`kernels.dispatch.use_kernel`).

Oracle: `hdrplenoxels.kernels.msi_tv_reference.msi_tv_grad_reference_`; parity: tests/test_background.py.
"""

from __future__ import annotations

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, to_warp, warp_device
from hdrplenoxels.kernels.tv import TV_EPS

TV_EPS_W = wp.constant(TV_EPS)


@wp.func
def forward_differences(values: wp.array4d(dtype=wp.float32), layer: int, row: int, col: int, c: int):
    """(D_layer, D_row, D_col) of a texel's channel c, 0 past the last layer and row, the column
    wrapping."""
    v = values[layer, row, col, c]
    d_layer = wp.float32(0.0)
    if layer + 1 < values.shape[0]:
        d_layer = values[layer + 1, row, col, c] - v
    d_row = wp.float32(0.0)
    if row + 1 < values.shape[1]:
        d_row = values[layer, row + 1, col, c] - v
    d_col = values[layer, row, (col + 1) % values.shape[2], c] - v
    return wp.vec3(d_layer, d_row, d_col)


@wp.func
def weight_of(d: wp.vec3, scale: float) -> float:
    """(weight / n) / sqrt(sum_a D_a^2 + eps), in the oracle's order of operations."""
    return scale / wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + TV_EPS_W)


@KERNEL
def _msi_tv_grad(values: wp.array4d(dtype=wp.float32), scale: float, grad: wp.array4d(dtype=wp.float32)):
    layer, row, col = wp.tid()
    width = values.shape[2]
    for c in range(values.shape[3]):
        d = forward_differences(values, layer, row, col, c)
        u = weight_of(d, scale)
        g = grad[layer, row, col, c] - d[0] * u - d[1] * u - d[2] * u
        if layer > 0:
            back = forward_differences(values, layer - 1, row, col, c)
            g += back[0] * weight_of(back, scale)
        if row > 0:
            back = forward_differences(values, layer, row - 1, col, c)
            g += back[1] * weight_of(back, scale)
        back = forward_differences(values, layer, row, (col + width - 1) % width, c)
        g += back[2] * weight_of(back, scale)
        grad[layer, row, col, c] = g


@torch.no_grad()
def msi_tv_grad_dense_(values: torch.Tensor, grad: torch.Tensor, weight: float) -> None:
    """Exactly `msi_tv_reference.msi_tv_grad_reference_`'s contract, for float32 (L, H, W, C) tensors,
    `grad` contiguous."""
    if values.shape != grad.shape or values.dim() != 4 or not grad.is_contiguous():
        raise ValueError(f"MSI TV: values {tuple(values.shape)} and a contiguous grad of the same 4-D shape")
    device = warp_device(values)
    inputs = [
        to_warp(values.detach().contiguous(), "the MSI's values"),
        float(weight) / values[..., 0].numel(),
        to_warp(grad, "the MSI's gradient"),
    ]
    launch_kernel(_msi_tv_grad, dim=tuple(values.shape[:3]), inputs=inputs, device=device)
