"""Fits of the exponent a that relates the learned radiance to linear radiance (learned = linear^a).

Self-calibration leaves a free (docs/method.md, "Gauge"): these pick it after training, either from known
exposures or from a prior on what a camera response looks like. Pure functions of the learned parameters,
so that `ToneMapper` only stores the result.
"""

from __future__ import annotations

import math

import torch

from hdrplenoxels.tonemap.response import ResponseCurve


def response_prior_exponent(knots: list[torch.Tensor], power: float, gamma: float) -> float:
    """The exponent e whose responses f(X^e) over linear X in [0, 1] are closest to X^(1 / gamma), summed
    over the curves `knots` (each (3, K+1) on the knot axis of `power`), from 401 candidates in [0.05, 5]."""
    x = torch.linspace(0.0, 1.0, 257, dtype=torch.float64)[:, None].expand(-1, 3)
    target = x ** (1.0 / gamma)
    candidates = torch.logspace(math.log10(0.05), math.log10(5.0), 401, dtype=torch.float64)
    learned = x[None] ** candidates[:, None, None]  # (candidates, 257, 3): X^e for every candidate
    errors = torch.zeros(len(candidates), dtype=torch.float64)
    for k in knots:
        curve = ResponseCurve(k.double(), power)  # takes learned radiance as it is
        errors += ((curve(learned.to(curve.knots.device)).cpu() - target) ** 2).mean((1, 2))
    return float(candidates[int(errors.argmin())])


def known_exposure_exponent(learned_log_level: torch.Tensor, known_log_exposure: torch.Tensor) -> float:
    """The least-squares slope of learned vs known per-view log exposure (N,) each.

    Raises ValueError where the known exposures cannot fix it (all equal) or the learned ones do not
    follow them (slope not above 0.05)."""
    level = learned_log_level.double()
    known = known_log_exposure.double()
    kc = known - known.mean()
    if float((kc * kc).sum()) < 1e-12:
        raise ValueError("the known exposures are all equal: they cannot fix the exponent")
    a = float((kc * (level - level.mean())).sum() / (kc * kc).sum())
    if not a > 0.05:
        raise ValueError(f"learned exposures do not follow the known ones (fitted exponent {a:.3g})")
    return a


def stops_departure(learned_log_level: torch.Tensor, stated_stops: torch.Tensor) -> float:
    """Root mean square in stops of the learned per-view exposures (log levels, N) about the stated ones
    (stops, N), both relative to their means, once the exponent is fitted to them
    (`known_exposure_exponent`, whose ValueError it passes on): how far the pixels put each photo's
    exposure from what was said of it."""
    known = stated_stops.double().cpu() * math.log(2.0)
    level = learned_log_level.double().cpu()
    a = known_exposure_exponent(level, known)
    off = (level - level.mean()) / a - (known - known.mean())
    return float(off.pow(2).mean().sqrt()) / math.log(2.0)
