"""Trilinear sampling of a level's rows at many points as one Warp kernel: the values (SH) of the
voxels a resample keeps.

The reference gathers every point's 8 corners into (points, 8, columns) temporaries a chunk at a time,
a dozen torch passes over memory per chunk; here each thread sums its own point's corners into its
output row.

Oracle: `hdrplenoxels.grid.resample_reference.trilinear_rows_reference`; parity: tests/test_grid.py.
"""

from __future__ import annotations

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, split
from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, launch_parts, to_warp, warp_device


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
    target = to_warp(out, "the sampled rows")

    def launch(start: int, stop: int, part: int) -> None:
        launch_kernel(_trilinear_rows, dim=stop - start, inputs=[*inputs, start, target], device=device)

    launch_parts(device, n, split(n, cpu_workers()), launch)
    return out
