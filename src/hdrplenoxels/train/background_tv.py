"""The MSI background's regulariser and optimiser settings, ready for the trainer (docs/method.md,
"Background").

Background texels are seen by few rays each and at grazing sphere crossings, so without a smoothness
prior the MSI fits every training pixel with floaters in its layers. For texel x and each axis a of
(layer, row, column), D_a = v(x + e_a) - v(x), the column wrapping around (the azimuth is periodic) and
the last layer and row having no forward neighbour along their axis (D = 0),

    TV = mean_x sqrt(sum_a D_a^2 + eps),   summed over channels,

the mean over every texel or over a step's sampled run of texels, as the grid's TV samples its cells.
`msi_tv` is the loss (autograd, the oracle); training adds its gradient in closed form
(`msi_tv_grad_`), since through autograd it was a large share of a `balanced` step
(JOURNAL.md, "The preset ladder"); over every texel on CUDA, one kernel
(`kernels/msi_tv_kernel.py`).

weighted separately for density and colour (svox2's `lambda_tv_background_sigma` / `_color`). The
sparsity prior is Plenoxels' Cauchy loss on density, `mean_x log(1 + 2 sigma_x^2)`: it keeps layers the
views do not need empty, so the constant background is not hidden behind haze.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.kernels.dispatch import use_kernel
from hdrplenoxels.kernels.msi_tv_kernel import msi_tv_grad_dense_
from hdrplenoxels.kernels.msi_tv_reference import msi_tv_grad_reference_
from hdrplenoxels.kernels.tv import TV_EPS


@dataclass(frozen=True)
class BackgroundTraining:
    """Learning rates and TV weights of the MSI, separate from the grid's (svox2's defaults)."""

    lr_sigma: float = 3.0
    lr_color: float = 0.1
    lambda_tv_sigma: float = 1e-2
    lambda_tv_color: float = 1e-2
    lambda_sparsity: float = 0.0  # off, as in svox2's defaults
    tv_sparsity: float = 1.0  # fraction of texels in each step's TV run (1: every texel)


def _tv(values: torch.Tensor) -> torch.Tensor:
    """`values` (L, H, W, C): the mean over texels of the TV term above, summed over channels."""
    d_layer = torch.zeros_like(values)
    d_layer[:-1] = values[1:] - values[:-1]
    d_row = torch.zeros_like(values)
    d_row[:, :-1] = values[:, 1:] - values[:, :-1]
    d_col = torch.roll(values, shifts=-1, dims=2) - values
    return torch.sqrt(d_layer**2 + d_row**2 + d_col**2 + TV_EPS).mean((0, 1, 2)).sum()


def _forward_neighbours(shape: tuple[int, ...], texels: torch.Tensor) -> list[torch.Tensor]:
    """Flattened indices of each texel's next layer, row and column; a texel with no forward neighbour
    along an axis is its own neighbour there (D = 0), and the column wraps."""
    layers, height, width = shape[:3]
    layer, row, col = texels // (height * width), (texels // width) % height, texels % width
    return [
        torch.where(layer < layers - 1, texels + height * width, texels),
        torch.where(row < height - 1, texels + width, texels),
        texels - col + (col + 1) % width,
    ]


def _tv_at(values: torch.Tensor, texels: torch.Tensor) -> torch.Tensor:
    """The same term as `_tv`, its mean over `texels` only (flattened (layer, row, column) indices)."""
    flat = values.reshape(-1, values.shape[-1])
    centre = flat[texels]
    squares = sum((flat[n] - centre) ** 2 for n in _forward_neighbours(values.shape, texels))
    return torch.sqrt(squares + TV_EPS).mean(0).sum()


@torch.no_grad()
def msi_tv_grad_(
    values: torch.Tensor, grad: torch.Tensor, weight: float, texels: torch.Tensor | None = None
) -> None:
    """Add `weight` times the gradient of the TV term (over every texel, or over `texels`) into `grad` in
    place (both (L, H, W, C), `grad` contiguous), in closed form: with u = 1 / sqrt(sum_a D_a^2 + eps) per
    texel and channel, the neighbour along a gets + (weight / n) u D_a and the texel itself
    - (weight / n) u sum_a D_a. About four times as fast as autograd through `msi_tv`, which is its
    oracle in the tests."""
    if weight == 0:
        return
    if texels is None:
        dense = msi_tv_grad_dense_ if use_kernel(values) else msi_tv_grad_reference_
        dense(values, grad, weight)
    elif texels.numel() > 0:
        _sampled_tv_grad_(values, grad, weight, texels)


def _sampled_tv_grad_(values: torch.Tensor, grad: torch.Tensor, weight: float, texels: torch.Tensor) -> None:
    """Only the sampled texels and their neighbours are touched, with no dense temporary (autograd
    through the gathers would allocate one per gather)."""
    channels = values.shape[-1]
    flat, flat_grad = values.reshape(-1, channels), grad.view(-1, channels)
    neighbours = _forward_neighbours(values.shape, texels)
    centre = flat[texels]
    deltas = [flat[n] - centre for n in neighbours]
    u = (weight / texels.numel()) * torch.rsqrt(sum(d * d for d in deltas) + TV_EPS)
    for n, d in zip(neighbours, deltas):
        to_neighbour = d.mul_(u)
        flat_grad.index_add_(0, n, to_neighbour)
        flat_grad.index_add_(0, texels, -to_neighbour)


def msi_tv(
    bg: MSIBackground, weights: BackgroundTraining = BackgroundTraining(), texels: torch.Tensor | None = None
) -> torch.Tensor:
    """The weighted TV loss of the MSI's density and colour, differentiable w.r.t. both: the mean over
    every texel, or over `texels` (flattened indices into (L, H, W)) when given."""
    if texels is None:
        tv_density, tv_color = _tv(bg.density[..., None]), _tv(bg.color)
    else:
        tv_density, tv_color = _tv_at(bg.density[..., None], texels), _tv_at(bg.color, texels)
    return weights.lambda_tv_sigma * tv_density + weights.lambda_tv_color * tv_color


def msi_sparsity(bg: MSIBackground, weights: BackgroundTraining = BackgroundTraining()) -> torch.Tensor:
    """The weighted Cauchy sparsity loss of the MSI's density (of the raw values: the ReLU's zero
    region already renders as empty)."""
    return weights.lambda_sparsity * torch.log1p(2.0 * bg.density**2).mean()


def msi_param_groups(bg: MSIBackground, settings: BackgroundTraining = BackgroundTraining()) -> list[dict]:
    """torch.optim parameter groups for the MSI with its own learning rates (the tensors must be leaves
    with requires_grad set)."""
    return [
        {"params": [bg.density], "lr": settings.lr_sigma, "name": "background_density"},
        {"params": [bg.color], "lr": settings.lr_color, "name": "background_color"},
    ]
