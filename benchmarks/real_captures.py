"""The real-capture benchmark (JOURNAL.md, "Real captures").

For each capture in a folder of real photo captures (by default `../shared/realdata`: each `NAME/images/`):
`process` -> `train` -> render -> score, printing the registered images, training time, peak memory of the
training process, PSNR of the training views (their own learned tones, whole images), PSNR / SSIM of
the test views' right halves, the grid's levels and its voxels with density (fog fills them), and writing
a contact sheet per capture and run (photo | render | depth, two test views).

Real photos have no truth for other camera settings, so each capture is also re-shot through simulated
cameras, as `synth` captures its scenes: the photos linearised with the inverse sRGB curve are the scene
radiance, then per view an exposure from {-2, 0, +2} EV and a white-balance gain of 1.25 on one channel
(the "varying" capture) or neither (the "static" capture), clipping, a gamma-3 response and 8 bits. This
gives static/varying pairs of real photos to score ours (`--tonemap`) against Plenoxels on each.

Runs (`--methods`): `ours-photos` and `plenoxels-photos` train on the photos as taken; `plenoxels-static`,
`plenoxels-varying` and `ours-varying` on the re-shoots; `ours-static` (asked for by name) puts the tone
mapper on the static re-shoot, to tell what it costs where no photo's camera differs. `ours-photos-full`
trains on the photos with `--holdout full` (test views never seen) and scores whole test views through
the tone controller's tone (`auto`), the mean learned tone (`mean`) and colour-corrected (`cc`), beside
`ours-photos`' right halves. Each run is `hdrplenoxels train` in its own
process (so the peak memory is its own); run on a quiet machine, since times are wall clock.
Protocol: every 8th view is a test view; its left half trains its tone (exposure, white balance), its
right half is scored; every model is the final step of its schedule.

`--split validation` is for choosing settings: each capture's test views are dropped altogether and every
8th of the remaining views becomes a validation view (its left half trains its tone, its right half is
scored), so that no setting is chosen on a test pixel. `--fold J` starts that every 8th at the J-th
remaining view (0 to 7): a shared capture has one to six validation views a fold, so a choice can be
checked on other folds' views before it is made.

Example: python benchmarks/real_captures.py --out runs/real --captures kermit brickstamp --presets fast
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from hdrplenoxels.core.atomic import atomic_write_files
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.protocol import HOLDOUT_EVERY
from hdrplenoxels.data.sight_lines import POINTS_KEY
from hdrplenoxels.eval.evaluate import PROTOCOLS, TONES, evaluate, run_downscale
from hdrplenoxels.eval.metrics import psnr
from hdrplenoxels.synth.pipeline import PipelineConfig, capture, crf_srgb_inverse, draw_settings
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.run_folder import LOG_FILE
from hdrplenoxels.viewer.display import depth_opacity_view, geometry_image

DEFAULT_REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
METHODS = (
    "ours-photos",
    "plenoxels-photos",
    "plenoxels-static",
    "plenoxels-varying",
    "ours-varying",
    "ours-photos-full",
)
EXTRA_METHODS = ("ours-static",)  # the tone mapper on one fixed camera: what it costs where nothing varies
NOVEL_TONES = ("auto", "mean", "cc")  # how `-full` runs see their unseen test views (`eval --tone`)
RESHOOT = PipelineConfig(ev_set=(-2.0, 0.0, 2.0), seed=11)
LONG_SIDE = 700  # images are downscaled by the smallest factor that brings the long side to at most this


@dataclass
class Method:
    dataset: str  # "photos", "static" or "varying"
    tonemap: bool
    full: bool = False  # `--holdout full`: test views unseen, scored through NOVEL_TONES


def method(name: str) -> Method:
    who, dataset, *rest = name.split("-")
    return Method(dataset, who == "ours", rest == ["full"])


def python_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "hdrplenoxels", *args]


def run_timed(cmd: list[str], log: Path) -> tuple[float, float]:
    """Run `cmd` (output to `log`); (wall seconds, peak resident GB of that process)."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}); see {log}")
    return time.perf_counter() - t0, usage.ru_maxrss * 1024 / 1e9


def capture_names(realdata: Path, chosen: list[str] | None) -> list[str]:
    """`chosen`, or every capture of `realdata` (each folder holding an `images/`)."""
    return chosen or sorted(p.name for p in realdata.iterdir() if (p / "images").is_dir())


def processed(capture: str, images: Path, out: Path, reuse: Path | None) -> tuple[Path, dict]:
    """The capture's dataset (`process`ed here, or reused from `reuse/NAME`) and what `process` reported."""
    data = out / capture / "data"
    if reuse is not None:
        data = reuse / capture
    elif not (data / "transforms.json").exists():
        data.parent.mkdir(parents=True, exist_ok=True)
        run_timed(python_cmd("process", str(images), str(data)), out / capture / "process.log")
    info = json.loads((data / "transforms.json").read_text()).get("process", {})
    return data, info


