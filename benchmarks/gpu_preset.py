"""Choosing a GPU preset for real captures on validation views (JOURNAL.md, "A GPU preset for
real captures").

A GPU's speed can buy a real capture more steps, a finer top level, finer photos, wider batches, and
re-tuned floater priors. Each candidate below is `balanced` plus one or more of those; each is trained
on every shared capture's validation split (`real_captures.validation_set`: the capture's test views
dropped, every 8th remaining view a validation view whose left half trains its tone and whose right half
is scored), photos as taken, tone mapping on. No test view of a capture is ever read: the kits carry
none. The choice (`choose`): among the candidates that ran on every capture within the wall budget, the
one with the highest mean validation PSNR; beside it each candidate's gain over `balanced` per capture.

Two steps, because the device machines have no COLMAP and carry at most 64 MiB a call:

    python benchmarks/gpu_preset.py kits --out runs/gpu-kits [--captures ...] [--candidates ...]
        (here, on the CPU) processes each capture (or reuses `--processed ROOT/NAME`), drops its test
        views, and writes one small dataset per photo resolution the candidates need: the photos reduced
        by the real-capture benchmark's downscale (`x1`) or by a whole divisor of it at most half as large
        (`x2`: 4 -> 2, 3 -> 1, 1 -> 1; `finer_downscale`), area-filtered as `train --downscale` does and
        stored as JPEG (`--quality`; every candidate reads the same pixels); a candidate trained on `x2` is
        scored on `x1`'s pixels (`scores_at`)

    python benchmarks/gpu_preset.py run --kits runs/gpu-kits --out $OUT/preset [--results F] [--deadline S]
        (on the GPU) trains each candidate on each kit, in order, appending a row to results.json and
        rewriting results.md after every run, skipping the runs already in `--results` (so that sessions
        continue one another) and starting none past `--deadline` seconds. A row counts as done only if
        it was trained with its candidate's configuration of today (`config_key`): one measured before a
        default changed is dropped, with a line, and run again. The first device session
        continued `benchmarks/gpu_preset_baseline.json` (`balanced` on the CPU: quality does not depend on
        the device), and later ones continue `benchmarks/gpu_preset_results.json` (its rows and the GPU's
        so far); rows of other candidates measured on a CPU belong in a file of their own, since a row in
        `--results` counts as a run done.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_captures import (  # noqa: E402
    DEFAULT_REALDATA,
    capture_names,
    downscale_for,
    processed,
    train_run,
    validation_folder,
    validation_set,
)

from hdrplenoxels.core.settings import apply_overrides  # noqa: E402
from hdrplenoxels.data.downscale import block_average  # noqa: E402
from hdrplenoxels.data.sight_lines import POINTS_KEY  # noqa: E402
from hdrplenoxels.eval.controller_truth import TRUTH_FILE  # noqa: E402
from hdrplenoxels.train.config import TrainConfig  # noqa: E402
from hdrplenoxels.train.presets import BALANCED, preset  # noqa: E402

BASE = "balanced"
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")
SIZE_KEYS = ("w", "h")
SPLIT_KEYS = ("train_filenames", "test_filenames")
BALANCED_LEVELS = BALANCED["grid.reso_schedule"]
FINE_LEVELS = [*BALANCED_LEVELS, (512, 512, 512)]
BUDGET_S = 180.0  # the limit per run on one H100


def schedule(steps: int, levels: list[tuple[int, int, int]]) -> dict[str, Any]:
    """`steps` steps over `levels` in `balanced`'s proportions: an equal share of the steps per level, the
    density's learning-rate delay a tenth of the run, the decay over all of it, one checkpoint at the end
    (a cascade's at 512^3 writes gigabytes)."""
    return {
        "grid.reso_schedule": [tuple(r) for r in levels],
        "grid.upsample_every": steps // len(levels),
        "optim.n_iters": steps,
        "optim.lr_decay_steps": steps,
        "optim.lr_sigma_delay_steps": steps // 10,
        "checkpoint_every": steps,
    }


@dataclass(frozen=True)
class Candidate:
    what: str  # what the GPU's speed buys here, in a few words
    overrides: dict[str, Any] = field(default_factory=dict)  # `train --set` over `balanced`
    finer: int = 1  # photos at least this much finer than the benchmark's (`finer_downscale`)


FINE = schedule(12_000, FINE_LEVELS)
# The finer schedule keeps `balanced`'s TV, which since 2026-11-28 follows the number of photos
# (`optim.tv_photos`), so `fine` differs from `balanced` only in what the GPU's speed buys and each later
# `fine-*` candidate adds one thing to it (JOURNAL.md, "A GPU preset for real captures").
# `fine-tv10` and `fine-tv100` fix the TV instead, at 10x and 100x balanced's 1e-5 / 1e-4 whatever the
# photos: the two weights the CPU exploration measured before the rule ("The grid's TV beyond 10x").
TV10 = {"optim.lambda_tv_sigma": 1e-4, "optim.lambda_tv_sh": 1e-3, "optim.tv_photos": 0.0}
TV100 = {"optim.lambda_tv_sigma": 1e-3, "optim.lambda_tv_sh": 1e-2, "optim.tv_photos": 0.0}
CANDIDATES: dict[str, Candidate] = {
    BASE: Candidate("the CPU preset, as users run it"),
    "fine": Candidate("4x the steps and a 512^3 top level, balanced's TV (from the number of photos)", FINE),
    "fine-tv10": Candidate("fine at 10x balanced's TV, whatever the photos", FINE | TV10),
    "fine-tv100": Candidate("fine at 100x balanced's TV, whatever the photos", FINE | TV100),
    "fine-photos": Candidate("fine on photos at least twice as fine", FINE, finer=2),
    "fine-sparsity": Candidate("fine, Cauchy sparsity 1e-8", FINE | {"optim.lambda_sparsity": 1e-8}),
    "fine-distortion": Candidate("fine, 3x the distortion weight", FINE | {"optim.lambda_distortion": 0.03}),
    "fine-free-space": Candidate("fine, 3x the free-space prior", FINE | {"optim.lambda_free_space": 3.0}),
    "fine-views": Candidate("fine, voxels kept to what two photos see", FINE | {"grid.min_views": 2}),
    "fine-batch": Candidate("fine, 16 384 rays a step", FINE | {"optim.batch_size": 16_384}),
    "fine-sh1": Candidate("fine, SH degree 1 (4 coefficients a channel)", FINE | {"grid.sh_degree": 1}),
    "long": Candidate("4x the steps", schedule(12_000, BALANCED_LEVELS)),
    "fine-long": Candidate("8x the steps and a 512^3 top level", schedule(24_000, FINE_LEVELS)),
    "photos": Candidate("balanced on photos at least twice as fine", finer=2),
    "sh1": Candidate("balanced at SH degree 1: what less view dependence is worth", {"grid.sh_degree": 1}),
}


def candidate_config(name: str) -> TrainConfig:
    """The configuration `name` trains with (what `run` passes as `--preset balanced --set ...`)."""
    return apply_overrides(preset(BASE), CANDIDATES[name].overrides)


def config_digest(cfg: TrainConfig) -> str:
    """A short digest of a whole configuration: a row measured before a default changed carries another,
    and is run again rather than counted as done."""
    text = json.dumps(cfg.to_dict(), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def config_key(name: str) -> str:
    """The digest of the configuration candidate `name` trains with today."""
    return config_digest(candidate_config(name))


def current(rows: list[dict]) -> tuple[list[dict], list[dict]]:
    """`rows` split into those trained with their candidate's configuration of today and the stale rest
    (another key, none, or a candidate no longer defined)."""
    keys = {name: config_key(name) for name in CANDIDATES}
    fresh = [r for r in rows if r.get("config") is not None and r.get("config") == keys.get(r["candidate"])]
    return fresh, [r for r in rows if r not in fresh]


def set_args(overrides: dict[str, Any]) -> list[str]:
    """`overrides` as `train` arguments (`--set key=value`, values as JSON)."""
    return [a for key, value in overrides.items() for a in ("--set", f"{key}={json.dumps(value)}")]


# ----------------------------------------------------------------------------- kits (CPU)
def kit_size(kit: Path) -> float:
    """A kit's MiB (what a device call carries)."""
    return sum(p.stat().st_size for p in kit.rglob("*") if p.is_file()) / 2**20


def write_kit(data: Path, out: Path, factor: int, quality: int | None) -> Path:
    """`data` (a nerfstudio transforms.json dataset, frames possibly naming images by absolute path) as a
    dataset of its own in `out` whose photos are `factor` times smaller, area-filtered as `train
    --downscale` does (JPEG at `quality`, or PNG, lossless, with None), and whose intrinsics and sizes are
    scaled to match; its sparse points copied."""
    meta = json.loads((data / "transforms.json").read_text())
    work = out.with_name(out.name + ".partial")
    shutil.rmtree(work, ignore_errors=True)
    (work / "images").mkdir(parents=True)
    for entry in (meta, *meta["frames"]):
        for key in INTRINSIC_KEYS:
            if key in entry:
                entry[key] = entry[key] / factor
        for key in SIZE_KEYS:
            if key in entry:
                entry[key] = entry[key] // factor
    renamed = {}
    for frame in meta["frames"]:
        source = data / frame["file_path"]  # an absolute path stays itself
        with Image.open(source) as img:
            photo = np.asarray(img.convert("RGB"))
        reduced = Image.fromarray(block_average(photo, factor))
        name = f"images/{source.stem}.{'png' if quality is None else 'jpg'}"
        reduced.save(work / name, **({} if quality is None else {"quality": quality, "subsampling": 0}))
        renamed[frame["file_path"]] = frame["file_path"] = name
    for key in SPLIT_KEYS:  # a split named by file (a validation fold's) names the kit's files
        if key in meta:
            meta[key] = [renamed[f] for f in meta[key]]
    if POINTS_KEY in meta:
        points = data / meta[POINTS_KEY]
        shutil.copyfile(points, work / points.name)
        meta[POINTS_KEY] = points.name
    if (data / TRUTH_FILE).exists():  # a re-shoot's simulated camera settings
        shutil.copyfile(data / TRUTH_FILE, work / TRUTH_FILE)
    (work / "transforms.json").write_text(json.dumps(meta, indent=1))
    shutil.rmtree(out, ignore_errors=True)
    work.rename(out)
    return out


def finer_downscale(factor: int, finer: int) -> int:
    """The downscale of photos at least `finer` times finer than at `factor`: the largest whole divisor of
    `factor` at most `factor / finer` (4 -> 2, 3 -> 1, 1 -> 1 for `finer` 2), so that a picture rendered
    at it block-averages exactly to the benchmark's pixels (`scores_at`)."""
    return max(d for d in range(1, factor + 1) if factor % d == 0 and (d * finer <= factor or d == 1))


def kits(args: argparse.Namespace) -> None:
    finer = sorted({CANDIDATES[c].finer for c in args.candidates})
    for name in capture_names(args.realdata, args.captures):
        data, _ = processed(name, args.realdata / name / "images", args.work, args.processed)
        val = validation_set(data, args.work / name / validation_folder(args.fold) / "photos", args.fold)
        factor = downscale_for(data)
        for f in finer:
            reduced = finer_downscale(factor, f)
            kit = write_kit(val, args.out / name / f"x{f}", reduced, args.quality or None)
            print(f"{name} x{f}: downscale {reduced}, {kit_size(kit):.1f} MiB in {kit}", flush=True)


# ----------------------------------------------------------------------------- runs (GPU)
def scores_at(model, reference, sheet: Path | None = None) -> dict[str, Any]:
    """The validation views' right halves scored against `reference` (the same views' photos at the
    benchmark's downscale): each view rendered at the model's own resolution through its own tone, then
    block-averaged by the whole factor between the two (1 for the same kit; `finer_downscale`), as the
    photos themselves were reduced. A candidate trained on finer photos is so scored on the same pixels as
    every other; against its own finer photos it would be scored on detail the others' photos average
    away. With `sheet`, a PNG there: a row per view, the photo beside the render reduced."""
    import torch

    from hdrplenoxels.eval.evaluate import check_same_scene, scored_region, test_view_picture
    from hdrplenoxels.eval.metrics import image_metrics

    check_same_scene(model, reference)
    holdout = model.config.get("holdout", "right-half")
    views, rows = [], []
    for i in model.test_ids:
        scale = round(float(model.cameras.intrinsics[i][0] / reference.cameras.intrinsics[i][0]))
        picture = test_view_picture(model, model.render_camera(i), i, "own").cpu().numpy()
        pred = block_average(picture, scale)
        if pred.shape != reference.images[i].shape:
            got, photo = tuple(pred.shape), reference.images[i].shape
            raise ValueError(f"view {model.names[i]}: its render reduced is {got}, the photo {photo}")
        gt = torch.tensor(reference.images[i], dtype=torch.float32) / 255.0
        scored = scored_region(torch.from_numpy(pred), holdout), scored_region(gt, holdout)
        views.append(image_metrics(*scored, lpips_nets=()))
        rows.append(np.concatenate([reference.images[i], np.rint(pred * 255.0).astype(np.uint8)], axis=1))
    if sheet is not None:
        sheet.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.concatenate(rows, axis=0)).save(sheet)
    return {key: float(np.mean([v[key] for v in views])) for key in ("psnr", "ssim")} | {"views": len(views)}


def train_and_score(
    kit: Path, run: Path, name: str, reference: Path, sheet: Path | None = None
) -> dict[str, Any]:
    """Train candidate `name` on `kit` into `run` and score its validation views' right halves against
    `reference` (`kit` itself, or for a candidate trained on finer photos the same views at the
    benchmark's downscale: `scores_at`), drawing them into `sheet`."""
    import torch

    from hdrplenoxels.data import load_scene
    from hdrplenoxels.train.model import MODEL_FILE, Model

    # The kit is already at its downscale; --overwrite for a run a killed call left half-written.
    stats = train_run(
        kit, run, BASE, True, 1, ["--overwrite", "--quiet", *set_args(CANDIDATES[name].overrides)]
    )
    model = Model.load(run / MODEL_FILE)
    with torch.no_grad():
        scores = scores_at(model, load_scene(reference), sheet)
    return {
        **scores,
        **stats,  # train_s, wall_s, peak_gb (the training process's peak host memory)
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu",
    }


def runs(args: argparse.Namespace) -> None:
    start = time.monotonic()
    rows, stale = current(json.loads(args.results.read_text()) if args.results else [])
    for r in stale:
        print(f"stale: {r['candidate']} on {r['capture']} trained with other settings; run again", flush=True)
    done = {(r["capture"], r["candidate"]) for r in rows}
    args.out.mkdir(parents=True, exist_ok=True)
    captures = args.captures or sorted(p.name for p in args.kits.iterdir() if p.is_dir())
    for name in args.candidates:
        for capture in captures:
            if (capture, name) in done:
                continue
            if time.monotonic() - start > args.deadline:
                print(f"deadline: {name} on {capture} and after not started", flush=True)
                return
            kit, reference = args.kits / capture / f"x{CANDIDATES[name].finer}", args.kits / capture / "x1"
            row = {"capture": capture, "candidate": name, "config": config_key(name)}
            sheet = args.out / "sheets" / f"{capture}-{name}.png"
            try:
                row |= train_and_score(kit, args.out / capture / name, name, reference, sheet)
                print(f"{capture:>16} {name:<16} {row['psnr']:6.2f} dB  {row['wall_s']:7.1f} s", flush=True)
            except RuntimeError as e:  # a run that failed (out of memory, say) is a row, not the end
                row["error"] = str(e)
                print(f"{capture:>16} {name:<16} failed: {e}", flush=True)
            rows.append(row)
            (args.out / "results.json").write_text(json.dumps(rows, indent=1))
            (args.out / "results.md").write_text(report(rows, args.budget))
            if not args.keep:
                shutil.rmtree(args.out / capture / name, ignore_errors=True)  # a cascade's model is gigabytes


# ----------------------------------------------------------------------------- the choice
def gains(rows: list[dict]) -> dict[str, dict[str, float]]:
    """Each candidate's validation PSNR minus `balanced`'s, per capture (where both ran)."""
    rows = [r for r in rows if "error" not in r]
    base = {r["capture"]: r["psnr"] for r in rows if r["candidate"] == BASE}
    out: dict[str, dict[str, float]] = {}
    for r in rows:
        if r["capture"] in base:
            out.setdefault(r["candidate"], {})[r["capture"]] = r["psnr"] - base[r["capture"]]
    return out


def choose(rows: list[dict], budget_s: float) -> str | None:
    """The candidate with the highest mean validation PSNR among those that ran on every capture in
    `rows`, each run's whole `train` command (set-up, steps and the model's save: what a user waits for)
    within `budget_s`; None when none did."""
    captures = {r["capture"] for r in rows}
    by: dict[str, list[dict]] = {}
    for r in rows:
        if "error" not in r:
            by.setdefault(r["candidate"], []).append(r)
    eligible = {
        name: float(np.mean([r["psnr"] for r in own]))
        for name, own in by.items()
        if {r["capture"] for r in own} == captures and max(r["wall_s"] for r in own) <= budget_s
    }
    return max(eligible, key=eligible.get) if eligible else None


def report(rows: list[dict], budget_s: float) -> str:
    captures = sorted({r["capture"] for r in rows})
    cell = {(r["candidate"], r["capture"]): r for r in rows}
    gain = gains(rows)
    lines = [
        "Validation views of each capture (its test views dropped; every 8th remaining view's right half "
        f"scored); photos as taken, tone mapping on; PSNR dB (gain over {BASE}) / the `train` command's s.",
        "",
        "| candidate | what | " + " | ".join(captures) + " | device |",
        "|---|---|" + "---|" * len(captures) + "---|",
    ]
    for name in [n for n in CANDIDATES if any(k[0] == n for k in cell)]:
        cells = []
        for c in captures:
            r = cell.get((name, c))
            g = gain.get(name, {}).get(c)
            gained = f" ({g:+.2f})" if g is not None else ""
            if r is None or "error" in r:
                cells.append("–" if r is None else "failed")
            else:
                cells.append(f"{r['psnr']:.2f}{gained} / {r['wall_s']:.0f}")
        devices = ", ".join(sorted({r.get("device", "?") for k, r in cell.items() if k[0] == name}))
        lines.append(f"| {name} | {CANDIDATES[name].what} | " + " | ".join(cells) + f" | {devices} |")
    chosen = choose(rows, budget_s)
    lines += [
        "",
        f"Chosen (highest mean validation PSNR, every run ≤ {budget_s:.0f} s of training): {chosen or '–'}",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    steps = parser.add_subparsers(dest="step", required=True)
    kit = steps.add_parser("kits", help="(CPU) the validation kits")
    kit.add_argument("--out", type=Path, required=True)
    kit.add_argument("--work", type=Path, default=Path("runs/gpu-preset"), help="processed captures go here")
    kit.add_argument("--realdata", type=Path, default=DEFAULT_REALDATA)
    kit.add_argument("--processed", type=Path, default=None, help="reuse ROOT/NAME datasets (no SfM)")
    kit.add_argument("--quality", type=int, default=95, help="JPEG quality of the kits' photos (0: PNG)")
    kit.add_argument(
        "--fold", type=int, default=0, help="which every-8th views validate (0-7; 0: the search's)"
    )
    run = steps.add_parser("run", help="(GPU) train and score every candidate on every kit")
    run.add_argument("--kits", type=Path, required=True)
    run.add_argument("--out", type=Path, required=True)
    run.add_argument("--results", type=Path, default=None, help="an earlier results.json to continue")
    run.add_argument("--deadline", type=float, default=float("inf"), help="seconds: start no run after")
    run.add_argument(
        "--budget", type=float, default=BUDGET_S, help="seconds a chosen run's `train` command may take"
    )
    run.add_argument("--keep", action="store_true", help="keep each run's folder (to render it after)")
    for p in (kit, run):
        p.add_argument("--captures", nargs="*", default=None)
        p.add_argument("--candidates", nargs="+", default=list(CANDIDATES), choices=list(CANDIDATES))
    args = parser.parse_args()
    kits(args) if args.step == "kits" else runs(args)


if __name__ == "__main__":
    main()
