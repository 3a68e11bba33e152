"""Trilinear sampling of a level's rows at many points as one Warp kernel: the values (SH) of the
voxels a resample keeps.

The reference gathers every point's 8 corners into (points, 8, columns) temporaries a chunk at a time,
a dozen torch passes over memory per chunk; here each thread sums its own point's corners into its
output row.

Oracle: `hdrplenoxels.kernels.resample_reference.trilinear_rows_reference`; parity: tests/test_grid.py.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_split, to_warp, warp_device
from hdrplenoxels.grid.sparse_grid import SparseGrid, kept_voxels, resample_axes, resampled_density


@KERNEL
def _trilinear_rows(
    links: wp.array3d(dtype=wp.int32),
    data: wp.array2d(dtype=wp.float32),
    points: wp.array(dtype=wp.vec3),
    first: int,
    out: wp.array2d(dtype=wp.float32),
):
    i = wp.tid() + first
    reso = wp.vec3i(links.shape[0], links.shape[1], links.shape[2])
    base = wp.vec3i(0, 0, 0)
    frac = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):  # `corner_weights`: clamp into the grid, the base corner at most R - 2
        p = wp.min(wp.max(points[i][a], 0.0), float(reso[a] - 1))
        base[a] = wp.min(int(wp.floor(p)), reso[a] - 2)
        frac[a] = p - float(base[a])
    for c in range(out.shape[1]):
        out[i, c] = 0.0
    for corner in range(8):  # bit order x, y, z: `CORNER_OFFSETS`
        ox = corner >> 2
        oy = (corner >> 1) & 1
        oz = corner & 1
        row = links[base[0] + ox, base[1] + oy, base[2] + oz]
        if row >= 0:
            w = wp.where(ox == 1, frac[0], 1.0 - frac[0])
            w = w * wp.where(oy == 1, frac[1], 1.0 - frac[1])
            w = w * wp.where(oz == 1, frac[2], 1.0 - frac[2])
            for c in range(out.shape[1]):
                out[i, c] += w * data[row, c]


@torch.no_grad()
def trilinear_rows(links: torch.Tensor, data: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """`trilinear_rows_reference(links, data, points)` for one level's `links` (Rx, Ry, Rz), rows `data`
    (M, C) and grid points (N, 3) -> (N, C) float32, shared out over the CPU's threads."""
    n = points.shape[0]
    out = torch.empty((n, data.shape[1]), dtype=torch.float32, device=data.device)
    if n == 0:
        return out
    device = warp_device(data)
    inputs = [
        to_warp(links.contiguous(), "the grid links"),
        to_warp(data.detach().float().contiguous(), "the values to sample"),
        to_warp(points.float().contiguous(), "the sample points", dtype=wp.vec3),
    ]
    launch_split(_trilinear_rows, n, inputs, [to_warp(out, "the sampled rows")], device)
    return out


def resample(
    grid: SparseGrid,
    reso: tuple[int, int, int],
    score: torch.Tensor | None = None,
    thresh: float = 5.0,
    dilate: int = 2,
    max_voxels: int = 44_000_000,
    allowed: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> SparseGrid:
    """`grid` resampled: every level to a new resolution, pruning and dilating (docs/method.md, "Grid").

    New voxel i sits at old grid coordinate `(i + 0.5) * R / R' - 0.5` of its level. Voxels are kept
    where `score` (levels, R'x, R'y, R'z) >= `thresh`; the score defaults to the resampled density
    (the "sigma" rule), or is the per-voxel maximum ray weight of `pruning.max_weight_score` (the
    "weight" rule). The mask is dilated `dilate` times with a 26-neighbour max filter within each
    level and voxels no ray can read dropped; if more than `max_voxels` remain over all levels, the
    threshold rises until they fit (`kept_voxels`). Density and SH are trilinearly resampled at the
    kept voxels (density is kept unclamped, so it may be < thresh in the band). `allowed`, given the
    kept voxels (K, 4) as (level, x, y, z), says which of them may stay at all (`train/view_coverage`).
    """
    axes = resample_axes(grid.reso, reso, grid.device)
    with torch.no_grad():
        new_density = torch.stack([resampled_density(lk, grid.density, reso) for lk in grid.links])
        score = new_density if score is None else score.reshape(new_density.shape)
        keep = kept_voxels(score, thresh, dilate, max_voxels)
        idx = keep.nonzero()  # (K, 4): level, x, y, z in row-major order, matching `links[keep] = arange`
        if allowed is not None:
            ok = allowed(idx)
            keep[tuple(idx[~ok].T)] = False
            idx = idx[ok]  # still row-major: a subset in the same order
        pts = torch.stack([axes[a][idx[:, a + 1]] for a in range(3)], dim=-1)
        sh = torch.empty((idx.shape[0], grid.sh.shape[1]), dtype=grid.sh.dtype, device=grid.device)
        for level in range(grid.levels):
            at = idx[:, 0] == level
            sh[at] = trilinear_rows(grid.links[level], grid.sh, pts[at])
        links = torch.full((grid.levels, *reso), -1, dtype=torch.int32, device=grid.device)
        links[keep] = torch.arange(idx.shape[0], dtype=torch.int32, device=grid.device)
        density = new_density[keep].contiguous()
        return SparseGrid(links, density, sh.contiguous(), grid.center, grid.radius)
