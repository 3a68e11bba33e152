"""The paper's experiments (and the demo), one command each: `hdrplenoxels experiment NAME OUT`.

Every experiment writes OUT/report.md, OUT/report.json and OUT/images/, states its protocol, and keeps
its rendered truth (OUT/data, or a shared --data folder) and its runs (OUT/runs): running it again
reuses finished runs whose configuration is unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from hdrplenoxels.experiments import (
    crf_transfer,
    demo,
    nerf_tonemap,
    novel_views,
    robustness,
    table_s1,
    table_s2,
    truth_recovery,
    validation,
)
from hdrplenoxels.experiments.common import ExperimentSettings

EXPERIMENTS: dict[str, tuple[str, Callable[[Path, ExperimentSettings], Path]]] = {
    "table-s1": (
        "Plenoxels static / varying and NeRF-A vs ours on every synthetic scene (+ truth recovery)",
        table_s1.run,
    ),
    "table-s2": (
        "Median exposure (0 EV) from -3/+3 EV views: ours, Plenoxels, NeRF-A, NeRF + tone module",
        table_s2.run,
    ),
    "nerf-tonemap": (
        "Fig. S8: NeRF static / varying vs NeRF + tone module (varying) on every synthetic scene",
        nerf_tonemap.run,
    ),
    "truth-recovery": (
        "HDR, EV and CRF error vs the simulation: self-calibrated vs known EV",
        truth_recovery.run,
    ),
    "novel-views": (
        "Auto-exposure captures: right halves vs unseen views through the predicted, mean, true tone",
        novel_views.run,
    ),
    "robustness": ("Exposure ranges +-3..+-6 EV and shot noise", robustness.run),
    "crf-transfer": ("Swap learned responses between gamma-3 and filmic captures", crf_transfer.run),
    "validation": (
        "Compare tone settings (--variant) on renders from other cameras and seed; never test views",
        validation.run,
    ),
    "demo": ("The built-in scene: ours vs baselines, EV sweep, tone plots, EXR", demo.run),
}

__all__ = ["EXPERIMENTS", "ExperimentSettings"]
