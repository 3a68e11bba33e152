"""Training and rendering throughput and memory: the Warp path against the PyTorch reference, same rays.

Problems (each (problem, backend) pair runs in its own process, so its memory is its own):
  spike  the 128^3 problem the Warp backend was chosen on (docs/design.md, "Kernels"): a Gaussian blob
         (14.8 % of cells occupied), 27 SH coefficients, rays from a sphere of radius 2.5 aimed at the
         centre, 5000 per batch
  demo   the grid of a real training run of the built-in demo scene (synth demo, fast preset with the
         tone mapper), seen from its training cameras
  paper  a paper-size sparse grid: 512 x 512 x 256, about 4 % of voxels allocated (a shell and three
         blobs), 27 SH coefficients
`train` is forward + backward as the trainer does them (Warp: forward kernel, MSE, backward kernel into
preallocated per-thread gradient buffers; reference: the PyTorch renderer and autograd); `step` adds
the RMSProp update of density and SH (Warp: the fused kernel over the voxels the step touched, as
the trainer runs it once the view prior is off; reference: the dense PyTorch RMSProp, same result);
`update_ms` is the median of step minus train over the timed rounds, which run the three functions in
turn so that a slow spell of a shared machine hits them alike.
`peak_mb` is the peak memory over the timed steps above what was held before the problem was built
(kernels already loaded): on the CPU the process's resident memory, on CUDA torch's allocator (every
Warp array here is a torch tensor); `memory_ratio` divides it by parameters + gradients + optimiser
state (3 x density and SH) + links. `--device` picks CUDA when present (`auto`), else the CPU; every
problem is built on the CPU and moved there, and CUDA timings synchronise before reading the clock.

Also timed: one full `fast`-preset training run of the demo scene (what `make demo` trains three
times), the NeRF engine's training and render throughput at its CPU presets' sizes (`nerf-cpu`,
`nerf-fast`) on that scene's rays, with the minutes each preset's steps would take at that rate, and the
`paper-synthetic` preset scaled to this machine (on the demo scene, its step counts divided by
--paper-scale and its grid sides by --paper-reso-scale), with the time all 128 000 steps would take at
those sizes estimated from each level's seconds per step. Prints a table with Warp / reference ratios
and writes JSON.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from statistics import median

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402

PROBLEMS = ("spike", "demo", "paper")
BACKENDS = ("warp", "torch")
RAYS = {"spike": 5000, "demo": 4096, "paper": 1000}


# ----------------------------------------------------------------------------- problems
def spike_problem(n_rays: int, reso: int = 128):
    from hdrplenoxels.grid.sparse_grid import SparseGrid

    g = torch.Generator().manual_seed(1234)
    r = reso
    lin = torch.linspace(-1, 1, r)
    x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
    density = 20 * torch.exp(-(x**2 + y**2 + z**2) / 0.1)
    density[density < 0.25] = 0
    sh = torch.randn(r, r, r, 27, generator=g) * 0.1
    grid = SparseGrid.from_dense(density, sh, (0, 0, 0), (1, 1, 1))
    del density, sh
    o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 2.5
    d = torch.nn.functional.normalize(-o + 0.15 * torch.randn(n_rays, 3, generator=g), dim=-1)
    return grid, o, d, 0.0


def paper_problem(n_rays: int):
    """A 512 x 512 x 256 grid where only a shell and three blobs (and their 2-voxel rim) are allocated."""
    from hdrplenoxels.grid.sparse_grid import SparseGrid

    g = torch.Generator().manual_seed(7)
    reso = (512, 512, 256)
    axes = [torch.linspace(-1, 1, n) for n in reso]
    links = torch.full(reso, -1, dtype=torch.int32)
    density_slabs = []
    count = 0
    for i in range(reso[0]):  # slab by slab: the dense field would be 8 GB of SH
        x = axes[0][i]
        yy, zz = torch.meshgrid(axes[1], axes[2], indexing="ij")
        radius = torch.sqrt(x**2 + yy**2 + zz**2)
        field = 30.0 * torch.exp(-(((radius - 0.7) / 0.03) ** 2))
        for cx, cy, cz in ((0.2, 0.1, 0.0), (-0.3, 0.2, 0.1), (0.0, -0.3, -0.2)):
            field += 40.0 * torch.exp(-((x - cx) ** 2 + (yy - cy) ** 2 + (zz - cz) ** 2) / 0.004)
        keep = field > 0.5
        k = int(keep.sum())
        links[i][keep] = torch.arange(count, count + k, dtype=torch.int32)
        density_slabs.append(field[keep])
        count += k
    density = torch.cat(density_slabs)
    sh = torch.randn(count, 27, generator=g) * 0.1
    grid = SparseGrid(links, density, sh, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 2.5
    d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(n_rays, 3, generator=g), dim=-1)
    return grid, o, d, 0.0


def demo_problem(n_rays: int, run_dir: Path):
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.train.model import MODEL_FILE, Model
    from hdrplenoxels.train.ray_pool import RayPool

    model = Model.load(run_dir / MODEL_FILE)
    scene = load_scene(Path(model.data_path))
    pool = RayPool(scene.images, model.cameras, model.geometry, scene.train_ids, scene.test_ids,
                   "right-half", "cpu")  # fmt: skip
    batch = pool.sample(n_rays, torch.Generator().manual_seed(0))
    return model.grid, batch.origins, batch.dirs, model.render_opt.background_brightness


def make_problem(name: str, n_rays: int, demo_run: Path | None):
    if name == "spike":
        return spike_problem(n_rays)
    if name == "paper":
        return paper_problem(n_rays)
    return demo_problem(n_rays, demo_run)


# ----------------------------------------------------------------------------- one worker
def rss_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"{field} not in /proc/self/status")


def reset_peak() -> None:
    """Make VmHWM start again from the current resident size (Linux: clear_refs 5)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def step_functions(grid, o, d, background: float, backend: str):
    """(forward + backward, one training step, one render) over the rays `o`, `d` on the grid's device,
    timed on the very engine objects the trainer uses."""
    from hdrplenoxels.render import RenderOptions
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.engines import build_engine
    from hdrplenoxels.train.optim import StepClock
    from hdrplenoxels.train.ray_pool import RayBatch

    cfg = TrainConfig(backend=backend)
    # Small constant rates: the grid stays what it was, so every timed step does the same work.
    cfg.optim.lr_sigma = cfg.optim.lr_sigma_final = 1e-3
    cfg.optim.lr_sh = cfg.optim.lr_sh_final = 1e-4
    cfg.optim.lr_sigma_delay_steps = 0
    cfg = cfg.resolved(background_brightness=background, wants_background=False, levels=grid.levels)
    engine = build_engine(grid, cfg, RenderOptions(background_brightness=background))
    target = torch.rand(o.shape[0], 3, generator=torch.Generator().manual_seed(0)).to(grid.device)
    index = torch.zeros(o.shape[0], dtype=torch.long, device=grid.device)
    batch = RayBatch(o, d, target, index, index, index)

    def forward_backward():
        rgb, marched = engine.forward(batch)  # the Warp engine sorts each batch: the sort is timed
        loss = ((rgb - marched.target) ** 2).mean()
        (g_rgb,) = torch.autograd.grad(loss, [rgb])
        engine.backward(g_rgb)

    clock = StepClock.at(0, grid.device)

    def train_step():
        forward_backward()
        engine.step(clock)

    return {"render": lambda: engine.render(o, d), "train": forward_backward, "step": train_step}


