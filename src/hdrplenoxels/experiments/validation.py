"""Validation renders, for choosing settings without the experiments' test views: the same scenes seen
from other cameras (3/5 as many views, so other positions) and captured with another seed. Every
setting this package picked by measurement was picked here; the experiments only report.

Each variant (tone-mapping settings by name) is scored twice per scene: trained on the -3/0/+3 EV
captures (PSNR on right halves, and truth recovery), and trained on -3 and +3 EV captures only, rendering
0 EV (table-s2's setting, with its sparse-bracket prior unless the variant says).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from hdrplenoxels.experiments.common import (
    PROTOCOL,
    VALIDATION_SEED,
    ExperimentSettings,
    captured,
    check_overrides,
    run_spec,
    scores,
    validation_root,
    validation_views,
)
from hdrplenoxels.experiments.median import (
    DARK_BRIGHT,
    median_ev,
    median_targets,
    score_against,
)
from hdrplenoxels.experiments.report import TRUTH_COLUMNS, report_data, table, write_report
from hdrplenoxels.experiments.table_s1 import by_capture_ev
from hdrplenoxels.tonemap.config import SPARSE_BRACKET
from hdrplenoxels.train.runs import RunSpec, train_spec

DEFAULT_SCENES = ("room", "objects360")
DEFAULTS = "defaults"
COLUMNS = (
    ("psnr", "PSNR", 2),
    *(c for c in TRUTH_COLUMNS if c[0] in ("crf_rmse", "ev_error_stops", "hdr_error_stops")),
    ("minus_static_at_0ev", "ours − static at 0 EV", 2),
    ("median_psnr", "median-exposure PSNR", 2),
)


def parse_variant(text: str) -> dict:
    """'key=value,key=value' -> tone-mapping settings (the keys of the config's `tonemap` section),
    typed by the one override parser (`train.config.parse_overrides`)."""
    if text == DEFAULTS:
        return {}
    typed = check_overrides(f"tonemap.{item}" for item in text.split(","))
    return {key.removeprefix("tonemap."): value for key, value in typed.items()}


def scene_runs(scene: str, out: Path, s: ExperimentSettings) -> dict[str, RunSpec]:
    """Static Plenoxels, then per variant `i` ours on the varying captures (`variant{i}/varying`) and on
    the -3/+3 EV captures (`variant{i}/median`)."""
    root = validation_root(scene, s, out)
    runs = out / "runs" / scene
    dark_bright = captured(root, "dark_bright", "varying", replace(DARK_BRIGHT, seed=VALIDATION_SEED))
    specs = {"static": run_spec(root / "static", runs / "static", s, tonemap=False)}
    for i, variant in enumerate(dict.fromkeys(s.variants or (DEFAULTS,))):
        tone_settings = parse_variant(variant)
        specs[f"variant{i}/varying"] = run_spec(
            root / "varying", runs / f"variant{i}" / "varying", s, tonemap=True, tone_settings=tone_settings
        )
        specs[f"variant{i}/median"] = run_spec(
            dark_bright,
            runs / f"variant{i}" / "median",
            s,
            tonemap=True,
            tone_settings=SPARSE_BRACKET | tone_settings,
        )
    return specs


def plan(out: Path, s: ExperimentSettings) -> list[RunSpec]:
    return [spec for scene in s.scenes or DEFAULT_SCENES for spec in scene_runs(scene, out, s).values()]


def median_psnr(root: Path, s: ExperimentSettings, spec: RunSpec) -> float:
    model, _ = train_spec(spec)
    views = json.loads((spec.data / "camera_truth.json").read_text())["views"]
    _, _, truths = median_targets(root, views, model.test_ids)
    ev = median_ev(model)
    preds = [
        model.to_ldr_controlled(model.render_camera(i, s.backend), ev).cpu().numpy() for i in model.test_ids
    ]
    return score_against(preds, truths, False)["psnr"]


def run(out: Path, s: ExperimentSettings) -> Path:
    scenes = s.scenes or DEFAULT_SCENES
    variants = tuple(dict.fromkeys(s.variants or (DEFAULTS,)))
    protocol = (
        f"Validation renders: {validation_views(s)} views (other camera positions than the experiments' "
        f"{s.n_views}), captured with seed {VALIDATION_SEED}. {PROTOCOL} Per variant: ours trained on the "
        "-3/0/+3 EV captures (PSNR, truth recovery), and ours trained on -3 and +3 EV captures only, "
        "rendering 0 EV (`median_psnr`, with table-s2's settings for ours under the variant). "
        "PSNR follows the exposure of the scored capture (about 6 dB per 3 EV), so compare variants on "
        "`minus_static_at_0ev`: ours minus static Plenoxels on the test views captured at 0 EV."
    )
    data = report_data("validation", protocol, s)
    rows = []
    for scene in scenes:
        root = validation_root(scene, s, out)
        runs = scene_runs(scene, out, s)
        static, static_data = train_spec(runs["static"])
        result = {"plenoxels_static": scores(static, static_data, s), "variants": {}}
        rows.append((f"{scene} / plenoxels_static", result["plenoxels_static"]))
        for i, name in enumerate(variants):
            model, scene_data = train_spec(runs[f"variant{i}/varying"])
            scored = scores(model, scene_data, s, truth=True)
            scored["median_psnr"] = median_psnr(root, s, runs[f"variant{i}/median"])
            by_ev = by_capture_ev(
                root, {"ours_varying": scored, "plenoxels_static": result["plenoxels_static"]}
            )
            scored["by_capture_ev"] = by_ev
            scored["minus_static_at_0ev"] = by_ev["+0"]["difference"] if "+0" in by_ev else None
            result["variants"][name] = scored
            rows.append((f"{scene} / {name}", scored | scored["truth"]))
        data["scenes"][scene] = result
    md = [
        "# Validation: settings compared on renders the experiments never score",
        "",
        protocol,
        "",
        table(rows, COLUMNS, first="scene / variant"),
        "",
    ]
    return write_report(out, data, "\n".join(md))
