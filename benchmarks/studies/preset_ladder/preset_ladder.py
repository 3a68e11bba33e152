"""What each preset of the CPU ladder costs and gives (JOURNAL.md, "The preset ladder").

Trains ours (the tone mapper, on the varying captures) on each synthetic scene rendered with its long
side at `--long-side` pixels, once per variant (a preset, optionally with overrides), and prints per scene
the training time (from the run's log: the steps, not loading the images), the peak resident memory of
the run's own process, and PSNR / SSIM on the test views' right halves, with each variant's gain over the
first (by default `fast`).

`--split validation` trains on the scenes' validation captures (other cameras, another seed: the ones
settings are chosen on); `--split test` on the experiments' captures (the ones reported), whose test views
are rendered at the scene's own sample count so that Monte Carlo noise does not cap the scores. Each run is a
fresh process, so peak memory is its own; run it on a quiet machine, since the times are wall clock.
Protocol: test views' left halves train their tone parameters, right halves are scored; every model is
the final step of its schedule.

Example: python benchmarks/studies/preset_ladder/preset_ladder.py --split validation --scenes room courtyard \
    --variant fast --variant "balanced" --variant "b-sh1:balanced:grid.sh_degree=1"
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
from dataclasses import replace
from pathlib import Path

from hdrplenoxels.experiments.common import (
    ExperimentSettings,
    config_for,
    scores,
    truth_root,
    validation_root,
)
from hdrplenoxels.synth.scenes import SCENES
from hdrplenoxels.train.run_folder import LOG_FILE
from hdrplenoxels.train.runs import RunSpec, train_spec


def parse_variant(text: str) -> tuple[str, str, tuple[str, ...]]:
    """'label:preset:key=value,key=value' (or 'preset') -> (label, preset, overrides)."""
    parts = text.split(":", 2)
    label, preset = parts[0], parts[1] if len(parts) > 1 else parts[0]
    overrides = tuple(parts[2].split(",")) if len(parts) > 2 and parts[2] else ()
    return label, preset, overrides


def scene_size(scene: str, long_side: int) -> tuple[int, int]:
    spec = SCENES[scene]
    scale = long_side / max(spec.width, spec.height)
    return round(spec.width * scale), round(spec.height * scale)


def train_and_score(spec: RunSpec, s: ExperimentSettings) -> dict:
    """Runs in its own process: train (or load) the run, score it, and report this process's peak RSS and
    the training time its log recorded (so a finished run that is only loaded keeps its own time)."""
    model, scene = train_spec(spec)
    log = (spec.run / LOG_FILE).read_text().splitlines()
    seconds = json.loads(log[-1])["seconds"]
    result = scores(model, scene, s)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    return {"seconds": seconds, "peak_gb": peak_gb, "psnr": result["psnr"], "ssim": result["ssim"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=("validation", "test"), required=True)
    parser.add_argument("--scenes", nargs="+", default=["room", "objects360", "extreme", "courtyard"])
    parser.add_argument("--variant", action="append", help="label:preset:overrides (default: fast, balanced)")
    parser.add_argument("--long-side", type=int, default=400)
    parser.add_argument("--views", type=int, default=50)
    parser.add_argument("--spp", type=int, default=32, help="Mitsuba samples per pixel of the truth")
    parser.add_argument(
        "--test-spp",
        type=int,
        default=None,
        help="--split test: samples per pixel of the scored test views (default: the scene's own, e.g. 512 "
        "for room); validation captures render every view at --spp",
    )
    parser.add_argument("--out", type=Path, default=Path("ladder"))
    args = parser.parse_args()
    variants = [parse_variant(v) for v in args.variant or ("fast", "balanced")]
    context = multiprocessing.get_context("spawn")
    results: dict = {}
    for scene in args.scenes:
        s = ExperimentSettings(
            n_views=args.views,
            resolution=scene_size(scene, args.long_side),
            spp=args.spp,
            test_spp=args.test_spp or SCENES[scene].spp,
            lpips=False,
            data_root=args.out / "data",
        )
        root = (validation_root if args.split == "validation" else truth_root)(scene, s, args.out)
        for label, preset, overrides in variants:
            run_settings = replace(s, preset=preset, overrides=overrides)
            cfg = config_for(run_settings, tonemap=True)
            spec = RunSpec(root / "varying", args.out / "runs" / args.split / scene / label, cfg)
            with context.Pool(1) as pool:
                r = pool.apply(train_and_score, (spec, run_settings))
            results.setdefault(scene, {})[label] = r | {"steps": cfg.optim.n_iters}
            base = results[scene][variants[0][0]]["psnr"]
            print(
                f"{scene:10s} {label:14s} {cfg.optim.n_iters:6d} steps {r['seconds']:7.1f} s "
                f"peak {r['peak_gb']:5.2f} GB  PSNR {r['psnr']:6.2f} (+{r['psnr'] - base:5.2f})  "
                f"SSIM {r['ssim']:.3f}",
                flush=True,
            )
    (args.out / f"ladder_{args.split}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
