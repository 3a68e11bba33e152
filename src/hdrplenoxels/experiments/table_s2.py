"""Table S2 analogue: models trained only on darker (-3 EV) and brighter (+3 EV) views render the median
exposure (0 EV, the views' mean white balance), scored against the true 0 EV captures: ours, Plenoxels,
NeRF-A (embeddings interpolated with a weight chosen on validation captures) and NeRF + tone module."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.eval.truth import RadianceAlignment, SynthTruth, align_radiance
from hdrplenoxels.experiments.common import (
    PAPER_SCENES,
    PROTOCOL,
    ExperimentSettings,
    Method,
    captured,
    method_spec,
    right_half,
    strip,
    truth_root,
    view_ldr,
)
from hdrplenoxels.experiments.median import (
    DARK_BRIGHT,
    WEIGHTS,
    median_camera,
    median_ev,
    median_targets,
    nerf_a_median,
    score_against,
    validated_weight,
    validation_spec,
)
from hdrplenoxels.experiments.report import report_data, table, target_line, write_report
from hdrplenoxels.synth.pipeline import CameraSettings, capture
from hdrplenoxels.tonemap.config import SPARSE_BRACKET
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.runs import RunSpec, train_spec

TARGET_DB = 33.0
# ours >= NeRF-A + this (the paper's margin is larger: JOURNAL.md, "NeRF engine")
NERF_A_MARGIN_DB = 5.0
CEILING = "plenoxels_at_median_camera"
BLACK_CODE = 2  # 8-bit codes at or below this count as background, not as recorded scene
CAPTURES = "dark_bright"  # the captures' folder under the scene's truth
VALIDATION_RUN = "nerf_a_validation"  # chooses NeRF-A's interpolation weight on validation captures
METHODS = (  # trained on the -3/+3 EV captures; the tone-mapped ones with the sparse-bracket settings
    Method("ours_median", "varying", True),
    Method("plenoxels_median", "varying", False),
    Method("nerf_a_median", "varying", False, "nerf", True),
    Method("nerf_tone_median", "varying", True, "nerf"),
)
# Plenoxels on every view captured with the very median camera that is scored (no exposure to infer).
CEILING_METHOD = Method(CEILING, "median_camera", False)
ROWS = (
    *(m.key for m in METHODS),
    CEILING,
    "ours_tone_on_true_radiance",
    "true_tone_on_ours_radiance",
)


def swapped_renders(
    model: Model,
    alignment: RadianceAlignment,
    rendered: torch.Tensor,
    true: np.ndarray,
    camera: CameraSettings,
    ev: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the median render's error comes from: (our learned median tone on the true radiance,
    the true median camera settings on our radiance `rendered`), each radiance moved into the other's gauge by
    the exponent and per-channel gain that truth recovery fits on training views."""
    true_in_our_gauge = alignment.to_learned(true.astype(np.float64))
    as_rendered = model.tonemapper.learned_radiance(torch.as_tensor(true_in_our_gauge, dtype=torch.float32))
    ours_tone = model.to_ldr_controlled(as_rendered, ev).cpu().numpy()
    ours_in_true_gauge = alignment.to_true(model.hdr(rendered).cpu().numpy())
    true_tone = capture(ours_in_true_gauge.astype(np.float32), camera) / 255.0
    return ours_tone, true_tone.astype(np.float32)


def unclipped_fraction(images: list[np.ndarray]) -> float:
    """Of the pixels that are not black (background), the fraction no channel of which is clipped: how
    much of the scene an exposure group records at all."""
    lit = np.concatenate([np.asarray(x).max(-1).ravel() > BLACK_CODE for x in images])
    open_ = np.concatenate([np.asarray(x).max(-1).ravel() < 255 for x in images])
    return float((lit & open_).sum() / max(int(lit.sum()), 1))