def shared_points(meta: dict, data: Path) -> dict:
    """`meta` of a dataset made from `data`'s, naming `data`'s sparse points file (matched by image stem,
    so a re-shoot's PNGs and a validation subset keep them) by its absolute path."""
    if POINTS_KEY in meta:
        meta[POINTS_KEY] = str((data / meta[POINTS_KEY]).resolve())
    return meta


def reshoot(data: Path, out: Path, variant: str) -> Path:
    """A copy of the dataset whose photos are re-shot through the simulated `variant` cameras."""
    target = out / variant
    if (target / "transforms.json").exists():
        return target
    meta = shared_points(json.loads((data / "transforms.json").read_text()), data)

    def write(work: Path) -> None:
        (work / "images").mkdir()
        truth = []
        for view, frame in enumerate(meta["frames"]):
            photo = np.asarray(Image.open(data / frame["file_path"]).convert("RGB"), dtype=np.float32) / 255.0
            settings = draw_settings(view, variant, RESHOOT)
            name = Path(frame["file_path"]).with_suffix(".png").name
            Image.fromarray(capture(crf_srgb_inverse(photo), settings)).save(work / "images" / name)
            frame["file_path"] = f"images/{name}"
            for key in ("exif", "exposure_init_ev"):  # the photo's own exposure no longer applies
                frame.pop(key, None)
            truth.append({"view": view, **settings.to_dict()})
        record = {"variant": variant, "pipeline": asdict(RESHOOT), "views": truth}  # as `synth` writes it
        (work / "camera_truth.json").write_text(json.dumps(record))
        (work / "transforms.json").write_text(json.dumps(meta, indent=2))

    # moved into place file by file in name order: `transforms.json`, what marks it done, comes last
    return atomic_write_files(target, write)


def validation_folder(fold: int) -> str:
    """The folder a capture's validation sets of `fold` go in (beside its processed data)."""
    return "validation" + (f"-fold{fold}" if fold else "")


def validation_set(data: Path, target: Path, fold: int = 0) -> Path:
    """`data` without its test views (every 8th, from the first), as a dataset of its own in `target`
    whose every 8th view, from the `fold`-th, is a validation view; its frames name the original images.
    Fold 0 is the loader's own every-8th split; the other folds name their views in `test_filenames`."""
    if (target / "transforms.json").exists():
        return target
    meta = shared_points(json.loads((data / "transforms.json").read_text()), data)
    frames = [f for i, f in enumerate(meta["frames"]) if i % HOLDOUT_EVERY != 0]
    folds = min(HOLDOUT_EVERY, len(frames))
    if not 0 <= fold < folds:
        raise ValueError(f"fold {fold} of {data}: its {len(frames)} views left give folds 0 to {folds - 1}")
    for frame in frames:
        frame["file_path"] = str((data / frame["file_path"]).resolve())
    meta["frames"] = frames
    if fold:
        meta["test_filenames"] = [f["file_path"] for j, f in enumerate(frames) if j % HOLDOUT_EVERY == fold]
    target.mkdir(parents=True, exist_ok=True)
    (target / "transforms.json").write_text(json.dumps(meta, indent=2))
    return target


def downscale_for(data: Path) -> int:
    meta = json.loads((data / "transforms.json").read_text())
    frame = meta["frames"][0]
    w = frame.get("w", meta.get("w"))
    h = frame.get("h", meta.get("h"))
    if w is None or h is None:
        with Image.open(data / frame["file_path"]) as img:
            w, h = img.size
    factor = 1
    while max(w, h) / factor > LONG_SIDE:
        factor += 1
    return factor


def train_run(data: Path, run: Path, preset: str, tonemap: bool, downscale: int, extra: list[str]) -> dict:
    done = run / "model.npz"
    if not done.exists():
        run.parent.mkdir(parents=True, exist_ok=True)
        args = ["train", str(data), "--preset", preset, "--out", str(run), "--downscale", str(downscale)]
        args += ["--tonemap" if tonemap else "--no-tonemap"]
        wall, peak = run_timed(python_cmd(*args, *extra), run.parent / f"{run.name}.train.log")
        (run / "bench_process.json").write_text(json.dumps({"wall_s": wall, "peak_gb": peak}))
    stats = json.loads((run / "bench_process.json").read_text())
    log = (run / LOG_FILE).read_text().splitlines()
    stats["train_s"] = json.loads(log[-1])["seconds"]
    return stats


