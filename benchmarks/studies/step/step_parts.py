"""Where a real run's step goes, part by part, with the view prior's update dense and owed.

`profile_training.py` trains a scaled schedule from scratch; this resumes a run of any size from one of
its checkpoints (`train --resume`'s state: a grid as a real schedule left it, at its level and step)
once per `view_prior_update` mode, each into a folder of its own, times `--steps` steps after three
warm-up steps, split into the step's parts (the batch, the engine's forward, backward, regularisers and
optimiser step, the tone loss and the tone optimiser, the between-steps work), and prints a digest of
the grid each leaves, which must agree (the two modes are the same training to the bit). The default
of 64 steps is one settling window of the owed pull (`warp_grid.OWED_SETTLE_EVERY`), so its dense
settle is in the mean. On CUDA the step runs without its graph (each part is launched and synchronised).

Usage: python benchmarks/studies/step/step_parts.py RUN DATA --work DIR [--checkpoint step_0006352.npz]
       [--steps 64] [--modes dense owed] [--json F]
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402

from hdrplenoxels.core.settings import apply_overrides  # noqa: E402
from hdrplenoxels.data import load_scene  # noqa: E402
from hdrplenoxels.train.config import TrainConfig  # noqa: E402
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR, checkpoints  # noqa: E402
from hdrplenoxels.train.trainer import Trainer  # noqa: E402

WARMUP = 3


def resumable_copy(run: Path, checkpoint: str | None, work: Path) -> Path:
    """`work` made a run folder holding `run`'s configuration and one of its checkpoints (the newest, or
    `checkpoint`), linked rather than copied where the file system allows."""
    found = [p for p in checkpoints(run) if checkpoint in (None, p.name)]
    if not found:
        raise SystemExit(f"{run / CHECKPOINT_DIR}: no checkpoint {checkpoint or ''}")
    if work.exists():
        shutil.rmtree(work)
    (work / CHECKPOINT_DIR).mkdir(parents=True)
    shutil.copy(run / "config.json", work / "config.json")
    target = work / CHECKPOINT_DIR / found[-1].name
    try:
        os.link(found[-1], target)
    except OSError:
        shutil.copy(found[-1], target)
    return work


def timed(parts: dict[str, float], sync: Callable[[], None], obj: Any, name: str, label: str) -> None:
    """`obj.name` replaced by itself timed into `parts[label]`."""
    inner = getattr(obj, name)

    def wrapper(*args, **kwargs):
        sync()
        t = time.perf_counter()
        out = inner(*args, **kwargs)
        sync()
        parts[label] = parts.get(label, 0.0) + time.perf_counter() - t
        return out

    setattr(obj, name, wrapper)


def grid_digest(trainer: Trainer) -> str:
    """A digest of the settled grid's density and SH."""
    field = trainer.model().field
    h = hashlib.sha256()
    for values in (field.density, field.sh):
        h.update(values.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def measure(run: Path, data: Path, checkpoint: str | None, work: Path, mode: str, steps: int) -> dict:
    cfg = TrainConfig.from_dict(json.loads((run / "config.json").read_text()))
    cfg = apply_overrides(cfg, {"view_prior_update": mode, "cuda_graph": False})
    scene = load_scene(data, cfg.data.downscale)
    trainer = Trainer(scene, cfg, resumable_copy(run, checkpoint, work), resume=True)
    try:
        sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
        parts: dict[str, float] = {}
        engine = trainer.engine
        for name in ("forward", "backward", "regularise", "step", "after_step"):
            timed(parts, sync, engine, name, name)
        timed(parts, sync, trainer.pool, "sample", "batch")
        if trainer.tonemapper is not None:
            timed(parts, sync, trainer.tonemapper, "training_loss", "tone loss")
        if trainer.tone_optimiser is not None:
            timed(parts, sync, trainer.tone_optimiser, "step", "tone step")
        for _ in range(WARMUP):
            trainer.train_step()
        first = trainer.step
        parts.clear()
        sync()
        t = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        sync()
        total = time.perf_counter() - t
        return {
            "mode": mode,
            "steps": [first, trainer.step],
            "voxels": engine.field.num_voxels,
            "owing": engine.optimiser.owing_pull,
            "ms_per_step": 1e3 * total / steps,
            "parts_ms": {k: 1e3 * v / steps for k, v in sorted(parts.items(), key=lambda kv: -kv[1])},
            "digest": grid_digest(trainer),
        }
    finally:
        trainer.lock.release()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run folder with checkpoints")
    ap.add_argument("data", type=Path, help="the data it was trained on")
    ap.add_argument("--work", type=Path, required=True, help="each mode's resumed copy goes under here")
    ap.add_argument("--checkpoint", default=None, help="a checkpoint's file name (default: the newest)")
    ap.add_argument("--steps", type=int, default=64)
    ap.add_argument("--modes", nargs="+", default=["dense", "owed"], choices=["dense", "owed", "auto"])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    for mode in args.modes:
        row = measure(args.run, args.data, args.checkpoint, args.work / mode, mode, args.steps)
        rows.append(row)
        gc.collect()
        print(
            f"{mode}: {row['ms_per_step']:.0f} ms a step, steps {row['steps'][0]}..{row['steps'][1]}, "
            f"{row['voxels']:,} voxels, owing {row['owing']}, grid {row['digest']}",
            flush=True,
        )
        for part, ms in row["parts_ms"].items():
            print(f"    {part:12s} {ms:8.1f} ms", flush=True)
    base = rows[0]["ms_per_step"]
    for row in rows[1:]:
        print(f"{row['mode']} / {rows[0]['mode']}: x{row['ms_per_step'] / base:.2f}")
    print("grids agree" if len({r["digest"] for r in rows}) == 1 else "GRIDS DIFFER")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
