"""The spike step as training takes it: `benchmarks/run.py`'s 128³ problem (forward, loss, backward, the
grid's update on the very engine objects the trainer uses) replayed from a CUDA graph, at each batch size,
with the default kernels and with each variant: milliseconds a step and train rays a second.

A variant is a switch the package already has, set for the variant's steps and put back after them:
`TrainConfig`'s (`touched_update`), the march's lanes per ray (`march_kernel.CUDA_LANES`: 0 is a thread
per ray) and its compiled kernel (`kernel_variant`'s `specialise`, `max_registers`, `shuffle_sum`,
`rays_per_block`, `rows_from_corners`).
Each variant's render after its steps is compared with the default's (close: CUDA's atomics add in any
order), so a variant that is fast and wrong says so. `make gpu-check`'s `step` section runs
this; on a CPU it runs the same steps eagerly (no graph), as CI's test does on a small grid.

Usage: python benchmarks/graph_step.py [--rays 5000 100000] [--variants default lanes-16 ...]
       [--again gpu_check.json] [--reso 128] [--steps 20] [--device cuda] [--json OUT.json]
`--again`: the variants that beat the default in a `make gpu-check` report's `step` section, again.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from statistics import median

import torch

BENCH = Path(__file__).resolve().parent

# name: (TrainConfig settings, lanes per ray (None: the device's default), the march's kernel choices)
VARIANTS: dict[str, tuple[dict, int | None, dict]] = {
    "default": ({}, None, {}),
    "touched-listed": ({"touched_update": "listed"}, None, {}),
    "threads": ({}, 0, {}),
    "lanes-16": ({}, 16, {}),
    "lanes-8": ({}, 8, {}),
    "shuffle-sum": ({}, None, {"shuffle_sum": True}),
    "rays-2x16": ({}, 16, {"rays_per_block": 2}),
    "rays-4x8": ({}, 8, {"rays_per_block": 4}),
    "rows-from-corners": ({}, None, {"rows_from_corners": True}),
    "specialised": ({}, None, {"specialise": True}),
    "registers-128": ({}, None, {"max_registers": 128}),
    "registers-96": ({}, None, {"max_registers": 96}),
}
BACKWARD_ONLY = ("rows_from_corners",)  # choices of the backward alone: the forward reads no rows back
EAGER_STEPS = 3  # steps run before a capture, as the trainer runs (`StepGraph`'s warm-up)


@contextlib.contextmanager
def variant_kernels(lanes: int | None, kernel: dict) -> Iterator[None]:
    """The march's lanes and compiled kernels (`specialise`, `max_registers`, `shuffle_sum`,
    `rays_per_block`; `BACKWARD_ONLY`'s to `accumulate_backward` alone) for the engine's calls, put back
    after."""
    from hdrplenoxels.kernels import march_kernel
    from hdrplenoxels.train.engines import warp_grid

    saved = (march_kernel.CUDA_LANES, warp_grid.render_forward, warp_grid.accumulate_backward)
    if lanes is not None:
        march_kernel.CUDA_LANES = lanes
    forward = {k: v for k, v in kernel.items() if k not in BACKWARD_ONLY}
    warp_grid.render_forward = functools.partial(saved[1], **forward)
    warp_grid.accumulate_backward = functools.partial(saved[2], **kernel)
    try:
        yield
    finally:
        march_kernel.CUDA_LANES, warp_grid.render_forward, warp_grid.accumulate_backward = saved


def spike_step(grid, o: torch.Tensor, d: torch.Tensor, settings: dict) -> tuple[Callable[[], None], Callable]:
    """(one training step of the rays on a copy of `grid`, a render of the rays by the same engine)."""
    from hdrplenoxels.render import RenderOptions
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.engines import build_engine
    from hdrplenoxels.train.optim import StepClock
    from hdrplenoxels.train.ray_pool import RayBatch

    cfg = TrainConfig(**settings)
    # Small constant rates: the grid stays what it was, so every timed step does the same work.
    cfg.optim.lr_sigma = cfg.optim.lr_sigma_final = 1e-3
    cfg.optim.lr_sh = cfg.optim.lr_sh_final = 1e-4
    cfg.optim.lr_sigma_delay_steps = 0
    cfg = cfg.resolved(background_brightness=0.0, wants_background=False, levels=grid.levels)
    grid = grid.to(grid.device)
    grid.density, grid.sh = grid.density.clone(), grid.sh.clone()
    engine = build_engine(grid, cfg, RenderOptions(background_brightness=0.0))
    target = torch.rand(o.shape[0], 3, generator=torch.Generator().manual_seed(0)).to(grid.device)
    index = torch.zeros(o.shape[0], dtype=torch.long, device=grid.device)
    batch = RayBatch(o, d, target, index, index, index)
    clock = StepClock.at(0, grid.device)

    def step() -> None:
        rgb, marched = engine.forward(batch)
        loss = ((rgb - marched.target) ** 2).mean()
        (g_rgb,) = torch.autograd.grad(loss, [rgb])
        engine.backward(g_rgb)
        engine.step(clock)

    return step, lambda: engine.render(o, d)


def replayed(step: Callable[[], None], device: torch.device) -> Callable[[], None]:
    """`step` as training runs it on `device`: on CUDA recorded after `EAGER_STEPS` eager steps and
    replayed from the graph (`train.step_graph.CudaCapture`); on a CPU, eagerly."""
    if device.type != "cuda":
        return step
    from hdrplenoxels.train.step_graph import CudaCapture

    capture = CudaCapture(torch.Generator(device=device))
    for _ in range(EAGER_STEPS):
        capture.eager(step)
    replay, _ = capture.record(step)
    return replay


def time_variant(name: str, grid, o: torch.Tensor, d: torch.Tensor, steps: int) -> tuple[dict, torch.Tensor]:
    """A variant's median step (ms, rays/s, over `steps` timed replays after one untimed) and its render
    of the rays after them."""
    settings, lanes, kernel = VARIANTS[name]
    device = o.device
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with variant_kernels(lanes, kernel):
        step, render = spike_step(grid, o, d, settings)
        t = time.perf_counter()
        run = replayed(step, device)
        run()
        sync()
        ready_s = time.perf_counter() - t
        times = []
        for _ in range(steps):
            t = time.perf_counter()
            run()
            sync()
            times.append(time.perf_counter() - t)
        image = render()
    ms = 1000 * median(times)
    return {"ms": ms, "train_rays_per_s": o.shape[0] / (ms / 1000), "first_steps_s": ready_s}, image


def graph_steps(
    rays: list[int],
    variants: list[str],
    reso: int,
    steps: int,
    device: str,
    on_run: Callable[[dict], None] | None = None,
) -> dict:
    """`time_variant` of each variant at each batch size on the spike problem of `reso`³; with each
    variant's largest image difference from the default's render. `on_run` is handed the results so far
    after each variant (a caller that may be stopped keeps what is done)."""
    sys.path.insert(0, str(BENCH))
    from run import spike_problem

    dev = torch.device(device)
    out: dict = {"reso": reso, "steps": steps, "graph": dev.type == "cuda", "runs": {}}
    for n in rays:
        grid, o, d, _ = spike_problem(n, reso)
        grid, o, d = grid.to(dev), o.to(dev), d.to(dev)
        reference = None
        for name in variants:
            key = f"{name}@{n}"
            try:
                result, image = time_variant(name, grid, o, d, steps)
            except Exception as error:  # noqa: BLE001 -- one variant's failure is a result, not the end
                out["runs"][key] = {"error": f"{type(error).__name__}: {error}"}
                continue
            if reference is None:
                reference = image
            result["max_image_difference"] = float((image - reference).abs().max())
            out["runs"][key] = result
            if on_run is not None:
                on_run(out)
            print(f"{key:>24}: {result['ms']:8.3f} ms a step, {result['train_rays_per_s']:12.0f} rays/s, "
                  f"image off by {result['max_image_difference']:.2e}", flush=True)  # fmt: skip
    return out


def winners(report: dict, largest_difference: float = 1e-3) -> list[str]:
    """The variants of a `make gpu-check` report's `step` section that beat the default's step at some
    batch size and rendered what it rendered, the default first: what a second call times again."""
    runs = report["sections"]["step"]["result"]["runs"]
    default = {key.split("@")[1]: run["ms"] for key, run in runs.items() if key.startswith("default@")}
    out = ["default"]
    for key, run in runs.items():
        name, size = key.split("@")
        if name in out or "error" in run or size not in default:
            continue
        if run["ms"] < default[size] and run["max_image_difference"] <= largest_difference:
            out.append(name)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, nargs="+", default=[5000, 100_000])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--again", type=Path, help="a gpu_check.json: time its step section's winners again")
    parser.add_argument("--reso", type=int, default=128)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    variants = winners(json.loads(args.again.read_text())) if args.again else args.variants
    print(f"variants: {' '.join(variants)}", flush=True)
    out = graph_steps(args.rays, variants, args.reso, args.steps, args.device)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
