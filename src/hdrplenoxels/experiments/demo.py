"""The built-in demo (`make demo`): HDR-Plenoxels on the small varying-camera scene, with the baselines,
truth recovery, and the pictures a new user wants to see: a whole test view as photographed, by ours and
by the baselines, labelled, its calibrating left half marked; the same view at -2/0/+2 EV, an orbit
flythrough sweeping the exposure, the learned tones, a linear HDR EXR, and each run's wall time."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrplenoxels.data.image_io import read_image, write_exr, write_png
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.eval.truth import SynthTruth
from hdrplenoxels.eval.video import generated_frames, ramp, render_video
from hdrplenoxels.experiments.common import (
    PROTOCOL,
    TRUTH_PROTOCOL,
    ExperimentSettings,
    display_factor,
    enlarged,
    labelled,
    mark_left_half,
    right_half,
    stack,
    strip,
    view_ldr,
)
from hdrplenoxels.experiments.report import (
    METRIC_COLUMNS,
    TRUTH_COLUMNS,
    report_data,
    table,
    tone_section,
    write_report,
)
from hdrplenoxels.experiments.table_s1 import METHODS, run_scene, scene_runs
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.run_end import TONE_PARAMS_FILE, TONE_PLOT_FILE
from hdrplenoxels.train.runs import RunSpec, train_seconds

SCENE = "demo"
EV_SWEEP = (-2.0, 0.0, 2.0)
FLYTHROUGH_FRAMES, FLYTHROUGH_SIZE, FLYTHROUGH_FPS = 48, (128, 128), 24.0
DISPLAY_LONG_SIDE = 256  # the report's pictures are at least this large on their long side


def plan(out: Path, s: ExperimentSettings) -> list[RunSpec]:
    return list(scene_runs(SCENE, out, s).values())


@dataclass
class Pictures:
    """The demo's files for one test view, and how many times each scored pixel is repeated a side."""

    halves: Path
    ev_sweep: Path
    exr: Path
    video: Path
    repeat: int
    large_size: tuple[int, int]


def pictures(
    ours: Model, scene: SceneData, view: int, comparison: Path, images: Path, backend: str
) -> Pictures:
    """Test view `view`'s pictures: its right half against the truth, an EV sweep, its radiance as EXR, an
    orbit sweeping the exposure; and the methods' `comparison` figure enlarged in place. The EV sweep is
    rendered at display size from the field itself; the scored pictures (the truth has no more pixels)
    have their pixels repeated."""
    radiance = ours.render_camera(view, backend)
    w, h = ours.cameras.size(view)
    k = display_factor((w, h), DISPLAY_LONG_SIDE)
    large_size = (w * k, h * k)
    large_k = ours.cameras.intrinsics_at(view, large_size)
    large = ours.render_view(
        ours.cameras.c2w[view], large_k, large_size, backend, ours.default_appearance(view)
    )
    exr = write_exr(images / "test_view_radiance.exr", ours.hdr(radiance).cpu().numpy())
    truth = np.asarray(scene.images[view], dtype=np.float32) / 255.0
    pred = ours.to_ldr(radiance, view).cpu().numpy()
    halves = strip([enlarged(right_half(im), k) for im in (truth, pred)])
    halves = write_png(images / "right_half_vs_truth.png", halves)
    sweep = [ours.to_ldr_controlled(large, ev).cpu().numpy() for ev in EV_SWEEP]
    ev_png = write_png(images / "ev_sweep.png", strip(sweep))
    write_png(comparison, enlarged(read_image(comparison), k))
    evs = ramp(EV_SWEEP[0], EV_SWEEP[-1], FLYTHROUGH_FRAMES)
    frames = generated_frames(ours, "orbit", FLYTHROUGH_FRAMES, FLYTHROUGH_SIZE, evs)
    video = render_video(
        ours, frames, FLYTHROUGH_SIZE, images / "flythrough.mp4", FLYTHROUGH_FPS, backend, progress=False
    )
    return Pictures(halves, ev_png, exr, video, k, large_size)


def view_psnr(result: dict, key: str, view: int) -> float:
    return next(v["psnr"] for v in result[key]["views"] if v["index"] == view)


def test_view_figure(
    models: dict[str, tuple[Model, SceneData]], result: dict, view: int, path: Path, backend: str
) -> Path:
    """The whole test view: the photo of each capture and each method's picture of it, labelled with what
    it is, the photo's EV and the right half's PSNR; on the pictures, the left half that trained the
    view's tone is faded and cut off by a dashed line."""
    rows = []
    for variant, keys in (
        ("varying", ("ours_varying", "plenoxels_varying")),
        ("static", ("plenoxels_static",)),
    ):
        model, data = models[keys[0]]
        k = display_factor(model.cameras.size(view), DISPLAY_LONG_SIDE)
        truth = SynthTruth.load(data.source)
        ev = f", EV {truth.evs[view]:+g}" if truth is not None else ""
        photo = np.asarray(data.images[view], dtype=np.float32) / 255.0
        camera = "varying camera" if variant == "varying" else "one fixed camera"
        panels = [labelled(enlarged(photo, k), f"photo ({camera}{ev})")]
        for key in keys:
            name = "ours" if key.startswith("ours") else "Plenoxels"
            picture = mark_left_half(enlarged(view_ldr(models[key][0], view, backend), k), k)
            panels.append(labelled(picture, f"{name}: {view_psnr(result, key, view):.1f} dB right half"))
        rows.append(strip(panels, gap=4))
    return write_png(path, stack(rows, gap=4))


