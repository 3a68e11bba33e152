"""The surface prior: the line of sight from a training camera to a sparse point it saw ends there, so the
short stretch of it around the point must be opaque (docs/method.md, "Surfaces at the sparse points").

The free-space prior empties each line up to its point; nothing in it says the line stops. Where the
photos leave a surface ambiguous (a glossy floor, a dark textureless mat) the grid may leave a hole at
the point and paint what the pixel saw further back, which other views then see as fog behind the
surface. The loss is a hinge on each window's optical depth: nothing once the window is opaque to
`target`, else its shortfall, estimated at random points each step and scattered in PyTorch like the
free-space prior's (`train/free_space.py`), whose sampling it shares.
"""

from __future__ import annotations

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.train.free_space import (
    SightSegments,
    draw_segments,
    scatter_density_grad_,
    segment_density,
    segment_points,
)


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
    s, e, u = draw_segments(windows, lines, samples, generator, grad_density.device)
    sigma, per_sample, rows, cw = segment_density(grid, s, e, segment_points(s, e, u, 0.0, generator))
    tau = (sigma.clamp(min=0.0) * per_sample).sum(-1)
    coeff = -(weight / lines) * per_sample * (tau < target).to(tau.dtype)[:, None]
    scatter_density_grad_(grad_density, touched, rows, coeff[..., None] * cw)
    if with_loss:
        return weight * (target - tau).clamp(min=0.0).mean()
    return None
