"""The "weight" pruning rule: keep voxels that some training ray actually sees (docs/method.md, "Grid").

Every pooled training ray is marched through the density resampled at the *new* resolution (half-voxel
steps, its own early stop at transmittance 0.2 as in svox2), and each voxel records the largest sample
weight T_k alpha_k written to any of the 8 corners of a sample's cell. Used by `SparseGrid.resample`
with the threshold `weight_thresh / R'_z`.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights, resampled_density
from hdrplenoxels.kernels.march_reference import (
    composite_weights,
    optical_lengths,
    ray_segments,
    sample_points,
)
from hdrplenoxels.kernels.options import RenderOptions

WEIGHT_RENDER_STOP = 0.2


@torch.no_grad()
def max_weight_score(
    grid: SparseGrid,
    reso: tuple[int, int, int],
    rays: Iterable[tuple[torch.Tensor, torch.Tensor]],
    opt: RenderOptions = RenderOptions(),
    chunk: int = 2048,
) -> torch.Tensor:
    """Max ray weight (levels, R'x, R'y, R'z) per voxel of the resampled density, over the given
    (origins, dirs)."""
    density = torch.stack([resampled_density(lk, grid.density, reso) for lk in grid.links])
    n = density.numel()
    links = torch.arange(n, dtype=torch.int32, device=grid.device).reshape(density.shape)
    no_colour = torch.zeros((n, 3), device=grid.device)
    dense = SparseGrid(links, density.reshape(-1), no_colour, grid.center, grid.radius)
    march = RenderOptions(opt.step_size, opt.sigma_thresh, WEIGHT_RENDER_STOP, 0.0, opt.t_max)
    score = torch.zeros(n, device=grid.device)
    for origins, dirs in rays:
        for i in range(0, origins.shape[0], chunk):
            seg = ray_segments(dense, origins[i : i + chunk], dirs[i : i + chunk], march)
            pos, level, _, valid = sample_points(seg, march.step_size)
            rows, cw = corner_weights(links, pos, level)
            sigma = (cw * dense.density[rows]).sum(-1)
            weights, _ = composite_weights(sigma, valid, optical_lengths(seg, valid, march), march)
            score.scatter_reduce_(0, rows.reshape(-1), weights[..., None].expand_as(rows).reshape(-1), "amax")
    return score.reshape(density.shape)