def protocol_text() -> str:
    return (
        PROTOCOL + " Training views are captured at -3 or +3 EV only (white balance x1.25 on one "
        "channel per view); ours (grid + tone module) and NeRF + tone module render the median exposure at "
        "the midpoint of the darker and brighter groups' learned exposures with the mean learned white "
        "balance and the learned response; NeRF-A (NeRF-W's per-image appearance embeddings, no "
        "transients) renders it with the embedding interpolated between the darker and the brighter "
        "training views' mean embeddings (groups by each training capture's exposure), at the weight "
        f"(of {', '.join(f'{w:g}' for w in WEIGHTS)}) with the best PSNR on validation captures: a NeRF-A "
        "trained on renders of the same scene from other cameras, captured with another seed, scored on "
        "its own test views' right halves; never on these test views. All are scored against the true "
        "0 EV captures of the test views (right halves) with all views' geometric-mean white balance. "
        "Two exposures 6 stops apart leave the response between them to a prior (any wiggle of the curve "
        "periodic in log irradiance with that ratio as its period fits the images equally well), so the "
        "tone module trains with the response's log-log smoothness prior at "
        f"{SPARSE_BRACKET['lambda_crf_loglog']:g} (default: off) "
        "and with near-black and near-white pixels down-weighted in the loss (saturation weighting, "
        "default: off; here most samples are black or clipped codes), both chosen for ours on validation "
        "renders (other cameras, other capture seed), never on these test views, and kept unchanged for "
        "NeRF + tone module. "
        f"`{CEILING}` is Plenoxels trained on every view captured with the very median camera that "
        "is scored: what this grid and schedule reach when no exposure has to be inferred, a ceiling "
        "for the grid. "
        "`bright_unclipped` is the fraction of non-black pixels of the +3 EV training captures "
        "with no clipped channel: where it is small the bright exposure, and so the median between, is "
        "barely recorded."
    )


def median_preds(model: Model, m: Method, data: Path, s: ExperimentSettings, weight: float) -> list:
    """A method's test views at the median exposure (its own rule, see the protocol)."""
    if m.appearance:
        return nerf_a_median(model, data, weight, s.backend)
    if m.tonemap:
        ev = median_ev(model)
        return [
            model.to_ldr_controlled(model.render_camera(i, s.backend), ev).cpu().numpy()
            for i in model.test_ids
        ]
    return [view_ldr(model, i, s.backend) for i in model.test_ids]


def scene_runs(scene: str, out: Path, s: ExperimentSettings) -> dict[str, RunSpec]:
    """Every method's run on one scene (on the -3/+3 EV captures; the ceiling on captures at the median
    camera), plus the NeRF-A run on validation captures that chooses NeRF-A's weight."""
    root = truth_root(scene, s, out)
    train_data = captured(root, CAPTURES, "varying", DARK_BRIGHT)
    views = json.loads((train_data / "camera_truth.json").read_text())["views"]
    median_cameras = [median_camera(views, i) for i in range(len(views))]
    captured(root, CAPTURES, CEILING_METHOD.variant, DARK_BRIGHT, median_cameras.__getitem__)
    runs = out / "runs" / scene
    specs = {
        m.key: method_spec(train_data.parent, runs, s, m, SPARSE_BRACKET if m.tonemap else None)
        for m in (*METHODS, CEILING_METHOD)
    }
    return specs | {VALIDATION_RUN: validation_spec(scene, s, out)}


def plan(out: Path, s: ExperimentSettings) -> list[RunSpec]:
    return [spec for scene in s.scenes or PAPER_SCENES for spec in scene_runs(scene, out, s).values()]


def run_scene(scene: str, out: Path, s: ExperimentSettings) -> tuple[dict, Path]:
    """Train and score every method on one scene; writes its figure."""
    root = truth_root(scene, s, out)
    specs = scene_runs(scene, out, s)
    train_data = specs["ours_median"].data
    views = json.loads((train_data / "camera_truth.json").read_text())["views"]
    weight, weight_psnr = validated_weight(scene, s, out)
    models = {m.key: train_spec(specs[m.key]) for m in (*METHODS, CEILING_METHOD)}
    ours, scene_data = models["ours_median"]
    radiances, cameras, truths = median_targets(root, views, ours.test_ids)
    preds = {
        m.key: median_preds(models[m.key][0], m, train_data, s, weight) for m in (*METHODS, CEILING_METHOD)
    }
    result = {key: score_against(p, truths, s.lpips) for key, p in preds.items()}
    ev = median_ev(ours)
    result["ours_median"]["median_ev_relative"] = ev
    result["nerf_tone_median"]["median_ev_relative"] = median_ev(models["nerf_tone_median"][0])
    renders = [ours.render_camera(i, s.backend) for i in ours.test_ids]
    synth = SynthTruth.load(train_data)
    alignment = align_radiance(ours, synth, s.backend)
    swaps = [swapped_renders(ours, alignment, r, t, c, ev) for r, t, c in zip(renders, radiances, cameras)]
    result["ours_tone_on_true_radiance"] = score_against([c for c, _ in swaps], truths, False)
    result["true_tone_on_ours_radiance"] = score_against([r for _, r in swaps], truths, False)
    result["bright_unclipped"] = unclipped_fraction(
        [scene_data.images[i] for i in ours.train_ids if synth.evs[i] > 0]
    )
    result["nerf_a_weight"] = {"chosen": weight, "validation_psnr": weight_psnr}
    k = min(1, len(ours.test_ids) - 1)
    capture_k = np.asarray(scene_data.images[ours.test_ids[k]], dtype=np.float32) / 255.0
    columns = [capture_k, truths[k], *(preds[m.key][k] for m in METHODS)]
    figure = out / "images" / f"{scene}_median.png"
    write_png(figure, strip([right_half(x) for x in columns]))
    return result, figure


