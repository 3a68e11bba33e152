"""Writing an experiment's report: `report.md` (tables and figures), `report.json` (every number)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from hdrplenoxels.core.atomic import atomic_write_text

if TYPE_CHECKING:
    from hdrplenoxels.experiments.common import ExperimentSettings

METRIC_COLUMNS = (
    ("psnr", "PSNR", 2),
    ("ssim", "SSIM", 4),
    ("lpips_vgg", "LPIPS-VGG", 4),
    ("lpips_alex", "LPIPS-Alex", 4),
)
TONE_COLUMNS = (
    ("own", "own tone (the protocol)", 2),
    ("auto", "predicted (auto)", 2),
    ("mean", "mean tone", 2),
    ("cc", "colour-corrected", 2),
)
TONE_NOTE = (
    "PSNR of the same scored pixels through each tone (`eval --tone`): its own learned tone (the "
    "protocol's), the one the tone controller predicts from the render, the mean learned tone, and the "
    "mean tone colour-corrected to the photo by an affine fit (the metric of Zip-NeRF / BilaRF / PPISP "
    "tables). The last three are what a view no photo was taken from would get; a bracket's random "
    "exposures cannot be predicted, so on bracketed captures auto and mean sit far below own."
)
TRUTH_COLUMNS = (
    ("exponent_a", "a", 3),
    ("crf_rmse", "CRF RMSE", 4),
    ("ev_error_stops", "EV err (stops)", 3),
    ("wb_error_stops", "WB err (stops)", 3),
    ("hdr_error_stops", "HDR err (stops)", 3),
    ("hdr_error_median_stops", "HDR err median", 3),
    ("hdr_error_interior_stops", "HDR err off edges", 3),
    ("hdr_error_brightest_stops", "HDR err brightest 1 %", 3),
    ("hdr_psnr_mu", "HDR PSNR-mu", 2),
)


def _cell(value, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def tone_section(rows: list[tuple[str, dict]], first: str) -> list[str]:
    """The report's lines on the tones a new view would get: heading, `TONE_NOTE`, a table of
    `rows` (label, a result's `tones`)."""
    return [
        "### Through the tones a new view would get",
        "",
        TONE_NOTE,
        "",
        table(rows, TONE_COLUMNS, first),
        "",
    ]


def table(rows: list[tuple[str, dict]], columns=METRIC_COLUMNS, first: str = "") -> str:
    """A Markdown table: one row per (label, values); only columns some row has."""
    cols = [c for c in columns if any(c[0] in v for _, v in rows)]
    lines = [f"| {first} | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for label, values in rows:
        lines.append(f"| {label} | " + " | ".join(_cell(values.get(k), d) for k, _, d in cols) + " |")
    return "\n".join(lines)


def target_line(name: str, value: float, target: str, met: bool) -> str:
    return f"- {name}: **{value:.3f}** (target {target}) — {'met' if met else 'MISSED'}"


def report_data(
    experiment: str, protocol: str, settings: ExperimentSettings, truth_protocol: str | None = None
) -> dict:
    """The start of a report's JSON: what ran, under which protocol (and, where it scores against the
    camera truth, that protocol) and settings, its scenes to come."""
    truth = {} if truth_protocol is None else {"truth_protocol": truth_protocol}
    return {
        "experiment": experiment,
        "protocol": protocol,
        **truth,
        "settings": settings.to_dict(),
        "scenes": {},
    }


def write_report(out: Path, data: dict, markdown: str) -> Path:
    """Both files atomically; `data` must hold `experiment` and `protocol`."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.json", json.dumps(data, indent=1))
    atomic_write_text(out / "report.md", markdown.rstrip() + "\n")
    return out / "report.md"
