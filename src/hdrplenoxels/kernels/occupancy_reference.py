"""The cell and block occupancy of a grid in PyTorch: the readable oracle of the occupancy kernels in
kernels/occupancy_kernel.py (docs/design.md, "Kernels")."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def occupancy_reference(
    links: torch.Tensor, density: torch.Tensor, block: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 cell (R-1 per axis) and block (`occupancy.block_shape`) occupancy of each level of `links`
    (levels, Rx, Ry, Rz) (or of one level's (Rx, Ry, Rz)): 1 where a cell, or one of a block's cells,
    has an allocated corner voxel with density > 0. The oracle of kernels/occupancy_kernel.py."""
    alive = torch.zeros(links.shape, dtype=torch.float32, device=links.device)
    present = links >= 0
    alive[present] = (density.detach()[links[present].long()] > 0).float()
    batch = alive.reshape(-1, 1, *links.shape[-3:])
    cell = F.max_pool3d(batch, kernel_size=2, stride=1)  # (R-1)^3: any of a cell's corners
    blocks = F.max_pool3d(cell, kernel_size=block, stride=block, ceil_mode=True)
    lead = links.shape[:-3]
    return (
        (cell[:, 0] > 0).to(torch.uint8).reshape(*lead, *cell.shape[-3:]),
        (blocks[:, 0] > 0).to(torch.uint8).reshape(*lead, *blocks.shape[-3:]),
    )
