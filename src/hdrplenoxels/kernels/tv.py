"""Total-variation regulariser on the sparse grid, added straight into the gradient (docs/method.md,
"Training").

Plenoxels never puts TV into the loss: after `backward()` it adds the TV gradient of a random contiguous
1% run of dense cells to the density and SH gradients. For cell x, channel m, `D_a = v(x + e_a) - v(x)`
(a = x, y, z) and `u = 1 / sqrt(sum_a D_a^2 + 1e-9)`:

    grad[v(x)]       -= (weight / n) * u * sum_a rho_a D_a
    grad[v(x + e_a)] += (weight / n) * u * rho_a D_a,       rho_a = R_a / reference_reso

With `rho = 1` this is the exact gradient of `(weight / n) * sum sqrt(sum_a D_a^2 + 1e-9)`
(`tv_reference.tv_value`); otherwise the anisotropic factor sits on the numerator only, as in the trained
model.

A cascade's levels are regularised each on its own: neighbours never cross from one level to another.

Missing voxels (link < 0): "zero" mode (density) reads them as 0; "self" mode (SH, svox2's `ignore_edge`)
gives a missing neighbour the cell's own value (D = 0) and a missing centre the value 0. Neighbours past
the grid edge count as missing (the CUDA kernel reads data row 0 there: docs/method.md, "Fixes to the
reference code"). Only existing voxels receive gradient.

This module holds what the grid's kernel (`kernels/tv_kernel.py`, `tv_grad_`) and its oracle
(`kernels/tv_reference.py`, `tv_grad_reference_`) share, and the MSI's (`kernels/msi_tv_kernel.py` and its
oracle) take their epsilon from: the cells a step regularises, the anisotropy factors, the argument
checks, and the one argument structure both take (`TVTerm`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

MissingMode = Literal["zero", "self"]
TV_EPS = 1e-9


@dataclass(frozen=True)
class TVTerm:
    """One TV term of a step, as `tv_kernel.tv_grad_` and its oracle `tv_reference.tv_grad_reference_` both
    take it: the grid's links, the values (density (M,) or SH (M, C)), the term's weight, the sampled
    cells, how a missing neighbour counts, and the resolution that normalises anisotropy."""

    links: torch.Tensor
    values: torch.Tensor
    weight: float
    cells: torch.Tensor
    missing: MissingMode
    reference_reso: float = 256


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


# ----------------------------------------------------------------------------- shared
def rho_values(reso, reference_reso: float) -> list[float]:
    """The anisotropy factors `R_a / reference_reso`, on the host."""
    if reference_reso <= 0:
        raise ValueError(f"reference_reso must be > 0, got {reference_reso}")
    return [int(r) / reference_reso for r in reso]


def check_grad_args(values: torch.Tensor, grad: torch.Tensor, missing_mode: str) -> None:
    """What every TV-gradient implementation (the kernel and its oracle) refuses alike."""
    if grad.shape != values.shape:
        raise ValueError(f"grad {tuple(grad.shape)} and values {tuple(values.shape)} must match")
    check_mode(missing_mode)


def check_mode(missing_mode: str) -> None:
    if missing_mode not in ("zero", "self"):
        raise ValueError(f"missing_mode must be 'zero' or 'self', got {missing_mode!r}")


def check_cells(links: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The cells as flat int64 on the links' device, their range checked where that costs no wait: on a
    GPU reading it would stall the step (the kernel skips cells outside the grid instead)."""
    cells = cells.to(device=links.device, dtype=torch.long).reshape(-1)
    if cells.numel() and cells.device.type == "cpu":
        lo, hi = int(cells.min()), int(cells.max())
        if lo < 0 or hi >= links.numel():
            raise ValueError(f"TV cells must lie in [0, {links.numel()}), got [{lo}, {hi}]")
    return cells
