"""The free-space prior: density on the lines of sight from training cameras to the sparse points they
saw is penalised (docs/method.md, "Free space along lines of sight").

A floater that explains a few neighbouring photos costs nothing photometric: those photos agree with
it, and views that would see it through empty space may not exist. A structure-from-motion point seen
by a view says the segment between that camera and the point is empty, whatever the pixels say. The
loss is the mean optical depth of those segments (short of each point by a margin, for the points'
error and the voxels' reach), estimated at random points along them each step; its gradient is a
few thousand trilinear scatters, written here in PyTorch (no kernel: it marches nothing).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.geometry.cameras import pixel_rays
from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.train.view_coverage import pooled_frustums, views_seeing


@dataclass(frozen=True)
class SightSegments:
    """Stretches of lines of sight from training cameras, in the grid's world frame: known to be empty
    (`line_stretches` up to the points, `near_segments`) or to hold a surface (`line_stretches` around
    the points)."""

    starts: torch.Tensor  # (M, 3) the end nearer the observing camera
    ends: torch.Tensor  # (M, 3) the end nearer the point

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    def __add__(self, other: SightSegments) -> SightSegments:
        return SightSegments(torch.cat([self.starts, other.starts]), torch.cat([self.ends, other.ends]))


@dataclass(frozen=True)
class ObservedLines:
    """Lines of sight of the training views to the sparse points they saw, in the grid's frame: the
    one place the dataset's points change frame, for every prior built on them."""

    view: np.ndarray  # (M,) the observing view's index in the scene
    cameras: np.ndarray  # (M, 3) its camera centre
    points: np.ndarray  # (M, 3) the point it saw


def observed_lines(
    lines: SightLines, c2w_world: np.ndarray, world_from_data: np.ndarray, views: list[int]
) -> ObservedLines:
    """The observations made by `views` (the training views: a test view's points would carry its scored
    half's content): `c2w_world` is in the grid's frame, `world_from_data` takes the dataset's points
    there."""
    seen = lines.of_views(views)
    points = lines.points[seen.point] @ world_from_data[:3, :3].T + world_from_data[:3, 3]
    return ObservedLines(seen.view, np.asarray(c2w_world, dtype=np.float64)[seen.view, :3, 3], points)


def line_stretches(
    seen: ObservedLines, start: float, end: float, device: torch.device | str
) -> SightSegments:
    """The stretch of each line of sight between fractions `start` and `end` of the way from its camera
    (0) to its point (1): the free-space prior's runs from 0 to short of 1, the surface prior's across 1."""
    d = seen.points - seen.cameras
    as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    return SightSegments(as_tensor(seen.cameras + start * d), as_tensor(seen.cameras + end * d))


NEAR_PIXELS = 16
"""Each view's near segments go through a NEAR_PIXELS x NEAR_PIXELS grid of its pixels."""


def near_segments(
    seen: ObservedLines,
    c2w_world: np.ndarray,
    intrinsics: np.ndarray,
    sizes: np.ndarray,
    fraction: float,
    device: torch.device | str,
    left_widths: dict[int, int] | None = None,
) -> SightSegments:
    """Segments from each observing view's camera through a grid of its pixels, `fraction` of the way to
    the nearest of the sparse points it saw (the 1st percentile of their distances, against a stray
    point): its nearest surface is taken to be no nearer than its nearest keypoint, which guards the
    space in front of it where no keypoint lies behind (docs/method.md, "Near the cameras"). A view
    without points has none.

    Then the same for the test views whose left halves the paper's protocol trains (`left_widths`: view
    -> pooled columns): through a grid of the left half's pixels, to the nearest training view's point
    inside it. A test view's own keypoints are not read (they carry its scored half), but unguarded, a
    left half that no training photo sees grows a floater in front of its camera that reaches into the
    scored half."""
    c2w = np.asarray(c2w_world, dtype=np.float64)
    reaches, extents = {}, {}
    for v in np.unique(seen.view).tolist():
        reaches[v] = _reach(seen.points[seen.view == v], c2w[v, :3, 3], fraction)
        extents[v] = (int(sizes[v][0]), int(sizes[v][1]))
    points = np.unique(seen.points, axis=0)
    c2w_t, intrinsics_t = torch.as_tensor(c2w), torch.as_tensor(intrinsics)
    for v, width in (left_widths or {}).items():
        half = pooled_frustums(
            c2w_t, intrinsics_t, torch.tensor([v]), torch.tensor([width]), torch.tensor([int(sizes[v][1])])
        )
        inside = views_seeing(half, torch.as_tensor(points)).numpy() > 0
        if inside.any():
            reaches[v] = _reach(points[inside], c2w[v, :3, 3], fraction)
            extents[v] = (width, int(sizes[v][1]))
    return _through_pixels(c2w, intrinsics, extents, reaches, device)