def load_code(backend: str, device: torch.device) -> None:
    """Run both steps once on tiny grids, so that kernel loading and thread start-up are not counted
    as the problem's memory or time."""
    from hdrplenoxels.grid.sparse_grid import SparseGrid

    for basis_dim in (4, 9):
        grid = SparseGrid.create((6, 6, 6), basis_dim=basis_dim, device=device)
        o = torch.tensor([[0.1, 0.2, -3.0]] * 600, device=device)
        d = torch.tensor([[0.0, 0.0, 1.0]] * 600, device=device)
        for fn in step_functions(grid, o, d, 0.0, backend).values():
            fn()


class MemoryMeter:
    """Peak memory above a baseline: resident memory on the CPU, torch's allocator on CUDA."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.base_mb = self.now_mb()

    def now_mb(self) -> float:
        return torch.cuda.memory_allocated() / 2**20 if self.cuda else rss_mb("VmRSS")

    def reset_peak(self) -> None:
        if self.cuda:
            torch.cuda.reset_peak_memory_stats()
        else:
            reset_peak()

    def peak_mb(self) -> float:
        return (torch.cuda.max_memory_allocated() / 2**20 if self.cuda else rss_mb("VmHWM")) - self.base_mb


def round_robin(functions: dict[str, Callable[[], None]], repeats: int, sync: Callable[[], None]) -> dict:
    """Seconds of each function's `repeats` calls, after one warm-up call each (caches, optimiser
    state), taken in turn: a slow spell of a shared machine hits every function alike. `sync` waits for
    the device before and after each call."""
    for fn in functions.values():
        fn()
    times = {key: [] for key in functions}
    for _ in range(repeats):
        for key, fn in functions.items():
            sync()
            t = time.perf_counter()
            fn()
            sync()
            times[key].append(time.perf_counter() - t)
    return times


def worker(problem: str, backend: str, n_rays: int, repeats: int, demo_run: Path | None, device: str) -> dict:
    dev = torch.device(device)
    load_code(backend, dev)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    sync()
    gc.collect()
    meter = MemoryMeter(dev)
    grid, o, d, background = make_problem(problem, n_rays, demo_run)
    grid, o, d = grid.to(dev), o.to(dev), d.to(dev)
    gc.collect()
    functions = step_functions(grid, o, d, background, backend)
    meter.reset_peak()
    out = {}
    times = round_robin(functions, repeats, sync)
    for key, values in times.items():
        out[f"{key}_rays_per_s"] = n_rays / median(values)
    out["update_ms"] = 1000 * median([s - t for s, t in zip(times["step"], times["train"])])
    out["peak_mb"] = meter.peak_mb()
    param_mb = (grid.density.numel() + grid.sh.numel()) * 4 / 2**20
    out["params_grads_state_mb"] = 3 * param_mb + grid.links.numel() * 4 / 2**20
    out["memory_ratio"] = out["peak_mb"] / out["params_grads_state_mb"]
    out["rays"] = n_rays
    out["voxels"] = grid.num_voxels
    out["reso"] = list(grid.reso)
    return out


# ----------------------------------------------------------------------------- training runs
def synth_demo(root: Path) -> Path:
    subprocess.run([sys.executable, "-m", "hdrplenoxels", "synth", "demo", str(root)], check=True,
                   capture_output=True)  # fmt: skip
    return root


def timed_training(data: Path, out: Path, cfg, device: str) -> dict:
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.eval.evaluate import evaluate
    from hdrplenoxels.train.trainer import Trainer

    cfg.device = device
    scene = load_scene(data)
    t = time.perf_counter()
    model = Trainer(scene, cfg, out, overwrite=True).run(progress=False)
    seconds = time.perf_counter() - t
    psnr = evaluate(model, scene, lpips=False)["psnr"]
    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    return {"seconds": seconds, "steps": model.step, "psnr_right_halves": psnr, "log": log}


def demo_training(data: Path, out: Path, device: str) -> dict:
    from hdrplenoxels.train.presets import preset

    cfg = preset("fast")
    cfg.tonemap.enabled = True
    result = timed_training(data, out, cfg, device)
    del result["log"]
    return result


def scaled_preset(name: str, scale: int, reso_scale: int):
    """Preset `name` with every step count divided by `scale` and every grid side by `reso_scale`: the
    same levels and schedules in fewer steps, no checkpoints, eight log lines a level."""
    from hdrplenoxels.train.presets import preset

    full, cfg = preset(name), preset(name)
    cfg.grid.reso_schedule = [tuple(r // reso_scale for r in reso) for reso in full.grid.reso_schedule]
    cfg.optim.n_iters = full.optim.n_iters // scale
    cfg.grid.upsample_every = full.grid.upsample_every // scale
    cfg.optim.lr_decay_steps = full.optim.lr_decay_steps // scale
    cfg.optim.lr_sigma_delay_steps = full.optim.lr_sigma_delay_steps // scale
    cfg.checkpoint_every = 0
    cfg.log_every = max(1, cfg.grid.upsample_every // 8)
    return cfg


def paper_training(data: Path, out: Path, scale: int, reso_scale: int, device: str) -> dict:
    """The paper-synthetic schedule with every step count divided by `scale` and every grid side by
    `reso_scale` (the full 800 x 800 x 512 level does not fit a 24 GB machine: its resample was killed
    for memory), and the time all its steps would take at these sizes (`estimate_full_run`)."""
    from hdrplenoxels.train.presets import preset

    cfg = scaled_preset("paper-synthetic", scale, reso_scale)
    result = timed_training(data, out, cfg, device)
    levels, estimate = estimate_full_run(result.pop("log"), cfg, preset("paper-synthetic"))
    result.update(scale=scale, reso_scale=reso_scale, levels=levels, estimated_full_run_hours=estimate / 3600)
    return result


def estimate_full_run(log: list[dict], cfg, full) -> tuple[list[dict], float]:
    """Per level of a shortened run's `log` (train_log.jsonl entries of `cfg`, a `scaled_preset` of
    `full`): its typical step (the median over its logged intervals) and what it spent once beyond that
    (the resample and pruning that start it, which a shortened run would otherwise spread over too few
    steps); and the seconds `full`'s steps would take at those rates. A step costs more while the view
    prior acts (`TrainConfig.view_prior_end`: the update is dense then), and the prior ends at the same
    fraction of both schedules but not at a level's end, so a level's steps are priced by regime: the
    median of the intervals wholly before the prior's end (`step_seconds_prior`) and of those wholly
    after (`step_seconds_free`), the other regime's where it has none of one (the level's median where
    it has neither); the level's first interval, which holds its resample, counts only where its regime
    has no other."""
    every, last = cfg.grid.upsample_every, len(cfg.grid.reso_schedule) - 1
    end = math.ceil(cfg.view_prior_end())  # the steps s < view_prior_end take the prior: this many
    levels: dict[int, dict] = {}
    previous = (0, 0.0)
    for entry in log:
        level = min((entry["step"] - 1) // every, last)
        steps, seconds = entry["step"] - previous[0], entry["seconds"] - previous[1]
        agg = levels.setdefault(
            level,
            {"reso": list(cfg.grid.reso_schedule[level]), "steps": 0, "seconds": 0.0, "per_step": [],
             "prior": [], "free": []},
        )  # fmt: skip
        agg["steps"] += steps
        agg["seconds"] += seconds
        agg["per_step"].append(seconds / steps)
        if entry["step"] <= end or previous[0] >= end:  # wholly in one regime (steps previous .. step - 1)
            regime = agg["prior" if entry["step"] <= end else "free"]
            if len(agg["per_step"]) == 1:  # the level's first interval, which holds its resample
                agg["first"] = regime
            regime.append(seconds / steps)
        agg["voxels"] = entry["voxels"]
        previous = (entry["step"], entry["seconds"])
    full_end = math.ceil(full.view_prior_end())
    estimate = 0.0
    for level, lv in levels.items():
        lv["step_seconds"] = median(lv.pop("per_step"))
        first = lv.pop("first", None)  # left out where its regime has other intervals
        if first is not None and len(first) > 1:
            first.pop(0)
        rates = {regime: median(r) if (r := lv.pop(regime)) else None for regime in ("prior", "free")}
        for regime, other in (("prior", "free"), ("free", "prior")):  # a regime it lacks: the other's rate
            found = [r for r in (rates[regime], rates[other]) if r is not None]
            lv[f"step_seconds_{regime}"] = found[0] if found else lv["step_seconds"]
        start = level * every
        stop = start + lv["steps"]
        spent = _priced(start, stop, end, lv)
        lv["once_seconds"] = max(0.0, lv["seconds"] - spent)
        full_start = level * full.grid.upsample_every
        full_stop = full.optim.n_iters if level == last else full_start + full.grid.upsample_every
        estimate += _priced(full_start, full_stop, full_end, lv) + lv["once_seconds"]
    return list(levels.values()), estimate


def level_rates(lv: dict, fmt: str) -> str:
    """A level's line: its size and milliseconds a step, and with the view prior where that differs."""
    ms = {k: 1000 * lv.get(f"step_seconds_{k}", lv["step_seconds"]) for k in ("free", "prior")}
    rates = f"{ms['free']:{fmt}} ms/step" + (
        f" ({ms['prior']:{fmt}} with the view prior)" if ms["prior"] != ms["free"] else ""
    )
    return f"{'x'.join(map(str, lv['reso']))}: {rates}"


