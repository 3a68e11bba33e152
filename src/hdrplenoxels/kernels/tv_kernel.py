"""The TV gradient of `tv_reference.tv_grad_reference_` as one Warp kernel, `tv_grad_`.

The reference gathers and scatters through a dozen small torch ops per call, which cost more than the
arithmetic on a 1 % run of cells; here each thread handles one cell and adds its terms in place.

Oracle: `hdrplenoxels.kernels.tv_reference.tv_grad_reference_`; parity: tests/test_tv.py.
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, run_parts, split
from hdrplenoxels.core.warp_runtime import (
    KERNEL,
    launch_kernel,
    mark_touched,
    to_warp,
    warp_device,
)
from hdrplenoxels.kernels.grad_buffers import check_row_array
from hdrplenoxels.kernels.tv import TV_EPS, TVTerm, check_cells, check_grad_args, rho_values

TV_EPS_W = wp.constant(TV_EPS)
# Runs of fewer cells than this per thread stay on one thread: a small run gains little from threads,
# and the small grids (`fast`, the demo, the tests) then add their TV in the same order as ever.
MIN_TV_CELLS_PER_THREAD = 1 << 15
# The layout `tv_grad_` takes on CUDA by default: a thread per cell until a GPU's timing of the
# per-(cell, channel) variant says otherwise (JOURNAL.md, "Kernel variants").
CUDA_TV_PER_CHANNEL = False


@wp.func
def cell_rows(links: wp.array3d(dtype=wp.int32), rx: int, cell: wp.int64) -> wp.vec4i:
    """The rows of a cell's +x, +y and +z neighbours and its own (-1 past the level's edge or where no
    voxel is allocated); all -1 for a cell outside the grid (refused up front on the CPU; reading the
    range on a GPU would wait)."""
    ry = links.shape[1]
    rz = links.shape[2]
    if cell < wp.int64(0) or cell >= wp.int64(links.shape[0]) * wp.int64(ry * rz):
        return wp.vec4i(-1, -1, -1, -1)
    x = int(cell // wp.int64(ry * rz))
    y = int((cell // wp.int64(rz)) % wp.int64(ry))
    z = int(cell % wp.int64(rz))
    rows = wp.vec4i(-1, -1, -1, links[x, y, z])
    if x % rx + 1 < rx:
        rows[0] = links[x + 1, y, z]
    if y + 1 < ry:
        rows[1] = links[x, y + 1, z]
    if z + 1 < rz:
        rows[2] = links[x, y, z + 1]
    return rows


@wp.func
def mark_rows(touched: wp.array(dtype=wp.uint8), rows: wp.vec4i):
    for k in range(4):
        if rows[k] >= 0:
            mark_touched(touched, rows[k])


@wp.func
def add_channel_terms(
    values: wp.array2d(dtype=wp.float32),
    c: int,
    rows: wp.vec4i,
    rho: wp.vec3,
    scale: float,
    missing_self: int,
    grad: wp.array2d(dtype=wp.float32),
):
    """A cell's TV terms of channel `c`, added into `grad` (`rows`: `cell_rows`)."""
    centre = rows[3]
    v0 = wp.float32(0.0)
    if centre >= 0:
        v0 = values[centre, c]
    d = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        row = rows[a]
        if row >= 0:
            d[a] = values[row, c] - v0
        elif missing_self == 0:
            d[a] = -v0  # "zero": a missing neighbour reads 0
    u = scale / wp.sqrt(wp.dot(d, d) + TV_EPS_W)
    total = wp.float32(0.0)
    for a in range(3):
        to_neighbour = rho[a] * d[a] * u
        total += to_neighbour
        if rows[a] >= 0:
            wp.atomic_add(grad, rows[a], c, to_neighbour)
    if centre >= 0:
        wp.atomic_add(grad, centre, c, -total)


