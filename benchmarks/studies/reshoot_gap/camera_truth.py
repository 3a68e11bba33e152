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

from hdrplenoxels.eval.truth import camera_recovery
from hdrplenoxels.train.model import Model


def trained_views(model: Model) -> list[Path]:
    """The image of each of the run's views, in the run's order (a validation subset's frames point
    into the re-shoot's own folder, beside its camera_truth.json)."""
    data = Path(model.data_path)
    root = data.parent if data.suffix == ".json" else data
    return [root / name for name in model.names]


def camera_truth(run: Path) -> dict:
    """`eval.truth.camera_recovery` of the run against the cameras of the re-shoot it trained on."""
    model = Model.load(run / "model.npz", device="cpu")
    images = trained_views(model)
    truth_file = images[0].parent.parent / "camera_truth.json"
    views = json.loads(truth_file.read_text())["views"]  # in the re-shoot's frame order
    frames = json.loads((truth_file.parent / "transforms.json").read_text())["frames"]
    by_stem = {Path(f["file_path"]).stem: views[i] for i, f in enumerate(frames)}
    picked = [by_stem[p.stem] for p in images]
    evs = np.array([v["ev"] for v in picked], dtype=np.float64)
    true_gain = evs[:, None] + np.log2(np.array([v["wb_gains"] for v in picked], dtype=np.float64))
    curves = np.array([v["crf_curve"] for v in picked], dtype=np.float64)
    return {"run": str(run), **camera_recovery(model, true_gain, curves)}


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
