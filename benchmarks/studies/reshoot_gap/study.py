"""Where ours on a varying re-shoot loses to Plenoxels on the static one: per test view, the right half's
PSNR of both, beside the view's simulated exposure and how much of its re-shot right half is clipped
(8-bit code 0 or 255 in any channel). Reads the runs `benchmarks/real_captures.py` left (README beside
this script).

Usage: python benchmarks/studies/reshoot_gap/study.py OUT [--captures asclepius kermit ...]
       [--preset fast] [--label LABEL] [--json GAP.json]
  OUT: real_captures.py's --out, holding NAME/{static,varying}/ and NAME/LABEL/PRESET-METHOD/ (LABEL:
  real_captures.py's --label, `runs` without one)
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdrplenoxels.data import load_scene
from hdrplenoxels.eval.evaluate import evaluate, run_downscale
from hdrplenoxels.train.model import load_model


def clipped(image: np.ndarray) -> float:
    """The fraction of the right half's pixels with a channel at code 0 or 255."""
    half = image[:, image.shape[1] // 2 :]
    return float(((half == 0) | (half == 255)).any(-1).mean())


def capture_gap(root: Path, preset: str, label: str = "runs") -> list[dict]:
    """Per test view of one capture: EV, clipped fraction, PSNR of static Plenoxels and of ours."""
    evs = [v["ev"] for v in json.loads((root / "varying" / "camera_truth.json").read_text())["views"]]
    scores, scenes = {}, {}
    for method, variant in (("plenoxels-static", "static"), ("ours-varying", "varying")):
        model = load_model(root / label / f"{preset}-{method}")
        scenes[variant] = load_scene(root / variant, run_downscale(model))
        views = evaluate(model, scenes[variant], lpips=False)["views"]
        scores[method] = {v["index"]: v["psnr"] for v in views}
    varying = scenes["varying"]
    return [
        {
            "view": i,
            "ev": evs[i],
            "clipped": clipped(varying.images[i]),
            "static": scores["plenoxels-static"][i],
            "ours": scores["ours-varying"][i],
        }
        for i in sorted(scores["ours-varying"])
    ]


def study_arguments(description: str) -> tuple[argparse.Namespace, list[str]]:
    """The arguments this folder's scripts share, and the captures they name (default: every capture of
    OUT with a varying re-shoot)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("out", type=Path)
    parser.add_argument("--captures", nargs="*", default=None)
    parser.add_argument("--preset", default="fast")
    parser.add_argument(
        "--label", default="runs", help="the runs' folder: OUT/NAME/LABEL (real_captures.py's)"
    )
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    return args, args.captures or sorted(p.name for p in args.out.iterdir() if (p / "varying").is_dir())


def main() -> None:
    args, names = study_arguments(__doc__.splitlines()[0])
    results = {name: capture_gap(args.out / name, args.preset, args.label) for name in names}
    print("Right halves of the test views (left halves calibrate each view's tone); the last step.")
    print("| capture | view | EV | clipped | Plenoxels static | ours varying | gap dB |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    by_ev: dict[float, list[float]] = defaultdict(list)
    for name, rows in results.items():
        for r in rows:
            gap = r["static"] - r["ours"]
            by_ev[r["ev"]].append(gap)
            print(
                f"| {name} | {r['view']} | {r['ev']:+g} | {r['clipped']:.1%} | {r['static']:.2f} "
                f"| {r['ours']:.2f} | {gap:+.2f} |"
            )
    print("\n| capture | views | Plenoxels static | ours varying | gap dB |\n|---|---:|---:|---:|---:|")
    for name, rows in results.items():
        static, ours = np.mean([r["static"] for r in rows]), np.mean([r["ours"] for r in rows])
        print(f"| {name} | {len(rows)} | {static:.2f} | {ours:.2f} | {static - ours:+.2f} |")
    print("\n| EV | views | mean gap dB |\n|---:|---:|---:|")
    for ev in sorted(by_ev):
        print(f"| {ev:+g} | {len(by_ev[ev])} | {np.mean(by_ev[ev]):+.2f} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