@functools.cache
def _tv_kernel(per_channel: bool):
    """The TV kernel, launched over (cells, 1) a thread per cell, looping over the channels, or with
    `per_channel` over (cells, channels): on CUDA a cell's channels then read and add neighbouring floats
    from neighbouring threads, where a thread per cell strides by a row. Channel 0's thread marks."""

    @KERNEL
    def tv_cells(
        links: wp.array3d(dtype=wp.int32),  # a cascade's levels stacked along x
        rx: int,  # x voxels of one level
        values: wp.array2d(dtype=wp.float32),
        cells: wp.array(dtype=wp.int64),
        rho: wp.vec3,
        scale: float,
        missing_self: int,
        grad: wp.array2d(dtype=wp.float32),
        touched: wp.array(dtype=wp.uint8),
        mark: int,
        marks_only: int,
    ):
        i, channel = wp.tid()
        rows = cell_rows(links, rx, cells[i])
        if wp.max(rows) < 0:
            return  # nothing allocated here: no term writes anything (most of a cascade's outer cells)
        if marks_only == 0:
            # `wp.static`: decided when the kernel is built, so each layout holds only its own code
            if wp.static(per_channel):
                add_channel_terms(values, channel, rows, rho, scale, missing_self, grad)
            else:
                for c in range(values.shape[1]):
                    add_channel_terms(values, c, rows, rho, scale, missing_self, grad)
        # `tv_grad_(marks_only=True)`: the rows the cell's terms would read, marked
        if channel == 0 and (mark != 0 or marks_only != 0):
            mark_rows(touched, rows)

    return tv_cells


@torch.no_grad()
def tv_grad_(
    term: TVTerm,
    grad: torch.Tensor,
    touched: torch.Tensor | None = None,
    marks_only: bool = False,
    per_channel: bool | None = None,
) -> torch.Tensor:
    """Exactly `tv_reference.tv_grad_reference_`'s contract: add `term`'s TV gradient of its values over its
    cells into `grad`; also marks the rows it adds to in `touched` (uint8 over the rows) when given. With
    `marks_only` it only marks them (the rows it would read; `grad` is untouched): `train/optim`'s owed
    pull is paid there before the TV reads them.

    `grad` may instead be gradient parts (P, *values.shape), which the optimiser sums: on the CPU the
    cells are then shared out over up to P threads, each adding into its own part, because Warp runs a
    CPU kernel on one thread and its CPU atomics are plain adds; on CUDA one launch into part 0.

    `per_channel`: a thread per (cell, channel) rather than per cell: the same additions in the same
    order, so the same result (to the bit on a CPU); None: `CUDA_TV_PER_CHANNEL` on CUDA, per cell on a
    CPU."""
    if marks_only and touched is None:
        raise ValueError("marks_only marks the rows in `touched`: give it")
    grid_links, values, weight, missing_mode = term.links, term.values, term.weight, term.missing
    if weight == 0 or term.cells.numel() == 0:
        return grad
    parts = grad if grad.dim() == values.dim() + 1 else grad.unsqueeze(0)
    check_grad_args(values, parts[0], missing_mode)
    if touched is not None:
        check_row_array("touched", touched, values.shape[0], torch.uint8)
    cells = check_cells(grid_links, term.cells).contiguous()
    n = cells.numel()
    rho = rho_values(grid_links.shape[-3:], term.reference_reso)
    marks = values.new_zeros(1, dtype=torch.uint8) if touched is None else touched
    as2d = (lambda t: t.unsqueeze(-1)) if values.dim() == 1 else (lambda t: t)
    device = warp_device(values)
    if per_channel is None:
        per_channel = CUDA_TV_PER_CHANNEL and device != "cpu"
    links = to_warp(grid_links.reshape(-1, *grid_links.shape[-2:]), "the grid links")
    head = [links, int(grid_links.shape[-3]), to_warp(as2d(values.detach()), "the TV values")]
    middle = [wp.vec3(*rho), float(weight) / n, int(missing_mode == "self")]
    tail = [to_warp(marks, "the touched rows"), int(touched is not None), int(marks_only)]
    kernel = _tv_kernel(bool(per_channel))
    channels = as2d(values).shape[1] if per_channel and not marks_only else 1

    def launch(start: int, stop: int, part: int) -> None:
        share = to_warp(cells[start:stop], "the TV cells")
        inputs = [*head, share, *middle, to_warp(as2d(parts[part]), "a TV gradient part"), *tail]
        launch_kernel(kernel, dim=(stop - start, channels), inputs=inputs, device=device)

    workers = min(parts.shape[0], cpu_workers()) if device == "cpu" else 1
    if workers <= 1 or n < MIN_TV_CELLS_PER_THREAD * workers:
        launch(0, n, 0)
    else:
        run_parts(split(n, workers), launch, workers)
    return grad
