"""Total-variation regulariser on the sparse grid, added straight into the gradient (docs/method.md,
"Training").

Plenoxels never puts TV into the loss: after `backward()` it adds the TV gradient of a random contiguous
1% run of dense cells to the density and SH gradients. For cell x, channel m, `D_a = v(x + e_a) - v(x)`
(a = x, y, z) and `u = 1 / sqrt(sum_a D_a^2 + 1e-9)`:

    grad[v(x)]       -= (weight / n) * u * sum_a rho_a D_a
    grad[v(x + e_a)] += (weight / n) * u * rho_a D_a,       rho_a = R_a / reference_reso

With `rho = 1` this is the exact gradient of `(weight / n) * sum sqrt(sum_a D_a^2 + 1e-9)` (`tv_value`);
otherwise the anisotropic factor sits on the numerator only, as in the trained model.

A cascade's levels are regularised each on its own: neighbours never cross from one level to another.

Missing voxels (link < 0): "zero" mode (density) reads them as 0; "self" mode (SH, svox2's `ignore_edge`)
gives a missing neighbour the cell's own value (D = 0) and a missing centre the value 0. Neighbours past
the grid edge count as missing (the CUDA kernel reads data row 0 there: docs/method.md, "Fixes to the
reference code"). Only existing voxels receive gradient.
"""

from __future__ import annotations

import math
from typing import Literal

import torch

MissingMode = Literal["zero", "self"]
TV_EPS = 1e-9


