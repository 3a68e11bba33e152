"""The check that decides whether training holds the learned exposures to the stated ones
(`ToneMapConfig.exposure_hold`, docs/method.md, "Gauge").

Exact stated exposures (a bracket on a tripod) are worth holding: without it the exposures and the curve
share a bend the photos hardly tell apart. A phone's or a compact's EXIF is not exact: held to it, the
field pays. The pixels tell the two apart early in training: where the learned EVs already follow the
stated ones closely, the statement is taken as exact and held from then on.
"""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.tone_setup import departure


def check_step(t: ToneMapConfig, n_iters: int) -> int | None:
    """The step after which "checked" decides (at least the first), None where nothing is checked."""
    if t.exposure_hold != "checked" or t.lambda_exposure_ratios == 0:
        return None
    return max(1, round(t.exposure_check_at * n_iters))


def check_exposures(tm: ToneMapper, t: ToneMapConfig, stated: np.ndarray | None, step: int) -> str:
    """Hold `tm`'s exposures to `stated` (stops; None: the photos state none that vary) from now on where
    they are within `t.exposure_hold_within` of them; the line saying what was decided."""
    if stated is None:
        return ""
    try:
        off = departure(tm, stated)
    except ValueError as e:
        return f"exposures not held to the stated ones: at step {step} {e}"
    if off > t.exposure_hold_within:
        return (
            f"exposures not held to the stated ones: at step {step} the learned EVs are {off:.2f} stop RMS "
            f"from them (held within {t.exposure_hold_within:g})"
        )
    tm.set_stated_exposures(torch.as_tensor(stated))
    return (
        f"exposures held to the stated ones from step {step}: the learned EVs were {off:.2f} stop RMS "
        f"from them (held within {t.exposure_hold_within:g})"
    )