def _reach(points: np.ndarray, centre: np.ndarray, fraction: float) -> float:
    """`fraction` of the distance from `centre` to the nearest of `points` (the 1st percentile)."""
    return fraction * float(np.percentile(np.linalg.norm(points - centre, axis=1), 1.0))


def _through_pixels(
    c2w: np.ndarray,
    intrinsics: np.ndarray,
    extents: dict[int, tuple[int, int]],
    reaches: dict[int, float],
    device: torch.device | str,
) -> SightSegments:
    """For each view `v` of `reaches`, segments `reaches[v]` long from its camera through a NEAR_PIXELS²
    grid of its pixels [0, width) x [0, height) (`extents[v]`)."""
    steps = (np.arange(NEAR_PIXELS) + 0.5) / NEAR_PIXELS
    starts, ends = [], []
    for v, reach in reaches.items():
        centre = c2w[v, :3, 3]
        w, h = extents[v]
        px, py = np.meshgrid(steps * w - 0.5, steps * h - 0.5, indexing="xy")  # pixel_rays adds the 0.5
        n = px.size
        _, d = pixel_rays(
            torch.as_tensor(c2w[v]).expand(n, 4, 4),
            torch.as_tensor(intrinsics[v], dtype=torch.float64).expand(n, 4),
            torch.as_tensor(px.reshape(-1)),
            torch.as_tensor(py.reshape(-1)),
        )
        starts.append(np.broadcast_to(centre, d.shape))
        ends.append(centre + reach * d.numpy())
    as_tensor = lambda parts: torch.as_tensor(  # noqa: E731
        np.concatenate(parts) if parts else np.zeros((0, 3)), dtype=torch.float32, device=device
    )
    return SightSegments(as_tensor(starts), as_tensor(ends))


