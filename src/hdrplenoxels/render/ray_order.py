"""An order for a batch of rays in which neighbours in the batch pass through nearby voxels.

A CPU thread marches a contiguous range of the batch, one ray after another. Training batches are
pixels drawn at random over all images, so consecutive rays read (forward) and add to (backward)
unrelated grid rows, and nearly every row costs a cache miss. Sorted along a Morton curve of where
each ray enters and leaves the grid's box, rays that share voxels follow each other, and a row is
often still in cache from the ray before. The set of rays, and so the loss, is unchanged; only the
order of float additions differs.

A grid whose SH rows fit in the last-level cache (a 64^3 demo grid: a few MB) is left unsorted: there
the sort costs time and gains nothing (JOURNAL.md, "Constants justified by timings").
"""

from __future__ import annotations

import functools

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid

BITS = 5  # per coordinate: 6 coordinates fill 30 bits of the key
# SH size below which batches stay unsorted: such rows stay in a last-level cache of this size anyway
# (the benchmark machine's L3; JOURNAL.md, "Constants justified by timings").
CACHED_GRID_BYTES = 32 * 2**20


@functools.cache
def _spread_bits(device: torch.device) -> torch.Tensor:
    """For v < 2^BITS: v's bits moved to every 6th position (bit b to bit 6b)."""
    values = torch.arange(2**BITS, device=device)
    spread = torch.zeros_like(values)
    for b in range(BITS):
        spread |= ((values >> b) & 1) << (6 * b)
    return spread


def box_crossings(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each ray enters and leaves the grid's (outermost) box, in [0, 1]^3 box coordinates (a ray
    that misses the box gets the points nearest its line, clamped into the box)."""
    scale, offset = grid.world_to_grid_affine(origins.device, level=grid.levels - 1)
    reso = torch.tensor(grid.reso, dtype=torch.float32, device=origins.device)
    o = origins * scale + offset + 0.5  # the box is [0, reso] here
    d = dirs * scale
    inv = 1.0 / torch.where(d == 0, torch.full_like(d, 1e-12), d)
    t_a, t_b = -o * inv, (reso - o) * inv
    t_in = torch.minimum(t_a, t_b).amax(-1).clamp(min=0.0)
    t_out = torch.maximum(torch.maximum(t_a, t_b).amin(-1), t_in)
    enter = (o + t_in[:, None] * d) / reso
    leave = (o + t_out[:, None] * d) / reso
    return enter.clamp(0.0, 1.0), leave.clamp(0.0, 1.0)


def locality_order(grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Indices that sort the rays along a 6-D Morton curve of their box entry and exit points."""
    enter, leave = box_crossings(grid, origins, dirs)
    cells = (torch.cat([enter, leave], dim=-1) * (2**BITS - 1)).round().long()
    spread = _spread_bits(origins.device)[cells]  # (N, 6)
    shifts = torch.arange(6, device=origins.device)
    key = (spread << shifts).sum(-1)  # the spread bits of different coordinates never overlap
    return torch.argsort(key, stable=True)


def training_order(grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor | None:
    """`locality_order` for a training batch on the CPU, or None where sorting would not pay: the
    grid's SH rows fit in cache, or the rays are on a GPU (there a ray is a warp, and the order of the
    batch was not measured to matter)."""
    if origins.device.type != "cpu" or grid.sh.numel() * grid.sh.element_size() <= CACHED_GRID_BYTES:
        return None
    return locality_order(grid, origins, dirs)
