"""Voxels too few training views see, kept out of the grid (docs/method.md, "Views per voxel").

Content that a single training view sees has no second view to fix its depth: the photometric loss is as
content with a blob just in front of that camera as with the surface far behind it, and such a blob
hangs in every novel view that looks through it. Counting, for each voxel centre, the pooled views whose
pixels (all of a training view, the left half of a test view) it projects into, and keeping voxels only
where at least `grid.min_views` do, leaves that content to the levels farther out and the background.
Occlusion is ignored: a voxel behind a wall still counts as seen, so the count only ever keeps too much.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid


@dataclass(frozen=True)
class PooledFrustums:
    """The pixels each view lends the training pool, as pinhole frustums in the grid's world frame."""

    w2c: torch.Tensor  # (V, 4, 4) world to camera (OpenCV axes: z forward)
    intrinsics: torch.Tensor  # (V, 4) fx, fy, cx, cy
    widths: torch.Tensor  # (V,) columns [0, width) in the pool
    heights: torch.Tensor  # (V,)


def pooled_frustums(
    c2w: torch.Tensor,
    intrinsics: torch.Tensor,
    image_ids: torch.Tensor,
    widths: torch.Tensor,
    heights: torch.Tensor,
) -> PooledFrustums:
    """The frustums of the views `image_ids` (the ray pool's) with their pooled `widths` and `heights`."""
    ids = image_ids.long()
    return PooledFrustums(
        torch.linalg.inv(c2w[ids].double()).float(), intrinsics[ids].float(), widths.float(), heights.float()
    )


def views_seeing(frustums: PooledFrustums, points: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
    """(N,) how many of the frustums hold each of `points` (N, 3): in front of the camera and inside its
    pooled pixels (pixel u covers [u, u + 1), its centre at u + 0.5, as `geometry.cameras.pixel_rays`)."""
    f = frustums
    rot, shift = f.w2c[:, :3, :3].to(points.device), f.w2c[:, :3, 3].to(points.device)
    fx, fy, cx, cy = (c[:, None].to(points.device) for c in f.intrinsics.unbind(-1))
    widths, heights = f.widths[:, None].to(points.device), f.heights[:, None].to(points.device)
    counts = torch.empty(points.shape[0], dtype=torch.int32, device=points.device)
    for s in range(0, points.shape[0], chunk):
        x = torch.einsum("vij,nj->vni", rot, points[s : s + chunk].float()) + shift[:, None, :]
        z = x[..., 2]
        ahead = z > 1e-6
        z = torch.where(ahead, z, torch.ones_like(z))
        u, v = fx * x[..., 0] / z + cx, fy * x[..., 1] / z + cy
        inside = ahead & (u >= 0) & (u < widths) & (v >= 0) & (v < heights)
        counts[s : s + chunk] = inside.sum(0, dtype=torch.int32)
    return counts


def seen_enough(
    frustums: PooledFrustums,
    min_views: int,
    reso: tuple[int, int, int],
    grid: SparseGrid,
    voxels: torch.Tensor,
) -> torch.Tensor:
    """(K,) whether at least `min_views` frustums hold each of `voxels` (K, 4): (level, x, y, z) of a grid
    of resolution `reso` in `grid`'s boxes."""
    centres = SparseGrid.grid_to_world_of(reso, grid.center, grid.radius, voxels[:, 1:].float(), voxels[:, 0])
    return views_seeing(frustums, centres) >= min_views


def prune_unseen(grid: SparseGrid, frustums: PooledFrustums, min_views: int) -> SparseGrid:
    """`grid` without its voxels that fewer than `min_views` frustums hold."""
    voxels = (grid.links >= 0).nonzero()
    rows = grid.links[tuple(voxels.T)].long()
    keep = torch.zeros(grid.num_voxels, dtype=torch.bool, device=grid.device)
    keep[rows] = seen_enough(frustums, min_views, grid.reso, grid, voxels)
    return grid.prune(keep)
