"""Two-level occupancy for empty-space skipping, exact by construction.

A sample's density is a convex combination of its cell's 8 corner voxels (missing voxels count 0), so
it can only exceed `sigma_thresh >= 0` if some corner voxel has density > 0. A cell is occupied when
one of its corners is allocated with density > 0, a block of B^3 cells when one of its cells is. The
ray march jumps over empty blocks and, inside occupied ones, reads one byte instead of 8 corners for
an empty cell, without changing a single output or gradient. Marking more cells than that (as the
optimiser does between exact rebuilds when it updates only some voxels) costs speed, never results.
`kernels/occupancy_reference.py` is the readable definition the Warp kernel is tested against.

Oracle: `hdrplenoxels.kernels.occupancy_reference.occupancy_reference`; parity:
tests/test_render_acceleration.py.
"""

from __future__ import annotations

import functools
import math
import weakref

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_split, to_warp, warp_device, warp_struct
from hdrplenoxels.grid.sparse_grid import SparseGrid

DEFAULT_BLOCK = 8  # cells per block side: 16^3 blocks for a 128^3 grid
# Training steps between exact rebuilds of the marks, which the training engine makes between steps: its
# optimiser only adds marks (each costs a little skipping), and a rebuild visits every voxel, so it is
# spread thin.
TIGHTEN_EVERY = 32


def block_shape(reso: tuple[int, int, int], block: int) -> tuple[int, int, int]:
    """Blocks per axis: the R - 1 cells of an axis in groups of `block`."""
    return tuple(math.ceil((r - 1) / block) for r in reso)  # type: ignore[return-value]


@wp.struct
class OccupancyMarks:
    """What a kernel needs to mark the cells around a voxel it leaves with density > 0
    (`BlockOccupancy.marks`): every row's level and grid coordinates, and the cell and block marks."""

    coords: wp.array(dtype=wp.vec4i)  # level, x, y, z
    shift: int  # a block is 2^shift cells a side
    cells: wp.array4d(dtype=wp.uint8)
    blocks: wp.array4d(dtype=wp.uint8)


@wp.func
def mark_voxel(marks: OccupancyMarks, row: int):
    """Voxel `row` (density > 0) is a corner of cells v - 1 and v per axis (v its coordinates; those
    cells that exist): mark them and their blocks. Threads may mark the same cell: every write stores
    the same 1."""
    v = marks.coords[row]
    level = v[0]
    shift = marks.shift
    cells = marks.cells
    blocks = marks.blocks
    for n in range(8):  # unrolled: cell v - 1 + (n's bits)
        x = v[1] - 1 + (n >> 2)
        y = v[2] - 1 + ((n >> 1) & 1)
        z = v[3] - 1 + (n & 1)
        inside = x >= 0 and y >= 0 and z >= 0
        if inside and x < cells.shape[1] and y < cells.shape[2] and z < cells.shape[3]:  # noqa: SIM102
            # Nested, not `and`: Warp may evaluate both sides, and the read must stay in bounds.
            # Write only what changes: a cache line shared by threads stays clean once set.
            if cells[level, x, y, z] == wp.uint8(0):
                cells[level, x, y, z] = wp.uint8(1)
                if blocks[level, x >> shift, y >> shift, z >> shift] == wp.uint8(0):
                    blocks[level, x >> shift, y >> shift, z >> shift] = wp.uint8(1)


@KERNEL
def _mark_occupied(density: wp.array(dtype=wp.float32), first_row: int, marks: OccupancyMarks):
    row = wp.tid() + first_row
    if density[row] > 0.0:
        mark_voxel(marks, row)


@functools.cache
def no_marks(device: str) -> OccupancyMarks:
    """The kernel argument for "mark nothing" (with arrays of the right types, never written)."""
    return warp_struct(
        OccupancyMarks,
        coords=wp.zeros(1, dtype=wp.vec4i, device=device),
        shift=0,
        cells=wp.zeros((1, 1, 1, 1), dtype=wp.uint8, device=device),
        blocks=wp.zeros((1, 1, 1, 1), dtype=wp.uint8, device=device),
    )


def voxel_coords(links: torch.Tensor, num_voxels: int) -> torch.Tensor:
    """(M, 4) int32 level and grid coordinates of every allocated row of `links` (levels, Rx, Ry, Rz)."""
    where = (links >= 0).nonzero()
    coords = torch.zeros((num_voxels, 4), dtype=torch.int32, device=links.device)
    coords[links[where[:, 0], where[:, 1], where[:, 2], where[:, 3]].long()] = where.to(torch.int32)
    return coords


class BlockOccupancy:
    """The occupied cells and blocks of one grid, rebuilt only when its links or density change
    (or, after the optimiser's touched-voxel updates, added to until the engine calls `rebuild`).

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
        levels = grid.levels
        self.cells = torch.zeros((levels, *[r - 1 for r in grid.reso]), dtype=torch.uint8, device=grid.device)
        self.blocks = torch.zeros(
            (levels, *block_shape(grid.reso, block)), dtype=torch.uint8, device=grid.device
        )
        self.refresh(grid)

    def refresh(self, grid: SparseGrid) -> None:
        if self.density_stamp is None or not self.density_stamp.matches(grid.density):
            self.rebuild(grid.density)

    def rebuild(self, density: torch.Tensor) -> None:
        """The exact marks for `density` (one value per row of this grid), from scratch."""
        marks = self.marks()
        n = density.shape[0]
        if n:
            values = to_warp(density.detach(), "the grid density")
            launch_split(_mark_occupied, n, [values], [marks], warp_device(density))
        self.rebuilt_for(density)

    def marks(self, clear: bool = True) -> OccupancyMarks:
        """The kernel argument for `mark_voxel`, after clearing both levels: a kernel that writes the
        density of every row (the fused optimiser) rebuilds the occupancy in the same pass, and then
        calls `rebuilt_for(density)`. `clear=False`, for a kernel that writes some rows only: the
        rows it leaves with density > 0 are added, and other cells keep their marks."""
        if clear:
            self.cells.zero_()
            self.blocks.zero_()
        return warp_struct(
            OccupancyMarks,
            coords=to_warp(self.coords, "the voxel coordinates", dtype=wp.vec4i),
            shift=self.shift,
            cells=to_warp(self.cells, "the occupancy cells"),
            blocks=to_warp(self.blocks, "the occupancy blocks"),
        )

    def rebuilt_for(self, density: torch.Tensor) -> None:
        """The marks hold for `density` as it is now: exactly, or (after a touched-voxel update, which
        only adds marks) as a superset of the exact occupancy, which keeps skipping exact, only slower,
        until the next `rebuild`."""
        self.density_stamp = _Stamp(density)


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
