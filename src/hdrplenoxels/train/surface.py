"""The surface prior: the line of sight from a training camera to a sparse point it saw ends there, so the
short stretch of it around the point must be opaque (docs/method.md, "Surfaces at the sparse points").

The free-space prior empties each line up to its point; nothing in it says the line stops. Where the
photos leave a surface ambiguous (a glossy floor, a dark textureless mat) the grid may leave a hole at
the point and paint what the pixel saw further back, which other views then see as fog behind the
surface. The loss is a hinge on each window's optical depth: nothing once the window is opaque to
`target`, else its shortfall, estimated at random points each step and scattered in PyTorch like the
free-space prior's (`train/free_space.py`).
"""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.train.free_space import SightSegments, sample_levels


def surface_windows(
    lines: SightLines,
    c2w_world: np.ndarray,
    world_from_data: np.ndarray,
    views: list[int],
    margin: float,
    behind: float,
    device: torch.device | str,
) -> SightSegments:
    """For each observation by `views` (the training views), the stretch of its line of sight from
    `margin` of the point's distance in front of it (where the free-space prior stops) to `behind` of it
    past the point."""
    seen = lines.of_views(views)
    points = lines.points[seen.point] @ world_from_data[:3, :3].T + world_from_data[:3, 3]
    cameras = np.asarray(c2w_world, dtype=np.float64)[seen.view, :3, 3]
    starts = points - margin * (points - cameras)
    ends = points + behind * (points - cameras)
    as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    return SightSegments(as_tensor(starts), as_tensor(ends))


def surface_optical_depth(
    grid: SparseGrid, windows: SightSegments, pick: torch.Tensor, u: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The Monte Carlo optical depth of the windows `pick` at fractions `u` (N, S, 1): (optical depth (N,),
    d optical depth / d stored density per sample (N, S), corner rows (N, S, 8), corner weights masked to
    the voxels present (N, S, 8))."""
    s, e = windows.starts[pick], windows.ends[pick]
    x = s[:, None, :] + u * (e - s)[:, None, :]
    pos, level, inside = sample_levels(grid, x)
    rows, cw = corner_weights(grid.links, pos, level)
    present = ((rows >= 0) & inside[..., None]).to(cw.dtype)
    rho = grid.density.detach()[rows.clamp(min=0)] * present
    sigma = (cw * rho).sum(-1)
    per_sample = torch.pow(0.5, level.to(sigma.dtype)) * (e - s).norm(dim=-1)[:, None] / u.shape[1]
    tau = (sigma.clamp(min=0.0) * per_sample).sum(-1)
    return tau, per_sample, rows, cw * present


def surface_grad_(
    grid: SparseGrid,
    windows: SightSegments,
    weight: float,
    target: float,
    lines: int,
    samples: int,
    generator: torch.Generator,
    grad_density: torch.Tensor,
    touched: torch.Tensor | None = None,
    with_loss: bool = False,
) -> torch.Tensor | None:
    """Add d loss / d density of `weight` x the mean of max(`target` - optical depth, 0) over `lines`
    random windows (each at `samples` random points) into `grad_density` (rows,), marking the rows in
    `touched`. A window short of `target` pulls every sample's density up, a negative one too (the
    render clamps it at 0, which would leave a hole with no gradient to fill it). Nothing is read on the
    host, so a GPU's step never waits here."""
    if weight <= 0.0 or len(windows) == 0 or grid.num_voxels == 0:
        return None
    device, on = grad_density.device, generator.device
    pick = torch.randint(len(windows), (lines,), generator=generator, device=on).to(device)
    u = torch.rand((lines, samples, 1), generator=generator, device=on).to(device)
    tau, per_sample, rows, cw = surface_optical_depth(grid, windows, pick, u)
    short = (tau < target).to(tau.dtype)
    coeff = -(weight / lines) * per_sample * short[:, None]
    contrib = (coeff[..., None] * cw).reshape(-1)
    flat = rows.reshape(-1).clamp(min=0)
    grad_density.index_add_(0, flat, contrib)
    if touched is not None:  # marks the rows given a gradient, with no boolean index (a host read)
        touched.scatter_reduce_(0, flat, (contrib != 0).to(touched.dtype), "amax")
    if with_loss:
        return weight * (target - tau).clamp(min=0.0).mean()
    return None
