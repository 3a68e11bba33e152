"""The TV gradient in PyTorch: the readable oracle of kernels/tv_kernel.py (the math: `kernels/tv.py`), and
the torch engine's TV."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.tv import (
    TV_EPS,
    MissingMode,
    TVTerm,
    check_cells,
    check_grad_args,
    check_mode,
    rho_values,
)


@torch.no_grad()
def tv_grad_reference_(term: TVTerm, grad: torch.Tensor, chunk: int = 1 << 18) -> torch.Tensor:
    """Add `term`'s TV gradient of its values (M, C) or (M,) over its cells into `grad` (same shape) in
    place. The oracle of kernels/tv_kernel.py.

    The cells are flattened dense indices (e.g. from `sample_tv_cells`); n = their count. Work is done in
    chunks of `chunk` cells to bound temporary memory on large grids. Returns `grad`.
    """
    grid_links, missing_mode = term.links, term.missing
    if term.weight == 0 or term.cells.numel() == 0:
        return grad
    check_grad_args(term.values, grad, missing_mode)
    vals = term.values.detach()
    vals2, grad2 = (vals[:, None], grad[:, None]) if vals.dim() == 1 else (vals, grad)  # views: in place
    cells = check_cells(grid_links, term.cells)
    n = cells.numel()
    rho = _rho(grid_links.shape[-3:], term.reference_reso, vals.dtype, vals.device)
    scale = float(term.weight) / n
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

    With the defaults (rho = 1, eps = 1e-9) its gradient is what `tv_grad_reference_` adds for
    `reference_reso = R`. svox2 logs `reference_reso=256, eps=1e-5`.
    """
    vals2 = values[:, None] if values.dim() == 1 else values
    cells = check_cells(grid_links, cells)
    _, _, delta = _tv_terms(grid_links, vals2, cells, missing_mode)
    if reference_reso is not None:
        delta = (
            delta * _rho(grid_links.shape[-3:], reference_reso, values.dtype, values.device)[:, None, None]
        )
    return float(weight) / cells.numel() * torch.sqrt(delta.square().sum(0) + eps).sum()


def _rho(reso, reference_reso: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor(rho_values(reso, reference_reso), dtype=dtype, device=device)


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
    check_mode(missing_mode)
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