@torch.no_grad()
def score(run: Path, data: Path, sheet: Path, label: str, full: bool) -> dict:
    """Right halves and training views; or, for a `full` (`--holdout full`) run, whole unseen test views
    through NOVEL_TONES."""
    model = Model.load(run / MODEL_FILE)
    scene = load_scene(data, run_downscale(model))
    if full:
        novel = {c: evaluate(model, scene, lpips=False, tone=c) for c in NOVEL_TONES}
        return (
            {f"psnr_{c}": r["psnr"] for c, r in novel.items()}
            | {f"ssim_{c}": r["ssim"] for c, r in novel.items()}
            | {"test_views": novel["auto"]["num_test_views"], "controller": model.controller.form}
        )
    result = evaluate(model, scene, lpips=False)
    picks = np.linspace(0, len(model.train_ids) - 1, min(8, len(model.train_ids))).round().astype(int)
    train_psnr = []
    for i in (model.train_ids[j] for j in picks):
        pred = model.to_ldr(model.render_camera(i), i).cpu()
        train_psnr.append(psnr(pred, torch.tensor(scene.images[i], dtype=torch.float32) / 255.0))
    contact_sheet(model, scene, sheet, label)
    grid = model.grid
    return {
        "psnr_right": result["psnr"],
        "ssim_right": result["ssim"],
        "psnr_train": float(np.mean([float(p) for p in train_psnr])),
        "test_views": result["num_test_views"],
        "levels": grid.levels,
        "voxels": grid.num_voxels,  # allocated after the last pruning
        "occupied": int((grid.density > 0).sum()),  # of them, with density: fog shows as a high count
    }


def contact_sheet(model: Model, scene, path: Path, label: str) -> None:
    """Two test views, each a row: photo | render (its learned tone) | depth (turbo, near blue)."""
    rows = []
    ids = model.test_ids[:: max(1, len(model.test_ids) // 2)][:2]
    for i in ids:
        photo = scene.images[i]
        render = (model.to_ldr(model.render_camera(i), i).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        cams = model.cameras
        depth, opacity = depth_opacity_view(model, cams.c2w[i], cams.intrinsics[i], cams.size(i))
        rows.append(np.concatenate([photo, render, geometry_image(depth, opacity, "depth")], axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realdata", type=Path, default=DEFAULT_REALDATA)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--captures", nargs="*", default=None, help="default: every folder of --realdata")
    parser.add_argument("--presets", nargs="+", default=["fast", "balanced"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS + EXTRA_METHODS)
    parser.add_argument("--processed", type=Path, default=None, help="reuse ROOT/NAME datasets (no SfM)")
    parser.add_argument("--label", default="", help="a name for this code's runs (runs go in OUT/NAME/LABEL)")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], help="train --set, repeatable"
    )
    parser.add_argument("--train-arg", action="append", default=[], help="another train argument, repeatable")
    parser.add_argument("--split", choices=("test", "validation"), default="test")
    parser.add_argument("--fold", type=int, default=0, help="which every-8th validation views (0-7)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.fold and args.split != "validation":
        parser.error("--fold chooses validation views: it needs --split validation")
    captures = capture_names(args.realdata, args.captures)
    extra = [a for kv in args.overrides for a in ("--set", kv)] + args.train_arg
    results = []
    print(f"Protocol: {PROTOCOLS['right-half']}; final step of every schedule.")
    if any(method(m).full for m in args.methods):
        print(
            f"-full runs: {PROTOCOLS['full']}; through the tones " + "; ".join(TONES[c] for c in NOVEL_TONES)
        )
    for name in captures:
        data, info = processed(name, args.realdata / name / "images", args.out, args.processed)
        sets = {"photos": data}
        if any(method(m).dataset != "photos" for m in args.methods):
            sets |= {v: reshoot(data, args.out / name, v) for v in ("static", "varying")}
        downscale = downscale_for(data)
        if args.split == "validation":
            folder = validation_folder(args.fold)
            sets = {k: validation_set(v, args.out / name / folder / k, args.fold) for k, v in sets.items()}
        print(
            f"{name}: {info.get('registered', '?')} of {info.get('n_photos', '?')} registered, "
            f"downscale {downscale}"
        )
        for preset in args.presets:
            for m in args.methods:
                spec = method(m)
                split = "" if args.split == "test" else f"val{args.fold or ''}-"
                run = args.out / name / (args.label or "runs") / f"{split}{preset}-{m}"
                holdout = ["--holdout", "full"] if spec.full else []
                stats = train_run(sets[spec.dataset], run, preset, spec.tonemap, downscale, extra + holdout)
                sheet = args.out / "sheets" / f"{name}-{args.label or 'runs'}-{split}{preset}-{m}.png"
                stats |= score(run, sets[spec.dataset], sheet, f"{name} {preset} {m}", spec.full)
                row = {"capture": name, "preset": preset, "method": m, "registered": info.get("registered")}
                results.append(row | stats)
                head = f"  {preset:>9} {m:<18} train {stats['train_s']:7.1f} s  "
                head += f"peak {stats['peak_gb']:5.2f} GB  "
                if spec.full:
                    cams = "  ".join(f"{c} {stats['psnr_' + c]:6.2f} dB" for c in NOVEL_TONES)
                    print(f"{head}unseen test views: {cams} (controller {stats['controller']})", flush=True)
                else:
                    print(
                        f"{head}train views {stats['psnr_train']:6.2f} dB  right halves "
                        f"{stats['psnr_right']:6.2f} dB / {stats['ssim_right']:.3f}",
                        flush=True,
                    )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
