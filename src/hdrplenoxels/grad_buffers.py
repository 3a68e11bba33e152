"""Gradient accumulators for the grid, allocated once per grid resolution and reused every step.

Warp's CPU atomics are plain adds, so each CPU thread of the backward pass writes its own part
(`parts` of them, stacked in one tensor); GPU atomics need only one. The optimiser reads all parts
and zeroes them, so training allocates and clears no full-size gradient grid per step.
"""

from __future__ import annotations

import torch

from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.render.parallel import cpu_workers


def gradient_parts(device: torch.device) -> int:
    """Buffers the Warp backward needs: one per CPU thread, one on CUDA (its atomics are real)."""
    return cpu_workers() if device.type == "cpu" else 1


class GridGradients:
    def __init__(self, grid: SparseGrid, parts: int = 1):
        self.density = torch.zeros((parts, *grid.density.shape), device=grid.device)
        self.sh = torch.zeros((parts, *grid.sh.shape), device=grid.device)

    def fits(self, grid: SparseGrid) -> bool:
        return self.density.shape[1:] == grid.density.shape and self.sh.shape[1:] == grid.sh.shape

    def total(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(d density, d SH) summed over the parts (new tensors)."""
        return self.density.sum(0), self.sh.sum(0)
