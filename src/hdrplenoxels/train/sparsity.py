"""svox2's Cauchy sparsity prior on the grid's density, added straight into the gradient as TV is
(docs/method.md, "Training").

svox2 adds `weight * 4 sigma / (1 + 2 sigma^2)`, the gradient of `weight * log(1 + 2 sigma^2)`, for every
sample its rays take. Here it is added once for every voxel whose density the step's rays gave a
gradient: the same voxels, without a pass of its own through the march kernels. It pulls a density that
few photos hold (a floater) towards zero; the photos that see a surface hold it against the pull.
"""

from __future__ import annotations

import torch


def cauchy_sparsity_loss(density: torch.Tensor, seen: torch.Tensor, weight: float) -> torch.Tensor:
    """`weight * sum log(1 + 2 sigma^2)` over the rows `seen` marks: the loss whose gradient
    `cauchy_sparsity_grad_` adds (its oracle)."""
    return weight * (torch.log1p(2.0 * density * density) * seen.to(density.dtype)).sum()


def cauchy_sparsity_grad_(density: torch.Tensor, grad_parts: torch.Tensor, weight: float) -> None:
    """Add the gradient of `cauchy_sparsity_loss` into part 0 of `grad_parts` (parts, rows), over the rows
    to which any part holds a gradient already: call it before anything but the rays adds into them.
    Nothing is read on the host, so a GPU's step never waits here."""
    if weight <= 0.0:
        return
    seen = (grad_parts != 0).any(dim=0).to(density.dtype)
    sigma = density.detach()
    grad_parts[0].add_((4.0 * weight) * sigma / (1.0 + 2.0 * sigma * sigma) * seen)
