"""svox2's RMSProp fused into one Warp pass over the grid, reading and clearing the gradient buffers.

The same update as `optim.GridRMSProp.step` (its reference, held to it by tests), but one read and
one write of each array instead of a dozen torch passes and temporaries, split over the CPU's
cores by rows, and the gradient parts are summed and zeroed in the same pass.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from hdrplenoxels.render.occupancy import BlockOccupancy, mark_voxel
from hdrplenoxels.render.parallel import cpu_workers, split
from hdrplenoxels.warp_runtime import KERNEL, launch_parts, warp_device


@wp.func
def rmsprop_element(
    grads: wp.array2d(dtype=wp.float32),
    parts: int,
    i: int,
    param: wp.array(dtype=wp.float32),
    state: wp.array(dtype=wp.float32),
    lr: float,
    beta: float,
    eps: float,
    floor: float,
) -> float:
    """Sum and clear element i's gradient parts, update its state and value; returns the new value."""
    g = wp.float32(0.0)
    for p in range(parts):
        g += grads[p, i]
        grads[p, i] = 0.0
    v = state[i]
    g2 = g * g
    v = wp.where(v == 0.0, g2, v * beta + g2 * (1.0 - beta))  # svox2: a fresh state starts at g^2
    state[i] = v
    value = wp.max(param[i] - lr * (g / (wp.sqrt(v) + eps)), floor)
    param[i] = value
    return value


@functools.cache
def _rmsprop_kernel(columns: int, parts: int):
    """The update specialised for `columns` values per row and `parts` gradient buffers (unrolled).

    Rows are loaded and stored as whole vectors, so the arithmetic runs on local values the compiler
    can vectorise (element-wise array access would have to assume the arrays alias)."""
    row_t = wp.types.vector(length=columns, dtype=wp.float32)

    @KERNEL
    def rmsprop_rows(
        param: wp.array(dtype=row_t),
        state: wp.array(dtype=row_t),
        grads: wp.array2d(dtype=row_t),
        first_row: int,
        lr: float,
        beta: float,
        eps: float,
        floor: float,
    ):
        row = wp.tid() + first_row
        g = grads[0, row]
        grads[0, row] = row_t()
        for p in range(1, parts):
            g = g + grads[p, row]
            grads[p, row] = row_t()
        v = state[row]
        x = param[row]
        for c in range(columns):
            g2 = g[c] * g[c]
            v[c] = wp.where(v[c] == 0.0, g2, v[c] * beta + g2 * (1.0 - beta))  # svox2: fresh state is g^2
            x[c] = wp.max(x[c] - lr * (g[c] / (wp.sqrt(v[c]) + eps)), floor)
        state[row] = v
        param[row] = x

    return rmsprop_rows


@functools.cache
def _flat_kernel(parts: int):
    """The update one element per thread: on CUDA neighbouring threads then touch neighbouring
    floats (whole-row threads would stride by a row and waste most of every memory transaction)."""

    @KERNEL
    def rmsprop_flat(
        param: wp.array(dtype=wp.float32),
        state: wp.array(dtype=wp.float32),
        grads: wp.array2d(dtype=wp.float32),
        first: int,
        lr: float,
        beta: float,
        eps: float,
        floor: float,
    ):
        rmsprop_element(grads, parts, wp.tid() + first, param, state, lr, beta, eps, floor)

    return rmsprop_flat


@functools.cache
def _density_kernel(parts: int):
    """The update of the density, which also rebuilds the renderer's occupancy in the same pass."""

    @KERNEL
    def rmsprop_density(
        param: wp.array(dtype=wp.float32),
        state: wp.array(dtype=wp.float32),
        grads: wp.array2d(dtype=wp.float32),
        first_row: int,
        lr: float,
        beta: float,
        eps: float,
        floor: float,
        coords: wp.array(dtype=wp.vec3i),
        shift: int,
        cells: wp.array3d(dtype=wp.uint8),
        blocks: wp.array3d(dtype=wp.uint8),
    ):
        row = wp.tid() + first_row
        if rmsprop_element(grads, parts, row, param, state, lr, beta, eps, floor) > 0.0:
            mark_voxel(coords[row], shift, cells, blocks)

    return rmsprop_density


def fused_rmsprop_(
    param: torch.Tensor,
    state: torch.Tensor,
    grads: torch.Tensor,
    lr: float,
    beta: float,
    eps: float,
    floor: float,
    occupancy: BlockOccupancy | None = None,
    per_element: bool | None = None,
) -> None:
    """Update `param` (M,) or (M, C) and its mean-square `state` in place from the gradient parts
    `grads` (P, M) or (P, M, C), which are left zeroed. With `occupancy` (`param` is its grid's
    density), the occupancy is rebuilt for the new density in the same pass. `per_element`: a thread
    per element (default on CUDA) or per row (default on the CPU, where whole rows vectorise)."""
    n = param.shape[0]
    if n == 0:
        return
    marking = [] if occupancy is None else occupancy.marking_inputs()
    device = warp_device(param)
    flat = bool(marking) or (device != "cpu" if per_element is None else per_element)
    if marking:
        kernel = _density_kernel(grads.shape[0])
    elif flat:
        kernel = _flat_kernel(grads.shape[0])
        n = param.numel()
    else:
        kernel = _rmsprop_kernel(param.numel() // n, grads.shape[0])
    if flat:
        inputs = [
            wp.from_torch(param.detach().reshape(-1), requires_grad=False),
            wp.from_torch(state.reshape(-1), requires_grad=False),
            wp.from_torch(grads.reshape(grads.shape[0], -1), requires_grad=False),
        ]
    else:
        row_t = wp.types.vector(length=param.numel() // n, dtype=wp.float32)
        inputs = [
            wp.from_torch(param.detach().reshape(n, -1), dtype=row_t, requires_grad=False),
            wp.from_torch(state.reshape(n, -1), dtype=row_t, requires_grad=False),
            wp.from_torch(grads.reshape(grads.shape[0], n, -1), dtype=row_t, requires_grad=False),
        ]
    constants = [float(lr), float(beta), float(eps), float(floor)]

    def launch(start: int, stop: int, _part: int) -> None:
        wp.launch(kernel, dim=stop - start, inputs=inputs + [start] + constants + marking, device=device)

    launch_parts(device, n, split(n, cpu_workers()), launch)  # every row costs the same: a part per thread
    # Warp wrote behind torch's back: bump the version counters so caches keyed on them (the
    # renderer's block occupancy) see the change, and autograd refuses stale saved tensors.
    torch.autograd.graph.increment_version([param, state, grads])
    if occupancy is not None:
        occupancy.rebuilt_for(param)
