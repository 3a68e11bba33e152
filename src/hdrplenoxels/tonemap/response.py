"""Camera response curves: piecewise-linear per channel on 256 segments of a (possibly warped) knot axis.

The same lookup serves training (each ray through its own image's curve) and user controls (one learned
curve applied to any render); docs/method.md, "Tone mapping".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

CRF_SEGMENTS = 256
WARP_EPS = 1e-6  # keeps the knot-coordinate warp's slope finite at 0


def piecewise_linear(x: torch.Tensor, curves: torch.Tensor, curve_ids: torch.Tensor) -> torch.Tensor:
    """Evaluate element-wise curves: element j of `x` (in [0, 1]) through row `curve_ids[j]` of `curves`
    (M, K+1), knots at K equal segments of [0, 1].

    Two `index_select`s on the flattened table fetch each element's bracketing knots: O(elements), not
    O(elements x knots) as gathering whole curves per ray would be, and deterministic in backward.
    """
    k = curves.shape[-1] - 1
    pos = x.clamp(0.0, 1.0) * k
    idx = pos.floor().clamp(max=k - 1).long()
    frac = pos - idx
    flat_idx = (curve_ids * (k + 1) + idx).reshape(-1)
    table = curves.reshape(-1)
    lo = table.index_select(0, flat_idx).reshape(x.shape)
    hi = table.index_select(0, flat_idx + 1).reshape(x.shape)
    return lo + frac * (hi - lo)


def knot_coordinate(x: torch.Tensor, power: float) -> torch.Tensor:
    """Irradiance in [0, 1] -> position on the knot axis in [0, 1] (identity for even spacing)."""
    x = x.clamp(0.0, 1.0)
    if power == 1.0:
        return x
    lo, hi = WARP_EPS**power, (1.0 + WARP_EPS) ** power
    return ((x + WARP_EPS) ** power - lo) / (hi - lo)


def knot_positions(n_knots: int, power: float) -> np.ndarray:
    """The irradiance of every knot (inverse of `knot_coordinate` at k / (n_knots - 1))."""
    u = np.linspace(0.0, 1.0, n_knots)
    if power == 1.0:
        return u
    lo, hi = WARP_EPS**power, (1.0 + WARP_EPS) ** power
    x = np.clip((u * (hi - lo) + lo) ** (1.0 / power) - WARP_EPS, 0.0, 1.0)
    x[0], x[-1] = 0.0, 1.0  # exact ends (rounding leaves ~1e-22)
    return x


@dataclass
class ResponseCurve:
    """One camera response per channel: knot values (3, K+1) on the knot axis of `power`, taking
    irradiance^exponent (the model's gauge) when called with linear irradiance."""

    knots: torch.Tensor
    power: float = 1.0
    exponent: float = 1.0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., 3) linear irradiance -> pixel values (..., 3), clipped to [0, 1]."""
        flat = x.reshape(-1, 3).clamp(min=0.0) ** self.exponent
        ids = torch.arange(3, device=flat.device).expand_as(flat)
        y = piecewise_linear(knot_coordinate(flat, self.power), self.knots.to(flat), ids)
        return y.reshape(x.shape).clamp(0.0, 1.0)


def controlled_ldr(radiance: torch.Tensor, log_gains: torch.Tensor, curve: ResponseCurve) -> torch.Tensor:
    """Linear radiance (..., 3) through gains exp(log_gains) (3,) and one response, clipped to [0, 1]."""
    return curve(radiance * torch.exp(log_gains))
