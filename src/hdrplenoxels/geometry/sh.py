"""Real spherical-harmonics basis up to degree 2, with the svox2 constants and ordering.

The same constants are used by the Warp kernel (kernels/march_funcs.py); keep both in sync.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)

VALID_BASIS_DIMS = (1, 4, 9)


def basis_dim_for_degree(degree: int) -> int:
    if degree not in (0, 1, 2):
        raise ValueError(f"SH degree must be 0, 1 or 2, got {degree}")
    return (degree + 1) ** 2


def eval_sh_basis(dirs: torch.Tensor, basis_dim: int) -> torch.Tensor:
    """Basis values Y_j(d) for unit directions `dirs` (..., 3) -> (..., basis_dim)."""
    if basis_dim not in VALID_BASIS_DIMS:
        raise ValueError(f"basis_dim must be one of {VALID_BASIS_DIMS}, got {basis_dim}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if basis_dim >= 4:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if basis_dim >= 9:
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * z * z - x * x - y * y),
            SH_C2[3] * x * z,
            SH_C2[4] * (x * x - y * y),
        ]
    return torch.stack(out, dim=-1)
