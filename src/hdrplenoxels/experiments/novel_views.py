"""Views no photo was taken from: each scene captured with a phone's auto exposure and white balance
(`synth --camera auto`), trained twice with tone mapping: with the paper's right-half protocol, and with
`--holdout full` (test views never seen), whose test views are then scored through the tone controller's
camera, the mean learned tone, colour-corrected, and their true tone (docs/method.md, "Tone
controller")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.eval.controller_truth import truth_scores, truth_stops
from hdrplenoxels.eval.evaluate import PROTOCOLS, TONES, evaluate
from hdrplenoxels.experiments.common import ExperimentSettings, captured, run_spec, strip, truth_root
from hdrplenoxels.experiments.report import report_data, table, write_report
from hdrplenoxels.synth.generate import AUTO_VARIANT
from hdrplenoxels.synth.pipeline import PipelineConfig
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.runs import RunSpec, train_spec

DEFAULT_SCENES = ("room", "courtyard")
HOLDOUTS = ("right-half", "full")
NOVEL_TONES = ("auto", "mean", "cc")


def scene_runs(scene: str, out: Path, s: ExperimentSettings) -> dict[str, RunSpec]:
    """Ours on the scene's auto-exposure capture, once per holdout."""
    folder = captured(truth_root(scene, s, out), AUTO_VARIANT, AUTO_VARIANT, PipelineConfig())
    specs = {}
    for holdout in HOLDOUTS:
        spec = run_spec(folder, out / "runs" / scene / f"ours_{holdout}", s, True)
        spec.config.holdout = holdout
        specs[holdout] = spec
    return specs


def plan(out: Path, s: ExperimentSettings) -> list[RunSpec]:
    return [spec for scene in s.scenes or DEFAULT_SCENES for spec in scene_runs(scene, out, s).values()]


def run(out: Path, s: ExperimentSettings) -> Path:
    scenes = s.scenes or DEFAULT_SCENES
    protocol = (
        f"Right half: {PROTOCOLS['right-half']}, each through its own learned tone. Full holdout: "
        f"{PROTOCOLS['full']}; tones: auto, {TONES['auto']}; mean, {TONES['mean']}; cc, "
        f"{TONES['cc']}; true, the view's simulated camera settings brought into the model's gauge (slope "
        "and per-channel offset fitted on training views only). Exposure error: RMS over test views, stops; "
        "white balance: the largest per-channel gain-ratio error, averaged over test views."
    )
    data = report_data("novel-views", protocol, s)
    rows = []
    md = ["# Novel views: the tone a view would have had", "", protocol, ""]
    for scene in scenes:
        runs = scene_runs(scene, out, s)
        half_model, half_scene = train_spec(runs["right-half"])
        full_model, full_scene = train_spec(runs["full"])
        result = {"right_half": evaluate(half_model, half_scene, s.backend, lpips=False)["psnr"]}
        for tone in NOVEL_TONES:
            result[tone] = evaluate(full_model, full_scene, s.backend, lpips=False, tone=tone)["psnr"]
        truth = truth_scores(full_model, truth_stops(full_model), s.backend)
        result |= {"true": truth["true_psnr"], "controller": full_model.controller.form, "truth": truth}
        data["scenes"][scene] = result
        rows.append(
            (
                scene,
                {
                    "half": result["right_half"],
                    **{c: result[c] for c in (*NOVEL_TONES, "true")},
                    "e_auto": truth["auto_exposure_rms_stops"],
                    "e_mean": truth["mean_exposure_rms_stops"],
                    "wb_auto": truth["auto_wb_ratio_error"],
                },
            )
        )
        fig = out / "images" / f"{scene}_novel.png"
        write_png(fig, strip(first_test_view(full_model, full_scene, s.backend)))
        md += [f"![{scene}: photo, auto tone, mean tone]({fig.relative_to(out)})", ""]
    md += [
        "Figure: an unseen test view's photo, then its render through the controller's tone and through "
        "the mean tone.",
        "",
        table(
            rows,
            (
                ("half", "right halves", 2),
                ("auto", "full: auto", 2),
                ("mean", "full: mean", 2),
                ("cc", "full: cc", 2),
                ("true", "full: true tone", 2),
                ("e_auto", "EV error auto", 3),
                ("e_mean", "EV error mean", 3),
                ("wb_auto", "WB error auto", 3),
            ),
            first="scene",
        ),
    ]
    return write_report(out, data, "\n".join(md))


def first_test_view(model: Model, scene: SceneData, backend: str) -> list[np.ndarray]:
    """The first test view: its photo, then its render through the auto and through the mean tone."""
    i = model.test_ids[0]
    radiance = model.render_camera(i, backend)
    photo = scene.images[i].astype(np.float32) / 255.0
    auto = model.to_ldr_controlled(radiance, tone=model.auto_tone()).cpu().numpy()
    mean = model.to_ldr_controlled(radiance).cpu().numpy()
    return [photo, auto, mean]
