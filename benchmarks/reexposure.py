"""Controllable exposure, measured: each of N training views of a run trained on a synthetic capture (taken
in turn from each exposure) rendered through the learned tone of every other, against what that view's true
camera would have photographed from there (`experiments.reexposure`). Printed by how many true stops the
two views' exposures are apart, beside the view's own tone against its own photo (0 stops) and the
picture left in its own tone against the other camera's (what a renderer without a tone module gives).

The pairs are training views (both tones were learned from whole photos); no test view is used.

Usage: python benchmarks/reexposure.py RUN DATA [RUN DATA ...] [--views 8] [--json OUT.json]
  e.g. RUN = TABLE_S1_OUT/runs/room/ours_varying, DATA = TABLE_S1_OUT/data/room/varying
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdrplenoxels.experiments.reexposure import camera_settings, reexposure
from hdrplenoxels.train.model import load_model


def spread_over_exposures(ids: list[int], evs: list[float], n: int) -> list[int]:
    """Up to `n` of `ids`, taken in turn from each exposure (so every pair of exposures is compared)."""
    groups: dict[float, list[int]] = defaultdict(list)
    for i in ids:
        groups[evs[i]].append(i)
    queues = [groups[ev] for ev in sorted(groups)]
    out: list[int] = []
    while len(out) < n and any(queues):
        for q in queues:
            if q and len(out) < n:
                out.append(q.pop(0))
    return out


def measure(run: Path, data: Path, views: int) -> dict[float, dict[str, float]]:
    """Per |stops| apart: mean PSNR through the other view's learned tone, and of the view's own tone
    against the other camera's photo, over every ordered pair of `views` training views taken in turn
    from each exposure."""
    model = load_model(run)
    cameras = camera_settings(data)
    ids = spread_over_exposures(list(model.train_ids), [c.ev for c in cameras], views)
    pairs = [(i, j) for i in ids for j in ids]
    rows: dict[float, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in reexposure(model, data, pairs):
        rows[abs(r.stops)]["reexposed"].append(r.psnr)
        rows[abs(r.stops)]["own_tone"].append(r.own_tone_psnr)
    return {
        stops: {"pairs": len(v["reexposed"]), **{k: float(np.mean(x)) for k, x in v.items()}}
        for stops, v in sorted(rows.items())
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", type=Path, help="RUN DATA, repeated")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if len(args.pairs) % 2:
        parser.error("give RUN DATA pairs")
    results = {}
    print("Training views only (no test view); PSNR against the true HDR through the other view's camera.")
    print("| run | stops apart | pairs | through the other view's tone | left in its own tone |")
    print("|---|---:|---:|---:|---:|")
    for run, data in zip(args.pairs[::2], args.pairs[1::2]):
        rows = measure(run, data, args.views)
        results[str(run)] = {f"{k:g}": v for k, v in rows.items()}
        for stops, v in rows.items():
            print(f"| {run} | {stops:g} | {v['pairs']} | {v['reexposed']:.2f} | {v['own_tone']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
