"""What the tone module recovered of a re-shoot's simulated cameras: the exponent of its gauge, the
photos' exposure and white-balance errors in stops and the response curve's RMSE, against the cameras
`benchmarks/real_captures.py` re-shot the linearised photos through (their `camera_truth.json`). The
synthetic scenes' truth recovery (`hdrplenoxels.eval.truth`) on real photos: the HDR error needs a true
radiance, which a real capture does not have, so it is left out.

Usage: python benchmarks/studies/reshoot_gap/camera_truth.py RUN [RUN ...] [--json TRUTH.json]
  RUN: a run of ours on a varying re-shoot (or on its validation subset), e.g.
  OUT/kermit/LABEL/balanced-ours-varying
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from hdrplenoxels.eval.truth import crf_rmse, fit_exponent, gain_errors, learned_log2_gains
from hdrplenoxels.train.model import Model


def trained_views(model: Model) -> list[Path]:
    """The image of each of the run's views, in the run's order (a validation subset's frames point
    into the re-shoot's own folder, beside its camera_truth.json)."""
    data = Path(model.data_path)
    transforms = json.loads((data if data.suffix == ".json" else data / "transforms.json").read_text())
    root = data.parent if data.suffix == ".json" else data
    return [root / f["file_path"] for f in transforms["frames"]]


def camera_truth(run: Path) -> dict:
    """The run's exponent `a`, exposure and white-balance errors (stops) and mean CRF RMSE over its
    curves, each curve against the true response of a photo that uses it."""
    model = Model.load(run / "model.npz", device="cpu")
    images = trained_views(model)
    truth_file = images[0].parent.parent / "camera_truth.json"
    views = json.loads(truth_file.read_text())["views"]  # in the re-shoot's frame order
    frames = json.loads((truth_file.parent / "transforms.json").read_text())["frames"]
    by_stem = {Path(f["file_path"]).stem: views[i] for i, f in enumerate(frames)}
    picked = [by_stem[p.stem] for p in images]
    evs = np.array([v["ev"] for v in picked], dtype=np.float64)
    true_gain = evs[:, None] + np.log2(np.array([v["wb_gains"] for v in picked], dtype=np.float64))
    learned = learned_log2_gains(model)
    a, offset = fit_exponent(learned, true_gain)
    tm = model.tonemapper
    groups = {int(tm.crf_group[i]): i for i in range(len(picked))}
    rmse = [crf_rmse(tm.curve(i), np.array(picked[i]["crf_curve"]), a)[0] for i in groups.values()]
    return {
        "run": str(run),
        "exponent_a": a,
        **gain_errors(learned, true_gain, a, offset),
        "crf_rmse": float(np.mean(rmse)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description="What ours recovered of a re-shoot's simulated cameras.")
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args()
    rows = [camera_truth(run) for run in args.runs]
    print("| run | a | EV error (stops) | WB error (stops) | CRF RMSE |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['run']} | {r['exponent_a']:.3f} | {r['ev_error_stops']:.3f} | {r['wb_error_stops']:.3f} | "
            f"{r['crf_rmse']:.4f} |"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
