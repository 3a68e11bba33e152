"""The MSI background's regulariser and optimiser settings, ready for the trainer (docs/method.md,
"Background").

Background texels are seen by few rays each and at grazing sphere crossings, so without a smoothness
prior the MSI fits every training pixel with floaters in its layers. TV here is a plain autograd loss
(the MSI is small next to the grid, so no sampled-cell gradient kernel is needed): for texel x and each
axis a of (layer, row, column), D_a = v(x + e_a) - v(x), the column wrapping around (the azimuth is
periodic) and the last layer and row having no forward neighbour along their axis (D = 0),

    TV = mean_x sqrt(sum_a D_a^2 + eps),   summed over channels,

weighted separately for density and colour (svox2's `lambda_tv_background_sigma` / `_color`). The
sparsity prior is Plenoxels' Cauchy loss on density, `mean_x log(1 + 2 sigma_x^2)`: it keeps layers the
views do not need empty, so the constant background is not hidden behind haze.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.grid.background import MSIBackground

TV_EPS = 1e-9


@dataclass(frozen=True)
class BackgroundTraining:
    """Learning rates and TV weights of the MSI, separate from the grid's (svox2's defaults)."""

    lr_density: float = 3.0
    lr_color: float = 0.1
    lambda_tv_density: float = 1e-2
    lambda_tv_color: float = 1e-2
    lambda_sparsity: float = 0.0  # off, as in svox2's defaults


def _tv(values: torch.Tensor) -> torch.Tensor:
    """`values` (L, H, W, C): the mean over texels of the TV term above, summed over channels."""
    d_layer = torch.zeros_like(values)
    d_layer[:-1] = values[1:] - values[:-1]
    d_row = torch.zeros_like(values)
    d_row[:, :-1] = values[:, 1:] - values[:, :-1]
    d_col = torch.roll(values, shifts=-1, dims=2) - values
    return torch.sqrt(d_layer**2 + d_row**2 + d_col**2 + TV_EPS).mean((0, 1, 2)).sum()


def msi_tv(bg: MSIBackground, weights: BackgroundTraining = BackgroundTraining()) -> torch.Tensor:
    """The weighted TV loss of the MSI's density and colour, differentiable w.r.t. both."""
    return weights.lambda_tv_density * _tv(bg.density[..., None]) + weights.lambda_tv_color * _tv(bg.color)


def msi_sparsity(bg: MSIBackground, weights: BackgroundTraining = BackgroundTraining()) -> torch.Tensor:
    """The weighted Cauchy sparsity loss of the MSI's density (of the raw values: the ReLU's zero
    region already renders as empty)."""
    return weights.lambda_sparsity * torch.log1p(2.0 * bg.density**2).mean()


def msi_param_groups(bg: MSIBackground, settings: BackgroundTraining = BackgroundTraining()) -> list[dict]:
    """torch.optim parameter groups for the MSI with its own learning rates (the tensors must be leaves
    with requires_grad set)."""
    return [
        {"params": [bg.density], "lr": settings.lr_density, "name": "background_density"},
        {"params": [bg.color], "lr": settings.lr_color, "name": "background_color"},
    ]
