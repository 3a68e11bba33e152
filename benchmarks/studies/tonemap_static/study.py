"""What the tone mapper costs on photos taken with one fixed camera, against plain Plenoxels on the same
photos: the figure that decides whether `train` runs it by default (README beside this script).

For each preset and synthetic scene, the scene's validation render (`experiments.common.validation_root`:
other cameras than the experiments' test views, another capture seed) is captured with one fixed camera
(its `static` dataset) and trained twice, with the tone mapper (each `--variant` of its settings) and
without; scored on the validation views' right halves, their left halves calibrating each view's tone.
Real photos taken with one fixed camera (kermit's) are measured by `benchmarks/real_captures.py --methods
ours-photos plenoxels-photos --split validation`.

Usage: python benchmarks/studies/tonemap_static/study.py OUT [--scenes room objects360 ...]
       [--presets fast balanced] [--variants defaults lr=1e-3] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from hdrplenoxels.experiments.common import (
    PAPER_SCENES,
    ExperimentSettings,
    run_spec,
    scores,
    validation_root,
)
from hdrplenoxels.experiments.validation import DEFAULTS, parse_variant
from hdrplenoxels.train.runs import train_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--scenes", nargs="+", default=list(PAPER_SCENES))
    parser.add_argument("--presets", nargs="+", default=["fast", "balanced"])
    parser.add_argument("--variants", nargs="+", default=[DEFAULTS], help="tone settings, as `validation`'s")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    rows = []
    print(
        "| preset | scene | tone mapper | PSNR plain | PSNR tone-mapped | cost dB | s plain | s tone-mapped |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for preset in args.presets:
        s = ExperimentSettings(preset=preset, lpips=False, data_root=args.out / "data")
        for scene in args.scenes:
            root = validation_root(scene, s, args.out)
            runs = args.out / "runs" / preset / scene
            t0 = time.perf_counter()
            plain, data = train_spec(run_spec(root / "static", runs / "plain", s, tonemap=False))
            plain_s, plain_psnr = time.perf_counter() - t0, scores(plain, data, s)["psnr"]
            for i, variant in enumerate(args.variants):
                t0 = time.perf_counter()
                spec = run_spec(root / "static", runs / f"tonemapped{i}", s, tonemap=True,
                                tone_settings=parse_variant(variant))  # fmt: skip
                ours, data = train_spec(spec)
                ours_s, ours_psnr = time.perf_counter() - t0, scores(ours, data, s)["psnr"]
                row = {"preset": preset, "scene": scene, "variant": variant, "plain_psnr": plain_psnr,
                       "tonemapped_psnr": ours_psnr, "plain_s": plain_s, "tonemapped_s": ours_s}  # fmt: skip
                rows.append(row)
                print(
                    f"| {preset} | {scene} | {variant} | {plain_psnr:.2f} | {ours_psnr:.2f} | "
                    f"{plain_psnr - ours_psnr:+.2f} | {plain_s:.0f} | {ours_s:.0f} |",
                    flush=True,
                )
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