def _priced(start: float, stop: float, end: float, lv: dict) -> float:
    """Seconds of steps [start, stop) at a level's rates, those before `end` at its prior's rate."""
    prior = max(0.0, min(stop, end) - start)
    return prior * lv["step_seconds_prior"] + (stop - start - prior) * lv["step_seconds_free"]


NERF_PRESETS = ("nerf-cpu", "nerf-fast")


def nerf_rates(data: Path, device: str, repeats: int, preset_name: str) -> dict:
    """The NeRF engine at a preset's sizes on the demo scene's training rays, in batches of the preset's
    size: rays/s of a training step (forward, loss, backward, Adam) and of a render, medians of `repeats`
    timed batches, and what the preset's steps would take at that rate (training steps only)."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.data.placement import setup_scene
    from hdrplenoxels.render import RenderOptions
    from hdrplenoxels.train.engines import NerfEngine
    from hdrplenoxels.train.optim import StepClock
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.ray_pool import RayPool

    cfg = preset(preset_name)
    n_rays = cfg.optim.batch_size
    dev = torch.device(device)
    scene = load_scene(data)
    cams, geometry = setup_scene(scene)
    pool = RayPool(scene.images, cams, geometry, scene.train_ids, scene.test_ids, "right-half", dev)
    field = NerfEngine.new_field(cfg, geometry, len(cams), dev)
    engine = NerfEngine(field, cfg, RenderOptions(background_brightness=scene.background_brightness))
    batch = pool.sample(n_rays, torch.Generator().manual_seed(0))
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    clock = StepClock.at(0, dev)

    def train_step():
        rgb, rows = engine.forward(batch)
        (grad,) = torch.autograd.grad(torch.mean((rgb - rows.target) ** 2), [rgb])
        engine.backward(grad)
        engine.step(clock)

    functions = {"train": train_step, "render": lambda: engine.render(batch.origins, batch.dirs)}
    times = round_robin(functions, repeats, sync)
    step = median(times["train"])
    return {
        "preset": preset_name,
        "rays": n_rays,
        **{f"{k}_rays_per_s": n_rays / median(v) for k, v in times.items()},
        "step_ms": 1000 * step,
        "steps": cfg.optim.n_iters,
        "estimated_run_minutes": cfg.optim.n_iters * step / 60,
    }


# ----------------------------------------------------------------------------- main
def run_worker(problem: str, backend: str, args, demo_run: Path | None) -> dict:
    cmd = [sys.executable, __file__, "--worker", problem, backend, "--repeats", str(args.repeats),
           "--device", args.device]  # fmt: skip
    if args.rays:
        cmd += ["--rays", str(args.rays)]
    if demo_run is not None:
        cmd += ["--demo-run", str(demo_run)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{problem}/{backend} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def print_table(device: str, results: dict, training: dict) -> None:
    print(f"device: {device}; rays/s of the median timed batch")
    print("train = forward + backward; step = train + RMSProp update; update ms: step - train, paired")
    print("peak/(P+G+S): see the docstring")
    keys = ("train", "step", "render")
    head = f"{'problem':<8}{'backend':<8}{'rays':>6}" + "".join(f"{k + ' rays/s':>15}" for k in keys)
    print(head + f"{'update ms':>11}{'peak MB':>9}{'peak/(P+G+S)':>14}")
    for problem, by_backend in results.items():
        for backend, r in by_backend.items():
            row = f"{r['rays']:>6}" + "".join(f"{r[k + '_rays_per_s']:>15.0f}" for k in keys)
            row += f"{r['update_ms']:>11.1f}"
            print(f"{problem:<8}{backend:<8}{row}{r['peak_mb']:>9.0f}{r['memory_ratio']:>14.2f}")
        if len(by_backend) == 2:
            w, t = by_backend["warp"], by_backend["torch"]
            ratios = "".join(f"{w[k + '_rays_per_s'] / t[k + '_rays_per_s']:>14.1f}x" for k in keys)
            print(f"{problem:<8}{'ratio':<8}{'':>6}{ratios}")
    if "demo" in training:
        r = training["demo"]
        print(f"demo training run (fast preset, tone mapping): {r['seconds']:.1f} s for {r['steps']} steps, "
              f"{r['psnr_right_halves']:.2f} dB on right halves")  # fmt: skip
    for r in training.get("nerf", []):
        print(f"NeRF engine ({r['preset']}, {r['rays']} rays): train {r['train_rays_per_s']:.0f} rays/s "
              f"({r['step_ms']:.0f} ms/step; {r['steps']} steps: {r['estimated_run_minutes']:.1f} min), "
              f"render {r['render_rays_per_s']:.0f} rays/s")  # fmt: skip
    if "paper_synthetic_scaled" in training:
        r = training["paper_synthetic_scaled"]
        levels = ", ".join(level_rates(lv, ".0f") for lv in r["levels"])
        print(f"paper-synthetic preset, 1/{r['scale']} of its steps, grid sides / {r['reso_scale']}:")
        print(f"  {r['seconds']:.0f} s ({levels});")
        print(
            f"  all 128 000 steps at these sizes: about {r['estimated_full_run_hours']:.1f} h on this machine"
        )


def checked_device(name: str) -> str:
    """The trainer's device choice (`auto`: CUDA when present); a missing GPU ends the run with one line."""
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.core.errors import InputError

    try:
        return str(pick_device(name))
    except InputError as e:
        sys.exit(f"error: {e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default="bench.json", help="where to write the results")
    ap.add_argument("--repeats", type=int, default=3, help="timed steps per measurement (median)")
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS)
    ap.add_argument("--paper-scale", type=int, default=400, help="divide the paper preset's steps by this")
    ap.add_argument("--paper-reso-scale", type=int, default=4, help="divide its grid sides by this")
    ap.add_argument("--no-training", action="store_true", help="skip the two timed training runs")
    ap.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")
    ap.add_argument("--demo-data", type=Path, help="an existing `hdrplenoxels synth demo` folder to use")
    ap.add_argument("--rays", type=int, help="rays per batch for every problem (default: per problem)")
    ap.add_argument("--worker", nargs=2, metavar=("PROBLEM", "BACKEND"), help=argparse.SUPPRESS)
    ap.add_argument("--demo-run", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.device = checked_device(args.device)
    if args.worker:
        problem, backend = args.worker
        n_rays = args.rays or RAYS[problem]
        print(json.dumps(worker(problem, backend, n_rays, args.repeats, args.demo_run, args.device)))
        return
    from hdrplenoxels.core.parallel import cpu_workers

    if args.device.startswith("cuda"):
        device = torch.cuda.get_device_name(torch.device(args.device))
    else:
        device = f"cpu ({cpu_workers()} threads)"
    training: dict[str, dict] = {}
    results: dict[str, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory(prefix="hdrplenoxels-bench-") as tmp:
        demo_run = None
        if "demo" in args.problems or not args.no_training:
            data = (args.demo_data or synth_demo(Path(tmp) / "data")) / "varying"
            demo_run = Path(tmp) / "demo-run"
            training["demo"] = demo_training(data, demo_run, args.device)
            training["nerf"] = [nerf_rates(data, args.device, args.repeats, p) for p in NERF_PRESETS]
            if not args.no_training:
                training["paper_synthetic_scaled"] = paper_training(
                    data, Path(tmp) / "paper-run", args.paper_scale, args.paper_reso_scale, args.device
                )
        for problem in args.problems:
            results[problem] = {b: run_worker(problem, b, args, demo_run) for b in args.backends}
    print_table(device, results, training)
    report = {"device": device, "threads": os.environ.get("OMP_NUM_THREADS"), "results": results,
              "training_runs": training}  # fmt: skip
    Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