def sample_levels(grid: SparseGrid, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points `x` (..., 3) in the finest level that holds each: (position in that level's grid,
    level, inside any level). The boxes are those of `kernels/march_reference.ray_segments`."""
    box = tuple(float(v) for v in (*grid.center, *grid.radius))
    scale, offset, mid, half = _level_frame(grid.reso, box[:3], box[3:], x.device)
    p = x * scale + offset
    reach = ((p - mid).abs() / half).amax(-1)  # 1: on level 0's faces, 2^l on level l's
    level = torch.ceil(torch.log2(reach.clamp(min=1.0))).long()
    inside = level < grid.levels
    level = level.clamp(max=grid.levels - 1)
    pos = (p - mid) * torch.pow(0.5, level.to(p.dtype))[..., None] + mid
    return pos, level, inside


@functools.cache
def _level_frame(reso, center, radius, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Level 0's (scale, offset) from the world and its grid's (middle, half extent), on `device`, made
    once per grid: copying them to a GPU every step would make the step wait for it. Kept for good (a few
    bytes per grid): a recorded CUDA graph reads them at their addresses (`train/step_graph.py`)."""
    scale, offset = SparseGrid.world_to_grid_affine_of(reso, center, radius)
    r = torch.tensor(reso, dtype=torch.float32)
    return tuple(t.to(device) for t in (scale, offset, (r - 1.0) / 2.0, r / 2.0))


def segment_points(
    s: torch.Tensor, e: torch.Tensor, u: torch.Tensor, spread: float, generator: torch.Generator
) -> torch.Tensor:
    """Points (N, S, 3) at fractions `u` (N, S, 1) from `s` to `e` (N, 3); with `spread` > 0, each moved
    off its segment, uniformly within a cone of apex `s` whose radius at `e` is `spread` times its
    length: a keypoint stands for the pixels around it, whose rays pass through the same empty space."""
    x = s[:, None, :] + u * (e - s)[:, None, :]
    if spread <= 0.0:
        return x
    d = e - s
    length = d.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    axis = (d / length)[:, None, :]
    on = generator.device  # drawn where the generator lives: a GPU's draws never pass through the host
    r = torch.randn(x.shape, generator=generator, device=on).to(x.device)
    r = torch.nn.functional.normalize(r - (r * axis).sum(-1, keepdim=True) * axis, dim=-1)
    radius = torch.rand((*x.shape[:-1], 1), generator=generator, device=on).to(x.device).sqrt()  # in the disc
    return x + r * radius * u * spread * length[:, None, :]


def draw_segments(
    segments: SightSegments, lines: int, samples: int, generator: torch.Generator, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`lines` random segments' (starts, ends) (N, 3) and `samples` random fractions along each (N, S, 1),
    drawn where `generator` lives: a GPU's draws never pass through the host."""
    on = generator.device
    pick = torch.randint(len(segments), (lines,), generator=generator, device=on).to(device)
    u = torch.rand((lines, samples, 1), generator=generator, device=on).to(device)
    return segments.starts[pick], segments.ends[pick], u


def segment_density(
    grid: SparseGrid, s: torch.Tensor, e: torch.Tensor, x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The grid at points `x` (N, S, 3), S of them standing for each segment `s` -> `e`: (density (N, S),
    0 where a corner is absent; d optical depth / d density per sample (N, S), the world length a sample
    stands for, over 2^level since a level-l voxel's density is 2^l times the world's (docs/method.md,
    "Cascade"); corner rows (N, S, 8); corner weights (N, S, 8), 0 at absent corners)."""
    pos, level, inside = sample_levels(grid, x)
    rows, cw = corner_weights(grid.links, pos, level)
    present = (rows >= 0) & inside[..., None]
    rho = torch.where(present, grid.density.detach()[rows.clamp(min=0)], torch.zeros_like(cw))
    sigma = (cw * rho).sum(-1)
    length = (e - s).norm(dim=-1)[:, None] / x.shape[1]
    per_sample = torch.pow(0.5, level.to(sigma.dtype)) * length
    return sigma, per_sample, rows, cw * present.to(cw.dtype)


def scatter_density_grad_(
    grad_density: torch.Tensor, touched: torch.Tensor | None, rows: torch.Tensor, contrib: torch.Tensor
) -> None:
    """Add each corner's `contrib` (N, S, 8) into `grad_density` at its row, marking the rows in
    `touched` with no boolean index (a host read)."""
    flat = rows.reshape(-1).clamp(min=0)
    contrib = contrib.reshape(-1)
    grad_density.index_add_(0, flat, contrib)
    if touched is not None:
        touched.scatter_reduce_(0, flat, (contrib != 0).to(touched.dtype), "amax")


def free_space_grad_(
    grid: SparseGrid,
    segments: SightSegments,
    weight: float,
    lines: int,
    samples: int,
    generator: torch.Generator,
    grad_density: torch.Tensor,
    touched: torch.Tensor | None = None,
    spread: float = 0.0,
    with_loss: bool = False,
) -> torch.Tensor | None:
    """Add d loss / d density of `weight` x the mean optical depth of `lines` random segments (each at
    `samples` random points, within the cone `spread` gives it) into `grad_density` (rows,), marking the
    rows in `touched`. With `with_loss`, returns the loss (a 0-d tensor on the device; training needs
    only its gradient). Nothing is read on the host, so a GPU's step never waits here."""
    if weight <= 0.0 or len(segments) == 0 or grid.num_voxels == 0:
        return None
    s, e, u = draw_segments(segments, lines, samples, generator, grad_density.device)
    sigma, per_sample, rows, cw = segment_density(grid, s, e, segment_points(s, e, u, spread, generator))
    coeff = (weight / lines) * per_sample * (sigma > 0).to(sigma.dtype)
    scatter_density_grad_(grad_density, touched, rows, coeff[..., None] * cw)
    if with_loss:
        return weight * (sigma.clamp(min=0.0) * per_sample).sum(-1).mean()
    return None
