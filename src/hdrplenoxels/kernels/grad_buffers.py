"""Gradient accumulators for the grid, allocated once per grid resolution and reused every step.

Warp's CPU atomics are plain adds, so each CPU thread of the backward pass writes its own part
(`parts` of them; as many as memory allows); GPU atomics need only one. The optimiser reads all parts
and zeroes them, so training allocates and clears no full-size gradient grid per step.

The parts are seen as one (parts, M, ...) tensor but stored with each row's parts side by side
(`part_buffers`): stacked whole, the step from one part to the next is a whole grid, which passes the
32-bit byte strides Warp addresses once a grid holds ~20 M voxels (JOURNAL.md, "Large arrays").

`touched` marks the rows (voxels) the Warp kernels added to, in density or SH (a byte per voxel,
shared by the parts: every writer stores the same 1), so the optimiser can visit only those rows
(or, where its update is dense because the view prior's pull acts on every row, read only their
gradients).
"""

from __future__ import annotations

import torch

from hdrplenoxels.core.host_memory import available_memory_bytes
from hdrplenoxels.core.parallel import cpu_workers
from hdrplenoxels.grid.sparse_grid import SparseGrid

# The parts beyond the first may take at most this share of the memory still available when they
# are allocated. Each is as large as the grid's parameters, so on a many-core machine a paper-size
# grid's parts alone would otherwise outgrow the grid, its optimiser state and its gradient together;
# fewer parts only means fewer threads
# in the backward, never a different result.
SPARE_MEMORY_SHARE = 0.5


def gradient_parts(grid: SparseGrid) -> int:
    """Buffers the Warp backward over `grid` uses: one per CPU thread (as many as fit in the memory
    share above, at least one), one on CUDA (its atomics are real)."""
    if grid.device.type != "cpu":
        return 1
    workers = cpu_workers()
    part_bytes = grid.num_voxels * (1 + grid.sh.shape[1]) * 4  # float32 density and SH rows
    available = available_memory_bytes()
    if workers == 1 or available is None or part_bytes == 0:
        return workers
    return max(1, min(workers, 1 + int(available * SPARE_MEMORY_SHARE) // part_bytes))


def part_buffers(parts: int, shape: tuple[int, ...], row_axes: int, device: torch.device) -> torch.Tensor:
    """Zeroed gradient parts, a (parts, *shape) view of storage laid out (*shape[:row_axes], parts,
    *shape[row_axes:]): every stride stays within one row's parts, and each part is a strided view the
    kernels address like a tensor of its own. `row_axes`: the leading axes the optimiser takes as its
    rows (each row's parts then stay adjacent, so its (parts, rows, columns) view needs no copy); 0
    stacks the parts whole, each contiguous."""
    storage = torch.zeros((*shape[:row_axes], parts, *shape[row_axes:]), device=device)
    return storage.movedim(row_axes, 0)


class GridGradients:
    def __init__(self, grid: SparseGrid, parts: int = 1):
        self.density = part_buffers(parts, tuple(grid.density.shape), 1, grid.device)
        self.sh = part_buffers(parts, tuple(grid.sh.shape), 1, grid.device)
        self.touched = torch.zeros(grid.num_voxels, dtype=torch.uint8, device=grid.device)

    def fits(self, grid: SparseGrid) -> bool:
        return self.density.shape[1:] == grid.density.shape and self.sh.shape[1:] == grid.sh.shape

    def total(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(d density, d SH) summed over the parts (new tensors)."""
        return self.density.sum(0), self.sh.sum(0)


def check_row_array(name: str, t: torch.Tensor, rows: int, dtype: torch.dtype) -> None:
    """Raise unless `t` holds one `dtype` value per row (kernels index it by row, unchecked)."""
    if t.shape != (rows,) or t.dtype != dtype:
        raise ValueError(f"{name} must be {dtype} of shape ({rows},), got {t.dtype} {tuple(t.shape)}")
