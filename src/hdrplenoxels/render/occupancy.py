"""Coarse block occupancy for empty-space skipping, exact by construction.

A sample's density is a convex combination of its cell's 8 corner voxels (missing voxels count 0), so
it can only exceed `sigma_thresh >= 0` if some corner voxel has density > 0. A block of B^3 cells is
marked occupied when any corner voxel of any of its cells (voxels [bB, bB + B] per axis) is allocated
with density > 0; the ray march jumps over the other blocks without changing a single output or
gradient. `block_occupancy_reference` is the readable definition the Warp kernel is tested against.
"""

from __future__ import annotations

import math
import weakref

import torch
import torch.nn.functional as F
import warp as wp

from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.warp_runtime import KERNEL, warp_device

DEFAULT_BLOCK = 8  # cells per block side: 16^3 blocks for a 128^3 grid


def block_shape(reso: tuple[int, int, int], block: int) -> tuple[int, int, int]:
    """Blocks per axis: the R - 1 cells of an axis in groups of `block`."""
    return tuple(math.ceil((r - 1) / block) for r in reso)  # type: ignore[return-value]


def block_occupancy_reference(links: torch.Tensor, density: torch.Tensor, block: int) -> torch.Tensor:
    """uint8 (Bx, By, Bz): 1 where a block's cells touch an allocated voxel with density > 0."""
    alive = torch.zeros(links.shape, dtype=torch.float32, device=links.device)
    present = links >= 0
    alive[present] = (density.detach()[links[present].long()] > 0).float()
    cell = F.max_pool3d(alive[None, None], kernel_size=2, stride=1)  # (R-1)^3: any of a cell's corners
    blocks = F.max_pool3d(cell, kernel_size=block, stride=block, ceil_mode=True)
    return (blocks[0, 0] > 0).to(torch.uint8)


@KERNEL
def _mark_blocks(
    coords: wp.array(dtype=wp.vec3i),
    density: wp.array(dtype=wp.float32),
    cells: wp.vec3i,
    block: int,
    occupancy: wp.array3d(dtype=wp.uint8),
):
    """Voxel v is a corner of cells v - 1 and v per axis (those that exist); mark their blocks."""
    row = wp.tid()
    if density[row] <= 0.0:
        return
    v = coords[row]
    lo = wp.vec3i(0, 0, 0)
    hi = wp.vec3i(0, 0, 0)
    for a in range(3):
        lo[a] = wp.max(v[a] - 1, 0) // block
        hi[a] = wp.min(v[a], cells[a] - 1) // block
    for bx in range(lo[0], hi[0] + 1):
        for by in range(lo[1], hi[1] + 1):
            for bz in range(lo[2], hi[2] + 1):
                occupancy[bx, by, bz] = wp.uint8(1)


def voxel_coords(links: torch.Tensor, num_voxels: int) -> torch.Tensor:
    """(M, 3) int32 grid coordinates of every allocated row."""
    where = (links >= 0).nonzero()
    coords = torch.zeros((num_voxels, 3), dtype=torch.int32, device=links.device)
    coords[links[where[:, 0], where[:, 1], where[:, 2]].long()] = where.to(torch.int32)
    return coords


class BlockOccupancy:
    """The occupied blocks of one grid, rebuilt only when its links or density change.

    `occupancy_for(grid)` keeps one per grid and checks torch's version counters, so renders of an
    unchanged grid (evaluation, rendering views chunk by chunk) build it once; code that writes the
    arrays behind torch's back (the fused optimiser) bumps the counters.
    """

    def __init__(self, grid: SparseGrid, block: int = DEFAULT_BLOCK):
        if block < 1 or block & (block - 1):
            raise ValueError(f"the occupancy block size must be a power of two, got {block}")
        self.block = block
        self.shift = block.bit_length() - 1  # the kernels divide by shifting
        self.links_stamp = _Stamp(grid.links)
        self.coords = voxel_coords(grid.links, grid.num_voxels)
        self.density_stamp: _Stamp | None = None
        self.blocks = torch.zeros(block_shape(grid.reso, block), dtype=torch.uint8, device=grid.device)
        self.refresh(grid)

    def refresh(self, grid: SparseGrid) -> None:
        if self.density_stamp is not None and self.density_stamp.matches(grid.density):
            return
        self.blocks.zero_()
        n = grid.num_voxels
        if n:
            device = warp_device(grid.density)
            wp.launch(
                _mark_blocks,
                dim=n,
                inputs=[
                    wp.from_torch(self.coords, dtype=wp.vec3i, requires_grad=False),
                    wp.from_torch(grid.density.detach(), requires_grad=False),
                    wp.vec3i(*(r - 1 for r in grid.reso)),
                    self.block,
                ],
                outputs=[wp.from_torch(self.blocks, requires_grad=False)],
                device=device,
                stream=None if device == "cpu" else wp.stream_from_torch(torch.cuda.current_stream()),
            )
        self.density_stamp = _Stamp(grid.density)

    def occupied_fraction(self) -> float:
        return float(self.blocks.float().mean()) if self.blocks.numel() else 0.0


class _Stamp:
    """Identifies one state of one tensor: the same object (held weakly) at the same version."""

    def __init__(self, t: torch.Tensor):
        self.ref = weakref.ref(t)
        self.version = t._version

    def matches(self, t: torch.Tensor) -> bool:
        return self.ref() is t and self.version == t._version


def occupancy_for(grid: SparseGrid, block: int | None = None) -> BlockOccupancy:
    """The grid's cached occupancy, rebuilt when the links (resample) or the density changed.

    `block` None keeps the cached block size (`DEFAULT_BLOCK` for a new one), so a caller (a test)
    can choose the size once and every later render uses it.
    """
    occ = grid.__dict__.get("_occupancy")
    if block is None:
        block = DEFAULT_BLOCK if occ is None else occ.block
    if occ is None or occ.block != block or not occ.links_stamp.matches(grid.links):
        occ = BlockOccupancy(grid, block)
        grid.__dict__["_occupancy"] = occ
    else:
        occ.refresh(grid)
    return occ
