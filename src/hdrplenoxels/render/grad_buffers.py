"""Gradient accumulators for the grid, allocated once per grid resolution and reused every step.

Warp's CPU atomics are plain adds, so each CPU thread of the backward pass writes its own part
(`parts` of them, stacked in one tensor; as many as memory allows); GPU atomics need only one. The
optimiser reads all parts and zeroes them, so training allocates and clears no full-size gradient
grid per step.

`touched` marks the rows (voxels) the Warp kernels added to, in density or SH (a byte per voxel,
shared by the parts: every writer stores the same 1), so the optimiser can visit only those rows
(unless its update is dense: the view prior's pull acts on every row).
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


class GridGradients:
    def __init__(self, grid: SparseGrid, parts: int = 1):
        self.density = torch.zeros((parts, *grid.density.shape), device=grid.device)
        self.sh = torch.zeros((parts, *grid.sh.shape), device=grid.device)
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