def sample_tv_cells(
    reso: tuple[int, ...],
    fraction: float = 0.01,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """A contiguous, wrapping run of `max(1, floor(fraction * N))` flattened cell indices (z fastest) of
    a grid of shape `reso` (a cascade's: levels first), on `device`.

    The start is uniform over all N cells (svox2 `tv_contiguous = 1`): contiguous runs are cheap to read.
    It is drawn on the generator's device and never read on the host, so that a GPU's step does not wait.
    """
    if fraction < 0:
        raise ValueError(f"TV cell fraction must be >= 0, got {fraction}")
    total = math.prod(int(r) for r in reso)
    n = min(total, max(1, math.floor(fraction * total)))
    on = torch.device("cpu") if generator is None else generator.device
    start = torch.randint(0, total, (1,), generator=generator, device=on).to(device)
    return (start + torch.arange(n, dtype=torch.long, device=device)) % total


@torch.no_grad()
def tv_grad_(
    grid_links: torch.Tensor,
    values: torch.Tensor,
    grad: torch.Tensor,
    weight: float,
    cells: torch.Tensor,
    missing_mode: MissingMode,
    reference_reso: float = 256,
    chunk: int = 1 << 18,
) -> torch.Tensor:
    """Add the TV gradient of `values` (M, C) or (M,) over `cells` into `grad` (same shape) in place.
    The oracle of train/tv_kernel.py.

    `cells` are flattened dense indices (e.g. from `sample_tv_cells`); n = their count. Work is done in
    chunks of `chunk` cells to bound temporary memory on large grids. Returns `grad`.
    """
    if weight == 0 or cells.numel() == 0:
        return grad
    _check_grad_args(values, grad, missing_mode)
    vals = values.detach()
    vals2, grad2 = (vals[:, None], grad[:, None]) if vals.dim() == 1 else (vals, grad)  # views: in place
    cells = _check_cells(grid_links, cells)
    n = cells.numel()
    rho = _rho(grid_links.shape[-3:], reference_reso, vals.dtype, vals.device)
    scale = float(weight) / n
    for start in range(0, n, chunk):
        centre, rows, delta = _tv_terms(grid_links, vals2, cells[start : start + chunk], missing_mode)
        u = scale * torch.rsqrt(delta.square().sum(0) + TV_EPS)  # (k, C)
        to_neighbour = delta.mul_(rho[:, None, None]).mul_(u)  # (3, k, C), reuses delta
        _index_add(grad2, centre, -to_neighbour.sum(0))
        _index_add(grad2, rows.reshape(-1), to_neighbour.reshape(-1, vals2.shape[1]))
    return grad


def tv_value(
    grid_links: torch.Tensor,
    values: torch.Tensor,
    cells: torch.Tensor,
    missing_mode: MissingMode,
    weight: float = 1.0,
    reference_reso: float | None = None,
    eps: float = TV_EPS,
) -> torch.Tensor:
    """`(weight / n) * sum_cells sum_channels sqrt(sum_a (rho_a D_a)^2 + eps)`, differentiable in `values`.

    With the defaults (rho = 1, eps = 1e-9) its gradient is what `tv_grad_` adds for `reference_reso = R`.
    svox2 logs `reference_reso=256, eps=1e-5`.
    """
    vals2 = values[:, None] if values.dim() == 1 else values
    cells = _check_cells(grid_links, cells)
    _, _, delta = _tv_terms(grid_links, vals2, cells, missing_mode)
    if reference_reso is not None:
        delta = (
            delta * _rho(grid_links.shape[-3:], reference_reso, values.dtype, values.device)[:, None, None]
        )
    return float(weight) / cells.numel() * torch.sqrt(delta.square().sum(0) + eps).sum()


# ----------------------------------------------------------------------------- helpers
def rho_values(reso, reference_reso: float) -> list[float]:
    """The anisotropy factors `R_a / reference_reso`, on the host."""
    if reference_reso <= 0:
        raise ValueError(f"reference_reso must be > 0, got {reference_reso}")
    return [int(r) / reference_reso for r in reso]


def _rho(reso, reference_reso: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor(rho_values(reso, reference_reso), dtype=dtype, device=device)


def _check_grad_args(values: torch.Tensor, grad: torch.Tensor, missing_mode: str) -> None:
    """What every TV-gradient implementation (this one, `tv_kernel`) refuses alike."""
    if grad.shape != values.shape:
        raise ValueError(f"grad {tuple(grad.shape)} and values {tuple(values.shape)} must match")
    _check_mode(missing_mode)


def _check_mode(missing_mode: str) -> None:
    if missing_mode not in ("zero", "self"):
        raise ValueError(f"missing_mode must be 'zero' or 'self', got {missing_mode!r}")


def _check_cells(links: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The cells as flat int64 on the links' device, their range checked where that costs no wait: on a
    GPU reading it would stall the step (the kernel skips cells outside the grid instead)."""
    cells = cells.to(device=links.device, dtype=torch.long).reshape(-1)
    if cells.numel() and cells.device.type == "cpu":
        lo, hi = int(cells.min()), int(cells.max())
        if lo < 0 or hi >= links.numel():
            raise ValueError(f"TV cells must lie in [0, {links.numel()}), got [{lo}, {hi}]")
    return cells


def _gather(values: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """values[rows] with 0 where rows < 0 (no gradient flows to missing rows)."""
    picked = values[rows.clamp(min=0)]
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    return torch.where((rows >= 0)[..., None], picked, zero)


def _tv_terms(
    links: torch.Tensor, values: torch.Tensor, cells: torch.Tensor, missing_mode: MissingMode
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centre rows (k,), +x/+y/+z neighbour rows (3, k) (-1 = missing or past the edge of the cell's
    level), D (3, k, C)."""
    _check_mode(missing_mode)
    rx, ry, rz = links.shape[-3:]
    flat = links.reshape(-1)
    coords = ((cells // (ry * rz)) % rx, (cells // rz) % ry, cells % rz)
    centre = flat[cells].long()
    neighbour_rows = []
    for coord, size, stride in zip(coords, (rx, ry, rz), (ry * rz, rz, 1), strict=True):
        inside = coord + 1 < size
        row = flat[torch.where(inside, cells + stride, cells)].long()
        neighbour_rows.append(torch.where(inside, row, -1))
    rows = torch.stack(neighbour_rows)  # (3, k)
    v0 = _gather(values, centre)  # (k, C): a missing centre counts as 0 in both modes
    vn = _gather(values, rows)  # (3, k, C)
    if missing_mode == "self":
        vn = torch.where((rows >= 0)[..., None], vn, v0)
    return centre, rows, vn - v0


def _index_add(grad: torch.Tensor, rows: torch.Tensor, contrib: torch.Tensor) -> None:
    keep = rows >= 0
    grad.index_add_(0, rows[keep], contrib[keep].to(grad.dtype))
