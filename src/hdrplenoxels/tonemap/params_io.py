"""The tone_params.json format: a `ToneMapper`'s learned tones as plain lists, and back.

The file is in the output (linear) gauge, so that it can be read, plotted and hand-edited without knowing
the gauge the grid was trained in; `ToneMapper.from_parameters_dict` rebuilds a mapper from it, which is how
learned tones are applied to other renders and runs (`render --crf-run`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.response import CRF_SEGMENTS, knot_positions

if TYPE_CHECKING:
    from hdrplenoxels.tonemap.module import ToneMapper


def parameters_dict(tm: ToneMapper) -> dict:
    """Learned parameters as plain lists (for JSON): EV and gains per image, curves per group."""
    with torch.no_grad():
        wb = torch.exp(tm.linear_log_wb()).cpu()
        return {
            "reference": int(tm.reference),
            "crf_sharing": tm.cfg.crf_sharing,
            "knot_power": tm.cfg.knot_power,
            "known_exposure": tm.cfg.known_exposure,
            "exponent": float(tm.exponent),
            "white_balance": wb.tolist(),
            "log2_gain": torch.log2(wb).tolist(),
            "crf_group": tm.crf_group.cpu().tolist(),
            "crf_knots": tm.knots().cpu().tolist(),
            # In output (linear) units, where the white balance above is too.
            "crf_knot_irradiance": (
                knot_positions(CRF_SEGMENTS + 1, tm.cfg.knot_power) ** (1.0 / float(tm.exponent))
            ).tolist(),
            "vignetting": tm.vignetting.detach().cpu().tolist() if tm.cfg.vignetting else None,
            "image_size": tm.sizes.cpu().int().tolist(),
        }


@dataclass
class ToneParams:
    """A checked tone_params.json: what `ToneMapper` needs to be built and loaded from it."""

    cfg: ToneMapConfig
    image_size: np.ndarray  # (N, 2): W, H (zeros where the file has none)
    reference: int
    state: dict[str, torch.Tensor]  # for `ToneMapper.load_state_arrays`, in the learned gauge


def parse_parameters(params: dict) -> ToneParams:
    """Check a tone_params.json dict (from `parameters_dict`, or edited by hand). Raises ValueError
    naming what is missing or malformed."""
    try:
        wb = torch.as_tensor(params["white_balance"], dtype=torch.float32)
        knots = torch.as_tensor(params["crf_knots"], dtype=torch.float32)
        groups = torch.as_tensor(params["crf_group"], dtype=torch.long)
        exponent, reference = float(params["exponent"]), int(params["reference"])
        vignetting = params.get("vignetting")
        if vignetting is not None:
            vignetting = torch.as_tensor(vignetting, dtype=torch.float32)
        cfg = ToneMapConfig(
            enabled=True,
            crf_sharing=params["crf_sharing"],
            knot_power=float(params.get("knot_power", 1.0)),
            known_exposure=bool(params.get("known_exposure", False)),
            vignetting=vignetting is not None,
        )
        sizes = params.get("image_size")
        sizes = None if sizes is None else np.asarray(sizes, dtype=np.float32)
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"not a tone_params.json: {type(e).__name__} {e}") from None
    n = len(wb) if wb.ndim == 2 else -1
    if wb.shape != (n, 3) or not bool((wb > 0).all()) or not exponent > 0:
        raise ValueError("white_balance must be positive (views, 3) gains and exponent positive")
    if knots.ndim != 3 or knots.shape[1:] != (3, CRF_SEGMENTS + 1):
        raise ValueError(f"crf_knots must be (curves, 3, {CRF_SEGMENTS + 1})")
    if groups.shape != (n,) or not 0 <= int(groups.min()) <= int(groups.max()) < len(knots):
        raise ValueError("crf_group must name one of the curves for every view")
    if not 0 <= reference < n:
        raise ValueError(f"reference {reference} is not a view (0..{n - 1})")
    if not (math.isfinite(cfg.knot_power) and cfg.knot_power > 0):
        raise ValueError(f"knot_power must be a positive number, got {cfg.knot_power}")
    if sizes is None or sizes.size == 0:
        sizes = np.zeros((n, 2), dtype=np.float32)
    if sizes.shape != (n, 2) or not np.isfinite(sizes).all():
        raise ValueError(f"image_size must be (views, 2) = ({n}, 2) sizes, got shape {sizes.shape}")
    state = {
        "crf_group": groups,
        "crf_interior": knots[:, :, 1:-1].contiguous(),
        "exponent": torch.tensor(exponent),
        "log_wb": torch.log(wb) * exponent,  # the file holds the linear (output) gauge
    }
    if vignetting is not None:
        if vignetting.shape != (n, 4):
            raise ValueError(f"vignetting must be (views, 4) = ({n}, 4), got {tuple(vignetting.shape)}")
        state["vignetting"] = vignetting
    return ToneParams(cfg, sizes, reference, state)
