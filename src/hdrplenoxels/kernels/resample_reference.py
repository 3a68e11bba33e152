"""Trilinear sampling of a grid's rows in PyTorch: the readable oracle of kernels/resample_kernel.py (the
resample's sampler of the kept voxels)."""

from __future__ import annotations

import torch

from hdrplenoxels.grid.sparse_grid import corner_weights


def trilinear_rows_reference(links: torch.Tensor, data: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """Trilinearly interpolate rows of `data` (M, C) at grid points `pos` (..., 3) -> (..., C); a missing
    corner (link -1) counts as 0. The oracle of kernels/resample_kernel.py."""
    rows, weights = corner_weights(links, pos)
    values = data[rows.clamp(min=0)] * (rows >= 0)[..., None].to(data.dtype)  # (..., 8, C)
    return (weights[..., None] * values).sum(-2)
