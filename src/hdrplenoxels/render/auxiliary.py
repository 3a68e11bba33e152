"""Expected depth and opacity along rays, from the ordinary forward kernel (for the viewer's displays).

Opacity is 1 - T, the transmittance the march leaves for the background. Depth is the weighted mean
distance of the samples, sum_k w_k d_k / sum_k w_k: the forward computes sum_k w_k c_k for any colour field
c, so a copy of the grid whose colour at each voxel is that voxel's distance from the camera gives the
numerator (DC-only SH: colour = C0 sh + 0.5 inverts exactly; the distance is interpolated trilinearly
between voxel centres, within half a voxel of the sample's own distance). A corner missing from the
sparse grid has zero SH and so reads as distance 0.5; pruning keeps a dilated shell of voxels around every
surface, so such corners carry little weight in a trained grid.
"""

from __future__ import annotations

import torch

from hdrplenoxels.geometry.sh import SH_C0
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.march_kernel import render_forward
from hdrplenoxels.kernels.occupancy_kernel import voxel_coords
from hdrplenoxels.kernels.options import RenderOptions


def distance_field(grid: SparseGrid, eye: torch.Tensor) -> SparseGrid:
    """`grid`'s density with, as colour, each voxel's distance from `eye` (grid's own space)."""
    coords = voxel_coords(grid.links, grid.num_voxels)
    centres = grid.grid_to_world(coords[:, 1:].float(), coords[:, 0].long())
    distance = torch.linalg.norm(centres - eye.to(centres), dim=1)
    sh = ((distance - 0.5) / SH_C0)[:, None].expand(-1, 3).contiguous()
    return SparseGrid(grid.links, grid.density, sh, grid.center, grid.radius)


@torch.no_grad()
def depth_and_opacity(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions, eye: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth, opacity), each (N,): depth from `eye` (0 where nothing is hit), opacity in [0, 1]."""
    n = origins.shape[0]
    behind = torch.zeros((n, 3), device=origins.device)
    transmittance = torch.empty(n, device=origins.device)
    weighted = render_forward(
        distance_field(grid, eye), origins, dirs, opt, behind=behind, transmittance=transmittance
    )
    opacity = (1.0 - transmittance).clamp(0.0, 1.0)
    depth = torch.where(opacity > 1e-4, weighted[:, 0] / opacity.clamp(min=1e-4), torch.zeros_like(opacity))
    return depth, opacity