def run(out: Path, s: ExperimentSettings) -> Path:
    scenes = s.scenes or PAPER_SCENES
    protocol = protocol_text()
    data = report_data("table-s2", protocol, s)
    md = [
        "# Table S2 analogue: median-exposure reconstruction from darker and brighter views",
        "",
        protocol,
        "",
    ]
    for scene in scenes:
        data["scenes"][scene], fig = run_scene(scene, out, s)
        md += [f"![{scene}]({fig.relative_to(out)})", ""]
    rows = [(f"{sc} / {key}", r[key]) for sc, r in data["scenes"].items() for key in ROWS]
    md += [
        "Figure columns: the training capture of the view (−3 or +3 EV), true 0 EV, ours at the median "
        "exposure, Plenoxels (no tone mapping), NeRF-A (validated interpolation weight), NeRF + tone module.",
        "",
        "Where the error comes from (synthetic truth only): `ours_tone_on_true_radiance` puts the true "
        "radiance through our learned median tone, `true_tone_on_ours_radiance` puts our radiance "
        "through the true median camera, each moved into the other's gauge by the exponent `a` and the "
        "per-channel gain that truth recovery fits on training views.",
        "",
        table(rows, first="scene / method"),
        "",
        "Non-black pixels of the +3 EV training captures with no clipped channel: "
        + ", ".join(f"{sc} {r['bright_unclipped']:.1%}" for sc, r in data["scenes"].items())
        + ".",
        "",
        "### NeRF-A's interpolation weight, chosen on validation captures",
        "",
        "| scene | chosen | " + " | ".join(f"{w:g}" for w in WEIGHTS) + " |",
        "|---" * (len(WEIGHTS) + 2) + "|",
        *(
            f"| {sc} | {r['nerf_a_weight']['chosen']:g} | "
            + " | ".join(f"{r['nerf_a_weight']['validation_psnr'][f'{w:g}']:.2f}" for w in WEIGHTS)
            + " |"
            for sc, r in data["scenes"].items()
        ),
        "",
        "(validation PSNR in dB on the right halves of the validation captures' test views at 0 EV)",
        "",
    ]
    worst = min(r["ours_median"]["psnr"] for r in data["scenes"].values())
    margin = float(
        np.mean([r["ours_median"]["psnr"] - r["nerf_a_median"]["psnr"] for r in data["scenes"].values()])
    )
    data["targets"] = {
        "min_psnr": worst,
        "met": worst >= TARGET_DB,
        "ours_minus_nerf_a_mean_db": margin,
        "met_nerf_a": margin >= NERF_A_MARGIN_DB,
    }
    md += [
        "## Targets",
        "",
        target_line("ours, lowest PSNR over scenes (dB)", worst, f"≥ {TARGET_DB}", worst >= TARGET_DB),
        *(
            target_line(
                f"ours, {sc} (dB)",
                r["ours_median"]["psnr"],
                f"≥ {TARGET_DB}",
                r["ours_median"]["psnr"] >= TARGET_DB,
            )
            for sc, r in data["scenes"].items()
        ),
        target_line(
            "ours − NeRF-A, mean over scenes (dB)",
            margin,
            f"≥ +{NERF_A_MARGIN_DB}",
            margin >= NERF_A_MARGIN_DB,
        ),
        *(
            f"- {sc}: ceiling {r[CEILING]['psnr']:.2f} dB "
            f"({'at or above' if r[CEILING]['psnr'] >= TARGET_DB else 'below'} the target): ours is "
            f"{r[CEILING]['psnr'] - r['ours_median']['psnr']:.2f} dB under it"
            for sc, r in data["scenes"].items()
        ),
    ]
    return write_report(out, data, "\n".join(md))
