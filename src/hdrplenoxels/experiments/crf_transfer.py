"""CRF transfer (Supp. C.2): train on the same scene captured with two responses (gamma 3 and filmic),
then render each model's radiance through the other model's learned curve, and score it against the
truth captured with that other response."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from hdrplenoxels.data.image_io import read_exr, write_png
from hdrplenoxels.experiments.common import (
    PROTOCOL,
    ExperimentSettings,
    captured,
    right_half,
    right_half_metrics,
    run_spec,
    strip,
    truth_root,
    view_ldr,
)
from hdrplenoxels.experiments.report import report_data, table, write_report
from hdrplenoxels.synth.pipeline import CameraSettings, PipelineConfig, capture
from hdrplenoxels.tonemap.response import controlled_ldr
from hdrplenoxels.train.runs import RunSpec, train_spec

DEFAULT_SCENES = ("objects360",)
RESPONSES = ("gamma3", "filmic")
MODES = (("self_calibrated", False), ("known_exposure", True))


def transferred(src, dst, i: int, backend: str) -> np.ndarray:
    """View `i` of `src`: its radiance and white balance, through `dst`'s response curve for that view."""
    radiance = src.hdr(src.render_camera(i, backend))
    log_gains = src.tonemapper.linear_log_wb()[i]
    return controlled_ldr(radiance, log_gains, dst.tonemapper.curve(i)).cpu().numpy()


def truth_with_response(folder: Path, i: int, crf: str) -> np.ndarray:
    """View `i` captured with the settings recorded in `folder` except for the response (no noise)."""
    view = json.loads((folder / "camera_truth.json").read_text())["views"][i]
    settings = CameraSettings(view["ev"], tuple(view["wb_gains"]), crf, tuple(view["vignetting"]))
    return capture(read_exr(folder / view["hdr"]), settings).astype(np.float32) / 255.0


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    return right_half_metrics(pred, gt)["psnr"]


def scene_runs(scene: str, out: Path, s: ExperimentSettings) -> dict[tuple[str, str], RunSpec]:
    """A run per (mode, response), each on the scene captured with that response alone."""
    root = truth_root(scene, s, out)
    folders = {crf: captured(root, crf, "varying", PipelineConfig(crfs=(crf,))) for crf in RESPONSES}
    return {
        (mode, crf): run_spec(folders[crf], out / "runs" / scene / f"{mode}_{crf}", s, True, pinned)
        for mode, pinned in MODES
        for crf in RESPONSES
    }


def plan(out: Path, s: ExperimentSettings) -> list[RunSpec]:
    return [spec for scene in s.scenes or DEFAULT_SCENES for spec in scene_runs(scene, out, s).values()]


def run(out: Path, s: ExperimentSettings) -> Path:
    scenes = s.scenes or DEFAULT_SCENES
    protocol = (
        PROTOCOL + " Transfer: model A's radiance and its learned white balance for a test view go "
        "through model B's learned response; the truth is the same view captured with A's exposure "
        "and white balance and B's true response. Self-calibrated models each carry their own "
        "exponent a, so a transferred curve only fits if both found the same a; known exposures "
        "pin a = 1 for both."
    )
    data = report_data("crf-transfer", protocol, s)
    md = ["# CRF transfer between responses (gamma 3 vs filmic)", "", protocol, ""]
    rows = []
    for scene in scenes:
        runs = scene_runs(scene, out, s)
        folders = {crf: runs[MODES[0][0], crf].data for crf in RESPONSES}
        data["scenes"][scene] = {}
        for mode, _ in MODES:
            models = {crf: train_spec(runs[mode, crf])[0] for crf in RESPONSES}
            res = {}
            for a, b in (RESPONSES, RESPONSES[::-1]):
                src, dst = models[a], models[b]
                own, swap, figs = [], [], []
                for i in src.test_ids:
                    own_img = view_ldr(src, i, s.backend)
                    own_gt = truth_with_response(folders[a], i, a)
                    swap_img = transferred(src, dst, i, s.backend)
                    swap_gt = truth_with_response(folders[a], i, b)
                    own.append(psnr(own_img, own_gt))
                    swap.append(psnr(swap_img, swap_gt))
                    figs.append([own_gt, own_img, swap_gt, swap_img])
                exps = [float(m.tonemapper.linear_log_wb().mean(1).std() / math.log(2)) for m in (src, dst)]
                res[f"{a}_to_{b}"] = {
                    "psnr_own": float(np.mean(own)),
                    "psnr_transferred": float(np.mean(swap)),
                    "exposure_spread_stops": exps,
                }
                rows.append(
                    (f"{scene} / {mode} / {a} → {b}", {"psnr": np.mean(own), "psnr_t": np.mean(swap)})
                )
                fig = out / "images" / f"{scene}_{mode}_{a}_to_{b}.png"
                write_png(fig, strip([right_half(x) for x in figs[min(1, len(figs) - 1)]]))
                md += [f"![{a} to {b}]({fig.relative_to(out)})", ""]
            data["scenes"][scene][mode] = res
    md += [
        "Figure columns: truth with A's response, A's render, truth with B's response, A's radiance "
        "through B's learned curve (right halves).",
        "",
        table(
            rows,
            (("psnr", "PSNR own curve", 2), ("psnr_t", "PSNR transferred curve", 2)),
            first="scene / mode / A → B",
        ),
    ]
    return write_report(out, data, "\n".join(md))
