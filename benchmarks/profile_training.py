"""Where a training run's step goes, level by level: each grid level of a preset's schedule (scaled down
in steps, as `run.py`'s paper-synthetic estimate is) timed over a few steps, then the same number of steps
under torch's profiler, its kernels listed by time.

`profile_step.py` times the kernels of one benchmark problem; this times the trainer's whole step (the
batch, the tone mapper, the regularisers, the optimisers) at each level of a real schedule, with or
without the CUDA graph, which is where the steps of `paper-synthetic` differ from one another. On CUDA
the table lists GPU kernels (torch's and Warp's, from CUPTI) with their device time; on a CPU, torch's
operators with their own CPU time (Warp's CPU kernels are not torch operators and do not appear, so
the listed time falls short of the step's).

Usage: python benchmarks/profile_training.py DATA [--preset paper-synthetic] [--scale 400] [--steps 6]
       [--graph] [--device auto] [--rows 8] [--json F]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402
from run import scaled_preset  # noqa: E402

from hdrplenoxels.train.config import TrainConfig  # noqa: E402

WARMUP = 4  # steps a level runs before its timing: three eager steps and the graph's recording


def profile_levels(
    scene, cfg: TrainConfig, out: Path, steps: int, rows: int, on_level: Callable[[dict], None] | None = None
) -> dict[str, Any]:
    """Train `cfg` on `scene` into `out`; for each level, its last `2 * steps` steps: `steps` timed
    (synchronised, milliseconds a step), then `steps` under the profiler (the `rows` costliest kernels or
    operators a step). `on_level` is handed the report so far after each level (a caller that may be
    stopped keeps what is done)."""
    from hdrplenoxels.train.trainer import Trainer

    every, n = cfg.grid.upsample_every, cfg.optim.n_iters
    levels = len(cfg.grid.reso_schedule)
    bounds = [(i * every, (i + 1) * every if i < levels - 1 else n) for i in range(levels)]
    short = [b - a for a, b in bounds if b - a < WARMUP + 2 * steps]
    if short:
        raise ValueError(
            f"a level of {min(short)} steps cannot hold {WARMUP} warm-up, {steps} timed and {steps} profiled "
            "steps: lower --steps or --scale"
        )
    trainer = Trainer(scene, cfg, out, overwrite=True)
    cuda = trainer.device.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)

    def advance(count: int) -> None:
        for _ in range(count):
            trainer.train_step()
            trainer.upsample()

    report = []

    def so_far() -> dict[str, Any]:
        graph = trainer.step_graph
        return {
            "device": torch.cuda.get_device_name(trainer.device) if cuda else "cpu",
            "graph": graph is not None,
            "graph_failure": graph.failure if graph is not None else None,
            "view_prior_update": cfg.view_prior_update,
            "tv_layout": cfg.tv_layout,
            "owed_pay": cfg.owed_pay,
            "touched_update": cfg.touched_update,
            "steps": steps,
            "levels": list(report),
        }

    for level, (_, end) in enumerate(bounds):
        advance(end - 2 * steps - trainer.step)
        voxels = trainer.engine.log_fields(trainer.step).get("voxels")
        sync()
        t = time.perf_counter()
        advance(steps)
        sync()
        wall_ms = 1000 * (time.perf_counter() - t) / steps
        activities = [torch.profiler.ProfilerActivity.CPU]
        if cuda:
            activities.append(torch.profiler.ProfilerActivity.CUDA)
        with torch.profiler.profile(activities=activities) as prof:
            advance(steps - 1)
            trainer.train_step()  # the level's last step: its resample stays out of the profile
            sync()
        table = _costliest(prof, cuda, steps)
        entry = {"level": level, "reso": list(cfg.grid.reso_schedule[level]), "voxels": voxels}
        entry["view_prior"] = trainer._view_prior_weight() > 0  # its pull on every voxel: owed or dense
        entry |= {"wall_ms": wall_ms, "top": table[:rows]}
        if cuda:
            entry["kernel_ms"] = sum(r["ms"] for r in table)
        report.append(entry)
        if on_level is not None:
            on_level(so_far())
        trainer.upsample()
    return so_far()


def _costliest(prof, cuda: bool, steps: int) -> list[dict[str, Any]]:
    """On CUDA the kernels (device time), else torch's operators (own CPU time), per step, costliest first."""
    rows = []
    for evt in prof.key_averages():
        on_device = evt.device_type == torch.autograd.DeviceType.CUDA
        if cuda != on_device:
            continue
        us = evt.self_device_time_total if cuda else evt.self_cpu_time_total
        rows.append({"name": evt.key[:80], "ms": us / 1000 / steps, "calls": evt.count / steps})
    return sorted(rows, key=lambda r: -r["ms"])


def format_report(report: dict[str, Any]) -> list[str]:
    what = "kernels, device ms a step" if report["device"] != "cpu" else "torch operators, own CPU ms a step"
    graph = "from a CUDA graph" if report["graph"] else "launched from the host"
    pull = report.get("view_prior_update", "auto")
    tv = report.get("tv_layout", "auto")
    paying, touched = report.get("owed_pay", "auto"), report.get("touched_update", "auto")
    lines = [
        f"{report['device']}, steps {graph}, the view prior's pull {pull} (paid {paying}), touched rows "
        f"updated {touched}, TV layout {tv}; "
        f"{report['steps']} timed and {report['steps']} profiled a level"
    ]
    for lv in report["levels"]:
        reso = "x".join(map(str, lv["reso"]))
        busy = f", kernels {lv['kernel_ms']:.2f} ms" if "kernel_ms" in lv else ""
        prior = ", view prior on" if lv.get("view_prior") else ""
        lines.append(
            f"level {lv['level']} ({reso}, {lv['voxels']} voxels{prior}): {lv['wall_ms']:.2f} ms a step{busy}"
        )
        lines.append(f"  costliest {what}:")
        lines += [f"    {r['ms']:8.3f}  {r['calls']:5.1f}x  {r['name']}" for r in lv["top"]]
    return lines


def main() -> None:
    from hdrplenoxels.data import load_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="a dataset (e.g. `hdrplenoxels synth demo DIR`'s DIR/varying)")
    ap.add_argument("--preset", default="paper-synthetic")
    ap.add_argument("--scale", type=int, default=400, help="the preset's step counts divided by this")
    ap.add_argument("--reso-scale", type=int, default=1, help="its grid sides divided by this")
    ap.add_argument("--steps", type=int, default=6, help="steps timed, and steps profiled, at each level")
    ap.add_argument("--graph", action="store_true", help="replay the steps from a CUDA graph")
    ap.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")
    ap.add_argument("--rows", type=int, default=8, help="kernels or operators listed a level")
    ap.add_argument("--out", type=Path, default=Path("runs/profile-training"), help="the run's folder")
    ap.add_argument("--json", type=Path, help="also write the report here")
    args = ap.parse_args()
    cfg = scaled_preset(args.preset, args.scale, args.reso_scale)
    cfg.device, cfg.cuda_graph = args.device, args.graph
    report = profile_levels(load_scene(args.data), cfg, args.out, args.steps, args.rows)
    report |= {"preset": args.preset, "scale": args.scale, "reso_scale": args.reso_scale}
    print("\n".join(format_report(report)))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