def ev_scale(run_dir: Path, truth: dict) -> str:
    """Which stops the sweep steps in: the run's own line (true stops where the photos' EXIF exposures or
    known exposures fixed the gauge, else the learned scale), and what one learned EV is in true stops
    against the synthetic truth."""
    note = json.loads((run_dir / TONE_PARAMS_FILE).read_text()).get("ev_scale", "")
    a = truth.get("exponent_a")
    true = f" (against the truth: one EV here is {1.0 / a:.2f} true stops)" if a else ""
    return f"{note[0].upper()}{note[1:]}{true}." if note else ""


def run(out: Path, s: ExperimentSettings) -> Path:
    result, comparison, models = run_scene(SCENE, out, s)
    for key in result:
        result[key]["train_s"] = train_seconds(out / "runs" / SCENE / key)
    run_dir = out / "runs" / SCENE / "ours_varying"
    ours, scene = models["ours_varying"]
    view = ours.test_ids[min(1, len(ours.test_ids) - 1)]
    pics = pictures(ours, scene, view, comparison, out / "images", s.backend)
    figure = test_view_figure(models, result, view, out / "images" / "test_view.png", s.backend)
    k, large_size = pics.repeat, pics.large_size
    data = report_data("demo", PROTOCOL, s, TRUTH_PROTOCOL)
    data["scenes"][SCENE] = result
    rows = [(m.key, result[m.key]) for m in METHODS]
    rel = lambda p: Path(p).relative_to(out)  # noqa: E731
    md = [
        "# HDR-Plenoxels demo: the built-in scene shot with varying, unknown camera settings",
        "",
        PROTOCOL,
        "",
        f"## Test view {Path(ours.names[view]).stem}",
        "",
        f"![the test view: photos, ours and Plenoxels]({rel(figure)})",
        "",
        "Top: the scene photographed with varying, unknown camera settings, ours, and plain Plenoxels on "
        "the same photos. Bottom: the scene photographed with one fixed camera, and plain Plenoxels on "
        "those photos (the upper bound). Left of each dashed line is the half of the test view that "
        "calibrates its tone (its white balance and exposure, learned from those pixels only); right of it "
        "is the half that is scored.",
        "",
        "## Metrics (right halves of test views)",
        "",
        table(rows, first="method", columns=(*METRIC_COLUMNS, ("train_s", "train s", 1))),
        "",
        "`plenoxels_static`: plain Plenoxels on the same scene shot with one fixed camera (the upper bound); "
        "`plenoxels_varying`: plain Plenoxels on the varying captures; `ours_varying`: with the learned "
        "tone mapping.",
        "",
        *tone_section([("ours_varying", result["ours_varying"].get("tones", {}))], "method"),
        "## Truth recovery of ours",
        "",
        table([("ours_varying", result["ours_varying"].get("truth", {}))], TRUTH_COLUMNS, first="method"),
        "",
        TRUTH_PROTOCOL,
        "",
        "## Exposure after the fact",
        "",
        f"Right half: truth | ours (each pixel shown {k} x {k}). ![right half vs truth]({rel(pics.halves)})",
        "",
        f"The same view at {', '.join(f'{ev:+g}' for ev in EV_SWEEP)} EV (relative to the mean of the "
        f"learned exposures, mean white balance, the reference view's response), rendered at "
        f"{large_size[0]} x {large_size[1]}. {ev_scale(run_dir, result['ours_varying'].get('truth', {}))} "
        f"![EV sweep]({rel(pics.ev_sweep)})",
        "",
        f"Linear HDR radiance of the view (float EXR, reference image's scale): `{rel(pics.exr)}`",
        "",
        f"An orbit around the scene sweeping the exposure from {EV_SWEEP[0]:+g} to {EV_SWEEP[-1]:+g} EV "
        f"(H.264): `{rel(pics.video)}`",
        "",
        f"All methods on this view (truth static, Plenoxels static, truth varying, Plenoxels varying, ours; "
        f"each pixel shown {k} x {k}): "
        f"![comparison]({rel(comparison)})",
        "",
        "## Learned tones",
        "",
        f"![tone parameters]({rel(run_dir / TONE_PLOT_FILE)})",
    ]
    return write_report(out, data, "\n".join(md))
