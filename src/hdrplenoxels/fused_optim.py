"""svox2's RMSProp fused into one Warp pass over the grid, reading and clearing the gradient buffers.

The same update as `optim.GridRMSProp.step` (its reference, held to it by tests), but one read and
one write of each array instead of a dozen torch passes and temporaries, split over the CPU's
cores by rows, and the gradient parts are summed and zeroed in the same pass.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from hdrplenoxels.render.parallel import cpu_workers, run_parts, split
from hdrplenoxels.warp_runtime import KERNEL, warp_device

ROWS_PER_PART = 1 << 14  # rows of one CPU launch: small enough to balance the threads


@functools.cache
def _rmsprop_kernel(columns: int, parts: int):
    """The update specialised for `columns` values per row and `parts` gradient buffers (unrolled)."""

    @KERNEL
    def rmsprop_rows(
        param: wp.array(dtype=wp.float32),
        state: wp.array(dtype=wp.float32),
        grads: wp.array2d(dtype=wp.float32),
        first_row: int,
        lr: float,
        beta: float,
        eps: float,
        floor: float,
    ):
        base = (wp.tid() + first_row) * columns  # flat arrays: the compiler sees contiguous columns
        for c in range(columns):
            i = base + c
            g = wp.float32(0.0)
            for p in range(parts):
                g += grads[p, i]
                grads[p, i] = 0.0
            v = state[i]
            g2 = g * g
            v = wp.where(v == 0.0, g2, v * beta + g2 * (1.0 - beta))  # svox2: a fresh state starts at g^2
            state[i] = v
            param[i] = wp.max(param[i] - lr * (g / (wp.sqrt(v) + eps)), floor)

    return rmsprop_rows


def fused_rmsprop_(
    param: torch.Tensor,
    state: torch.Tensor,
    grads: torch.Tensor,
    lr: float,
    beta: float,
    eps: float,
    floor: float,
) -> None:
    """Update `param` (M,) or (M, C) and its mean-square `state` in place from the gradient parts
    `grads` (P, M) or (P, M, C), which are left zeroed."""
    n = param.shape[0]
    if n == 0:
        return
    kernel = _rmsprop_kernel(param.numel() // n, grads.shape[0])
    device = warp_device(param)
    inputs = [
        wp.from_torch(param.detach().reshape(-1), requires_grad=False),
        wp.from_torch(state.reshape(-1), requires_grad=False),
        wp.from_torch(grads.reshape(grads.shape[0], -1), requires_grad=False),
    ]
    constants = [float(lr), float(beta), float(eps), float(floor)]

    def launch(start: int, stop: int, _part: int) -> None:
        wp.launch(kernel, dim=stop - start, inputs=inputs + [start] + constants, device=device)

    if device == "cpu":
        workers = cpu_workers()
        run_parts(split(n, max(workers, n // ROWS_PER_PART)), launch, workers)
    else:
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream())):
            launch(0, n, 0)
    # Warp wrote behind torch's back: bump the version counters so caches keyed on them (the
    # renderer's block occupancy) see the change, and autograd refuses stale saved tensors.
    torch.autograd.graph.increment_version([param, state, grads])
