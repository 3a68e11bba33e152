"""How far the learned EVs end from exact stated exposures, with and without holding their ratios.

The suite's EXIF capture (the `gallery` scene, 20 views at -3 / 0 / +3 EV, saved as JPEGs whose EXIF is
written from the camera truth) is processed once, then trained at a preset (`fast` unless `--preset`
says otherwise, its own number of steps unless `--iters` does) for each value of a setting (`--key`):
the hold's weight `tonemap.lambda_exposure_ratios` held from the first step (`exposure_hold=always`),
or, where `--key` names another, that setting at the package's defaults: the hold itself
(`tonemap.exposure_hold off checked always`), the response's smoothness (`tonemap.lambda_crf_smooth`).
Printed per value: each EV group's mean error against the truth (after
the gauge fitted to the EXIF), the RMS and largest error, the white-balance error and the response's RMSE
against the true camera (`eval.truth.camera_recovery`), and the PSNR of the test views' right halves
(a record only: the setting is chosen on validation views, README here).

    python benchmarks/studies/exposure_ratios/exposures.py OUT [--values 0 0.02 0.2] [--iters N]
        [--key tonemap.lambda_exposure_ratios] [--preset fast]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from hdrplenoxels.cli.main import main as cli
from hdrplenoxels.data import load_scene
from hdrplenoxels.eval.evaluate import evaluate
from hdrplenoxels.eval.truth import SynthTruth, camera_recovery
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.synth.photos import write_photos
from hdrplenoxels.train.model import load_model


def capture(out: Path) -> tuple[Path, Path]:
    """The gallery rendered and its JPEGs processed, once (the truth folder and the dataset)."""
    gallery, data = out / "gallery", out / "data"
    if not (gallery / "varying_jpeg").is_dir():
        synthesize("gallery", gallery, SynthOptions(n_views=20))
        write_photos(gallery / "varying", gallery / "varying_jpeg")
    if not (data / "transforms.json").is_file():
        cli(["process", str(gallery / "varying_jpeg"), str(data)])
    return gallery / "varying", data


def score(run: Path, truth: SynthTruth, data: Path) -> dict:
    model = load_model(run)
    views = [int(Path(n).stem.split("_")[1]) for n in model.names]
    learned = (model.tonemapper.linear_log_wb().mean(1) / np.log(2.0)).numpy()
    true_ev = truth.evs[views]
    error = (learned - learned.mean()) - (true_ev - true_ev.mean())
    cameras = camera_recovery(model, truth.true_log2_gain[views], truth.curves[views])
    return {
        "ev_error_by_ev": {f"{ev:+.0f}": float(error[true_ev == ev].mean()) for ev in np.unique(true_ev)},
        "ev_rms": float(np.sqrt(np.mean(error**2))),
        "ev_largest": float(np.abs(error).max()),
        "wb_error_stops": cameras["wb_error_stops"],
        "crf_rmse": cameras["crf_rmse"],
        "test_psnr": float(evaluate(model, load_scene(data), lpips=False)["psnr"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--values", nargs="+", default=["0", "0.02", "0.2"], help="of the setting")
    parser.add_argument("--iters", type=int, default=None, help="default: the preset's")
    parser.add_argument("--key", default="tonemap.lambda_exposure_ratios", help="the setting weighed")
    parser.add_argument("--preset", default="fast")
    args = parser.parse_args()
    truth_folder, data = capture(args.out)
    truth = SynthTruth.load(truth_folder)
    results = {}
    held = ["--set", "tonemap.exposure_hold=always"] if args.key == "tonemap.lambda_exposure_ratios" else []
    for value in args.values:
        run = args.out / f"{args.key}_{args.preset}_{value}"
        train = ["train", str(data), "--out", str(run), "--preset", args.preset]
        train += ["--iters", str(args.iters)] if args.iters else []
        cli([*train, "--quiet", *held, "--set", f"{args.key}={value}"])
        results[value] = r = score(run, truth, data)
        groups = "  ".join(f"{ev}: {e:+.3f}" for ev, e in r["ev_error_by_ev"].items())
        print(
            f"{args.key} {value}: EV error by EV {groups}; RMS {r['ev_rms']:.4f}, "
            f"largest {r['ev_largest']:.3f}; WB error {r['wb_error_stops']:.4f}; "
            f"CRF RMSE {r['crf_rmse']:.4f}; test PSNR {r['test_psnr']:.2f} dB",
            flush=True,
        )
    (args.out / f"exposures_{args.key}_{args.preset}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
