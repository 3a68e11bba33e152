"""`make gpu-check`: what the package claims on an NVIDIA GPU, checked in one device call of at most
8 minutes and written as `gpu_check.json` and `gpu_check.md` (JOURNAL.md, "Checking a GPU").

Sections, in this order, each in its own process under its own time limit; the summary is rewritten
after every section, so a late failure or the call's end loses nothing already measured, and the `step`
and `levels` sections write their results as each variant or level ends, so one stopped at its limit
keeps what it finished:
  env        the GPU, its driver, torch, Warp and CUDA versions
  parity     every kernel family's parity tests with the Warp path on CUDA and the PyTorch oracle on
             the CPU (tests/devices.py), and the trainer's tests on CUDA
  step       benchmarks/graph_step.py: the spike step from the CUDA graph at the training batch and at
             100 000 rays, with the default kernels and each variant (lanes, compiled kernel, listed rows)
  bench      benchmarks/run.py, Warp: the spike and demo problems, the demo `fast` run, the NeRF
             engine's CPU presets, and the paper-synthetic schedule scaled down in steps
  balanced   a `balanced` run (tone mapping on) of the built-in demo scene, each kernel launched from the
             host (`cuda_graph=false`): wall time, right-half PSNR
  graph      the same run as users get it: the step's repeating part replayed from a CUDA graph
  capture    `balanced` on a real capture's kit (--capture-data, benchmarks/capture_kit.py): wall time and
             its test views' right halves (only with --capture-data)
  viewer     the viewer's frame at 800 x 800 (render and display) from the balanced run
  reference  benchmarks/run.py, the PyTorch reference on the same GPU (spike): the ratio
  lanes      the spike problem's forward + backward with 0 (thread per ray), 8, 16 and 32 lanes per ray
  kernels    the same with each kernel variant (general, specialised, registers capped), and their compiles
  nerf       the NeRF engine at the paper-synthetic preset's sizes
  large      100 000-ray batches (spike, paper), Warp
  profile    benchmarks/profile_step.py on the spike problem: where a step's time goes
  ncu        benchmarks/ncu_march.py: Nsight Compute's counters over one spike step (default kernels)
  levels     benchmarks/profile_training.py: paper-synthetic's whole step at each level, from the CUDA
             graph, from the graph with the view prior's pull dense (not owed), from
             the graph with the TV a thread per (cell, channel) (`tv_layout`), and from the graph with
             the rows that owe the pull and the touched rows listed first (`owed_pay`, `touched_update`),
             and launched from the host, with its costliest kernels

Where torch sees no CUDA device it says so and exits 0 (CI runs it so). The device image lacks
pycolmap, Mitsuba, viser and PyAV: nothing here imports them, and the demo scene (rendered with
Mitsuba) is made beforehand and passed as --demo-data.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from statistics import median

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "benchmarks"
# The demo sections' run folders under --work; the viewer section shows whichever of them ran.
GRAPH_RUN, BALANCED_RUN = "graph-run", "balanced-run"

# The test files whose kernels run on tests/devices.py's FAST_DEVICE, and the trainer's.
PARITY_TESTS = (
    "test_render_parity.py",
    "test_render_acceleration.py",
    "test_near_gradient.py",
    "test_cascade.py",
    "test_grid.py",
    "test_background.py",
    "test_distortion.py",
    "test_tv.py",
    "test_optim.py",
    "test_ray_order.py",
    "test_depth_opacity.py",
    "test_free_space.py",
    "test_gradient_parts.py",
    "test_train.py",
    "test_sync_free_step.py",
    "test_step_graph.py",
    "test_kernel_variants.py",
    "test_tone_loss.py",
    "test_ray_draw.py",
    "test_read_rows.py",
    "test_owed_pull.py",
    "test_mark_touched.py",
)

# Seconds each section may take on an H100; one starts only while a third of that is left before the
# deadline, and stops at whichever comes first.
SECTIONS = {
    "env": 60,
    "parity": 200,
    "step": 150,
    "bench": 200,
    "balanced": 150,
    "graph": 150,
    "capture": 150,
    "viewer": 60,
    "reference": 60,
    "lanes": 60,
    "kernels": 150,
    "nerf": 60,
    "fused": 60,
    "large": 90,
    "profile": 60,
    "ncu": 120,
    "levels": 320,
}

# The targets of the issue on GPU-native training, for one H100.
TARGETS = {
    "spike_step_rays_per_s": 5e6,
    "paper_synthetic_minutes": 5.0,
    "balanced_seconds": 8.0,
    "capture_seconds": 15.0,
    "viewer_fps": 30.0,
}


# ----------------------------------------------------------------------------- sections (run in workers)
def section_env(args) -> dict:
    import torch
    import warp as wp

    wp.init()
    out = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "warp": wp.__version__,
        "warp_cuda_devices": wp.get_cuda_device_count(),
    }
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        out.update(
            gpu=props.name,
            multiprocessors=props.multi_processor_count,
            memory_gb=round(props.total_memory / 2**30, 1),
        )
    try:
        smi = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        out["driver"] = smi.stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        out["driver"] = None
    out["disk_write_mb_per_s"] = disk_write_rate(args.work)
    return out


def disk_write_rate(folder: Path, megabytes: int = 256) -> float:
    """MB/s of a synced write in `folder`, where runs write: a run's checkpoints and model are gigabytes,
    written with fsync, which on a GPU can take longer than its steps."""
    path, block = folder / "disk-rate.tmp", os.urandom(2**20)
    t = time.perf_counter()
    with open(path, "wb") as f:
        for _ in range(megabytes):
            f.write(block)
        f.flush()
        os.fsync(f.fileno())
    seconds = time.perf_counter() - t
    path.unlink()
    return megabytes * 2**20 / 1e6 / seconds


def train_demo(
    data: Path, run: Path, preset_name: str, device: str, steps: int | None, cuda_graph: bool = False
) -> dict:
    import torch

    from hdrplenoxels.data import load_scene
    from hdrplenoxels.eval.evaluate import evaluate
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.run_folder import LOG_FILE
    from hdrplenoxels.train.trainer import Trainer

    cfg = preset(preset_name)
    cfg.tonemap.enabled = True
    cfg.device = device
    cfg.cuda_graph = cuda_graph
    if steps:  # the plumbing check on a CPU: a shortened schedule
        cfg.optim.n_iters = steps
        cfg.grid.upsample_every = max(1, steps // len(cfg.grid.reso_schedule))
    scene = load_scene(data)
    t = time.perf_counter()
    trainer = Trainer(scene, cfg, run, overwrite=True)
    model = trainer.run(progress=False)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t
    psnr = evaluate(model, scene, lpips=False)["psnr"]
    out = {"preset": preset_name, "steps": model.step, "seconds": seconds, "psnr_right_halves": psnr}
    # from the loop's start to its last step; the rest of `seconds` is the set-up and the end (the final
    # checkpoint, the tone controller's fit, the model's save)
    out["steps_seconds"] = json.loads((run / LOG_FILE).read_text().splitlines()[-1])["seconds"]
    if trainer.step_graph is not None:
        out.update(graph_captures=trainer.step_graph.captures, graph_failure=trainer.step_graph.failure)
    if device.startswith("cuda"):
        out["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def section_balanced(args) -> dict:
    return train_demo(
        args.demo_data / "varying", args.work / BALANCED_RUN, "balanced", args.device, args.quick_steps
    )


def section_graph(args) -> dict:
    """`balanced` again with `cuda_graph` on, the default (a CPU has none: there it runs as `balanced`)."""
    data, run = args.demo_data / "varying", args.work / GRAPH_RUN
    return train_demo(data, run, "balanced", args.device, args.quick_steps, cuda_graph=True)


def section_capture(args) -> dict:
    """`balanced` with tone mapping, as users train it (from the CUDA graph), on a real capture carried as
    a kit (benchmarks/capture_kit.py): its wall time and its test views' right halves."""
    data, run = args.capture_data, args.work / "capture-run"
    out = train_demo(data, run, "balanced", args.device, args.quick_steps, cuda_graph=True)
    return out | {"capture": data.name}


def demo_model(work: Path) -> Path:
    """The demo's trained model that the viewer section shows: the `graph` section's (the default way to
    train), else the `balanced` one's, whichever of the two ran before it."""
    from hdrplenoxels.train.model import MODEL_FILE

    for run in (GRAPH_RUN, BALANCED_RUN):
        if (work / run / MODEL_FILE).is_file():
            return work / run / MODEL_FILE
    raise FileNotFoundError(f"{work}: no trained demo to view; run the `graph` or `balanced` section first")


def section_viewer(args) -> dict:
    """The viewer's full-size frame: `Model.render_view` as the server calls it, then the display."""
    import math

    import numpy as np
    import torch

    from hdrplenoxels.train.model import Model
    from hdrplenoxels.viewer.display import ViewState, display_image
    from hdrplenoxels.viewer.server import intrinsics_for

    model = Model.load(demo_model(args.work), device=args.device)
    size = (args.viewer_size, args.viewer_size)
    state = ViewState()
    c2w = np.asarray(model.cameras.c2w[0])
    fov = 2.0 * math.atan(0.5 * model.cameras.size(0)[1] / model.cameras.intrinsics[0][1])
    k = intrinsics_for(fov, *size)
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)

    def frame() -> None:
        display_image(model, model.render_view(c2w, k, size).cpu(), state)
        sync()

    frame()  # kernels loaded
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        frame()
        times.append(time.perf_counter() - t)
    ms = 1000 * median(times)
    return {"size": list(size), "frame_ms": ms, "fps": 1000 / ms, "frames": len(times)}


def _spike_timer(args):
    """The spike problem on the device (grid, all rays, the training batch's rays, render options,
    gradient buffers, upstream gradient) and a function timing a callable: the median of
    `args.repeats` synchronised runs after one untimed run (which compiles and loads its kernels)."""
    import torch

    sys.path.insert(0, str(BENCH))
    from run import make_problem

    from hdrplenoxels.kernels.grad_buffers import GridGradients
    from hdrplenoxels.render import RenderOptions

    dev = torch.device(args.device)
    grid, o_all, d_all, _ = make_problem("spike", max(args.spike_rays, *args.render_rays), None)
    grid, o_all, d_all = grid.to(dev), o_all.to(dev), d_all.to(dev)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def seconds(fn) -> float:
        fn()
        times = []
        for _ in range(args.repeats):
            sync()
            t = time.perf_counter()
            fn()
            sync()
            times.append(time.perf_counter() - t)
        return median(times)

    o, d = o_all[: args.spike_rays], d_all[: args.spike_rays]
    problem = (grid, o_all, d_all, o, d, RenderOptions(background_brightness=0.0), GridGradients(grid))
    return problem, torch.full_like(o, 1e-3), sync, seconds


def section_lanes(args) -> dict:
    """The spike problem's forward + backward with each kernel family at the training batch size, and
    its forward alone at growing batches with a thread and a warp per ray: where `lanes_for`'s switch
    to a thread per ray should sit."""
    from hdrplenoxels.kernels.march_kernel import accumulate_backward, render_forward

    (grid, o_all, d_all, o, d, opt, grads), g_rgb, _, seconds = _spike_timer(args)

    def step(lanes: int) -> None:
        rgb = render_forward(grid, o, d, opt, lanes=lanes)
        accumulate_backward(grid, o, d, rgb, g_rgb, opt, grads, lanes=lanes)

    out = {"rays": o.shape[0]}
    for lanes in args.lanes:
        out[f"lanes_{lanes}_train_rays_per_s"] = o.shape[0] / seconds(lambda lanes=lanes: step(lanes))
    for n in args.render_rays:
        for lanes in (0, 32):
            rate = n / seconds(
                lambda n=n, lanes=lanes: render_forward(grid, o_all[:n], d_all[:n], opt, lanes=lanes)
            )
            out[f"render_{n}_lanes_{lanes}_rays_per_s"] = rate
    return out


# The kernel variants the `kernels` section times (`kernels.march_kernel.kernel_variant`): specialise,
# register cap.
KERNEL_CHOICES = {
    "general": (False, None),
    "specialised": (True, None),
    "registers_128": (False, 128),
    "registers_96": (False, 96),
    "registers_64": (False, 64),
}


def section_kernels(args) -> dict:
    """The spike problem's forward + backward (each device's default lanes) and its largest forward
    batch with each kernel variant: general, fixed to the launch's features, and with a thread's
    registers capped (benchmarks/kernel_resources.py gives each one's registers and local memory).
    Each variant's first call, which compiles it, is timed too: what a variant costs a run."""
    from hdrplenoxels.kernels.march_kernel import accumulate_backward, render_forward

    (grid, o_all, d_all, o, d, opt, grads), g_rgb, sync, seconds = _spike_timer(args)
    out = {"rays": o.shape[0], "render_rays": o_all.shape[0]}
    for name, (specialise, cap) in KERNEL_CHOICES.items():
        choice = {"specialise": specialise, "max_registers": cap}

        def step(choice=choice) -> None:
            rgb = render_forward(grid, o, d, opt, **choice)
            accumulate_backward(grid, o, d, rgb, g_rgb, opt, grads, **choice)

        sync()
        t = time.perf_counter()
        step()
        sync()
        out[f"{name}_first_call_s"] = time.perf_counter() - t
        out[f"{name}_train_rays_per_s"] = o.shape[0] / seconds(step)
        render = o_all.shape[0] / seconds(
            lambda choice=choice: render_forward(grid, o_all, d_all, opt, **choice)
        )
        out[f"{name}_render_rays_per_s"] = render
    return out


def section_nerf(args) -> dict:
    sys.path.insert(0, str(BENCH))
    from run import nerf_rates

    return nerf_rates(args.demo_data / "varying", args.device, args.repeats, "paper-synthetic")


def section_levels(args) -> dict:
    """`paper-synthetic`, scaled down in steps as `bench` runs it, profiled at each level's end
    (benchmarks/profile_training.py): with every kernel launched, then from the CUDA graph."""
    sys.path.insert(0, str(BENCH))
    from profile_training import profile_levels
    from run import scaled_preset

    from hdrplenoxels.data import load_scene

    scene = load_scene(args.demo_data / "varying")
    out = {}
    # launched, from the graph, and from the graph with the view prior's pull dense rather than owed (the
    # levels it acts on: what owing it is worth in whole steps, marking march and paying passes included),
    # and from the graph with each kernel variant (`TrainConfig`'s layouts; parity held on the CPU)
    # (the listed run lists the rows both of its passes visit: each kernel's time is in its table)
    # (launched last: the graph's gain over it was measured on 2026-11-27; a deadline cuts it first)
    for name, graph, pull, tv, rows in (
        ("graph", True, "auto", "auto", "auto"),
        ("graph-dense", True, "dense", "auto", "auto"),
        ("graph-tv-channel", True, "auto", "channel", "auto"),
        ("graph-listed", True, "auto", "auto", "listed"),
        ("launched", False, "auto", "auto", "auto"),
    ):
        cfg = scaled_preset("paper-synthetic", args.paper_scale, args.paper_reso_scale)
        cfg.device, cfg.cuda_graph, cfg.view_prior_update = args.device, graph, pull
        cfg.tv_layout, cfg.owed_pay, cfg.touched_update = tv, rows, rows
        folder = args.work / f"levels-{name}"

        def level_done(report: dict, name: str = name) -> None:
            keep(args, out | {name: report})

        out[name] = profile_levels(scene, cfg, folder, steps=6, rows=8, on_level=level_done)
    return out


def keep(args, result: dict) -> None:
    """A worker section's results so far, written where its parent reads them: a section stopped at its
    time limit keeps every level or variant it finished."""
    if args.worker_out is not None:
        tmp = args.worker_out.with_suffix(".tmp")
        tmp.write_text(json.dumps(result))
        tmp.replace(args.worker_out)


def section_step(args) -> dict:
    """The spike step as training takes it, from the CUDA graph, at the training batch and at 100 000
    rays, with the default kernels and each variant (benchmarks/graph_step.py)."""
    sys.path.insert(0, str(BENCH))
    from graph_step import VARIANTS, graph_steps

    sizes = [args.spike_rays, args.large_rays]
    return graph_steps(sizes, list(VARIANTS), 128, args.repeats * 3, args.device, lambda out: keep(args, out))


def section_fused(args) -> dict:
    """The fused kernels (the tone mapper's loss and gradients, the ray draw) against the PyTorch
    operators they replace, at the training batch and at 100 000 rays, launched and from a CUDA graph
    (benchmarks/fused_kernels.py)."""
    sys.path.insert(0, str(BENCH))
    from fused_kernels import fused_kernel_times

    return fused_kernel_times(args.device, (args.spike_rays, 100_000), args.repeats)


SECTION_FUNCTIONS = {
    "env": section_env,
    "step": section_step,
    "levels": section_levels,
    "balanced": section_balanced,
    "graph": section_graph,
    "capture": section_capture,
    "viewer": section_viewer,
    "lanes": section_lanes,
    "kernels": section_kernels,
    "nerf": section_nerf,
    "fused": section_fused,
}


# ----------------------------------------------------------------------------- sections (subcommands)
def parity_command(args) -> tuple[list[str], dict]:
    files = [str(ROOT / "tests" / f) for f in (args.parity_files or PARITY_TESTS)]
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        "-q",
        "-p",
        "no:cacheprovider",
        *(["-x"] if args.quick else []),
        f"--junitxml={args.work / 'parity.xml'}",
        *files,
    ]
    return cmd, {"HDRPLENOXELS_TEST_DEVICE": args.device}


def parse_junit(path: Path) -> dict:
    root = ET.parse(path).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    failed = []
    for case in suite.iter("testcase"):
        for tag in ("failure", "error"):
            bad = case.find(tag)
            if bad is not None:
                message = (bad.get("message") or "").splitlines()[:1]
                failed.append(f"{case.get('classname')}::{case.get('name')}: {''.join(message)[:300]}")
    return {key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors", "skipped")} | {
        "seconds": float(suite.get("time", 0.0)),
        "failed": failed,
    }


def bench_command(args, name: str) -> list[str]:
    cmd = [
        sys.executable,
        str(BENCH / "run.py"),
        "--device",
        args.device,
        "--json",
        str(args.work / f"{name}.json"),
        "--demo-data",
        str(args.demo_data),
    ]
    repeats = ["--repeats", str(args.repeats)]
    if name == "bench":
        return (
            cmd
            + repeats
            + [
                "--problems",
                *args.problems,
                "--backends",
                "warp",
                "--paper-scale",
                str(args.paper_scale),
                "--paper-reso-scale",
                str(args.paper_reso_scale),
            ]
        )
    if name == "reference":
        return cmd + ["--repeats", "3", "--problems", "spike", "--backends", "torch", "--no-training"]
    return (
        cmd
        + repeats
        + [
            "--problems",
            "spike",
            "paper",
            "--backends",
            "warp",
            "--no-training",
            "--rays",
            str(args.large_rays),
        ]
    )


# ----------------------------------------------------------------------------- the driver
def run_section(name: str, args, limit: float, log) -> dict:
    """One section in its own process under `limit` seconds: status, seconds, result or error."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "src"), env.get("PYTHONPATH")]))
    env["PYTHONUNBUFFERED"] = "1"
    if name == "parity":
        cmd, extra = parity_command(args)
        env.update(extra)
    elif name in ("bench", "reference", "large"):
        cmd = bench_command(args, name)
    elif name == "ncu":
        cmd = [sys.executable, str(BENCH / "ncu_march.py"), "--out", str(args.work / "ncu"), "--problem",
               "spike", "--rays", str(args.spike_rays), "--steps", "1"]  # fmt: skip
    elif name == "profile":
        cmd = [
            sys.executable,
            str(BENCH / "profile_step.py"),
            "--device",
            args.device,
            "--problem",
            "spike",
            "--rays",
            str(args.spike_rays),
            "--rows",
            "20",
        ]
    else:
        result_file = args.work / f"{name}.result.json"
        cmd = [sys.executable, __file__, *args.argv, "--worker", name, "--worker-out", str(result_file)]
    t = time.perf_counter()
    log.write(f"\n===== {name}: {' '.join(cmd)}\n")
    log.flush()
    # A session of its own, so that a timeout ends the section's children too (run.py's workers, pytest):
    # left running, they would share the GPU with the sections after it.
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        cwd=ROOT,
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=limit)
        status = "ok" if proc.returncode == 0 else "failed"
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        status = "timeout"
    seconds = time.perf_counter() - t
    if proc.returncode and proc.returncode < 0 and status == "failed":  # a signal, as the OOM killer's
        output += f"\n{name}: killed by signal {-proc.returncode} (9: the out-of-memory killer, as a rule)"
    log.write(output)
    log.write(f"\n===== {name}: {status} (exit {proc.returncode}) in {seconds:.1f} s\n")
    log.flush()
    entry: dict = {"status": status, "seconds": round(seconds, 1)}
    try:
        if name == "parity":
            entry["result"] = parse_junit(args.work / "parity.xml")
        elif name in ("bench", "reference", "large"):
            entry["result"] = json.loads((args.work / f"{name}.json").read_text())
        elif name == "ncu":
            entry["result"] = json.loads((args.work / "ncu" / "ncu_summary.json").read_text())
        elif name == "profile":
            table = output.strip().splitlines()
            first = next(i for i, line in enumerate(table) if line.startswith("---"))
            entry["result"] = {"table": table[first:]}
        else:
            entry["result"] = json.loads(result_file.read_text())
    except (OSError, ValueError, ET.ParseError, AttributeError, StopIteration):
        if status == "ok":
            entry["status"] = "failed"
    if entry["status"] != "ok" or name == "parity":
        entry["output_tail"] = output[-4000:]
    return entry


def fmt_rate(x: float | None) -> str:
    if x is None:
        return "–"
    return f"{x / 1e6:.2f} M" if x >= 1e6 else f"{x / 1e3:.1f} k"


def headline(report: dict) -> list[tuple[str, str, str]]:
    """(figure, measured, target) rows of the summary's first table; a missing section reads '–'."""
    s = report["sections"]

    def get(section: str, *keys):
        value = s.get(section, {}).get("result")
        for key in keys:
            if not isinstance(value, (dict, list)):
                return None
            value = value[key] if isinstance(value, list) else value.get(key)
        return value

    rows = []
    parity = get("parity")
    if parity:
        bad = parity["failures"] + parity["errors"]
        rows.append(
            (
                "parity tests on CUDA",
                f"{parity['tests'] - bad - parity['skipped']} passed, {bad} failed, "
                f"{parity['skipped']} skipped",
                "all pass",
            )
        )
    spike = get("bench", "results", "spike", "warp")
    ref = get("reference", "results", "spike", "torch")
    if spike:
        ratio = f" ({spike['train_rays_per_s'] / ref['train_rays_per_s']:.0f}x the reference)" if ref else ""
        rows.append(
            (
                "spike 128³ train rays/s, 5000 rays",
                fmt_rate(spike["train_rays_per_s"]) + ratio,
                "",
            )
        )
        rows.append(
            (
                "spike step (with RMSProp) / render rays/s",
                f"{fmt_rate(spike['step_rays_per_s'])} / {fmt_rate(spike['render_rays_per_s'])}",
                f"step ≥ {fmt_rate(TARGETS['spike_step_rays_per_s'])}",
            )
        )
    large = get("large", "results", "spike", "warp")
    if large:
        rows.append(
            (
                f"spike train / step rays/s, {large['rays']} rays",
                f"{fmt_rate(large['train_rays_per_s'])} / {fmt_rate(large['step_rays_per_s'])}",
                "",
            )
        )
    paper = get("bench", "training_runs", "paper_synthetic_scaled")
    if paper:
        minutes = 60 * paper["estimated_full_run_hours"]
        rows.append(
            (
                "paper-synthetic, all 128 000 steps (estimated from each level's step time)",
                f"{minutes:.1f} min",
                f"≤ {TARGETS['paper_synthetic_minutes']:.0f} min",
            )
        )
    balanced = get("balanced")
    if balanced:
        rows.append(
            (
                "`balanced` on the demo scene (tone mapping), each kernel launched (`cuda_graph=false`)",
                f"{balanced['seconds']:.1f} s, {balanced['psnr_right_halves']:.2f} dB right halves",
                "",
            )
        )
    graph = get("graph")
    if graph:
        if graph.get("graph_failure"):
            held = f"capture failed: {graph['graph_failure']}"
        elif "graph_captures" in graph:
            held = f"{graph['graph_captures']} captures"
        else:
            held = "no graph (not on CUDA)"
        rows.append(
            (
                "the same from a CUDA graph (`cuda_graph`, the default)",
                f"{graph['seconds']:.1f} s, {graph['psnr_right_halves']:.2f} dB right halves; {held}",
                f"≤ {TARGETS['balanced_seconds']:.0f} s",
            )
        )
    capture = get("capture")
    if capture:
        rows.append(
            (
                f"`balanced` on {capture['capture']} (a real capture, tone mapping, from the graph)",
                f"{capture['seconds']:.1f} s ({capture['steps_seconds']:.1f} s of steps), "
                f"{capture['psnr_right_halves']:.2f} dB right halves",
                f"≤ {TARGETS['capture_seconds']:.0f} s",
            )
        )
    viewer = get("viewer")
    if viewer:
        rows.append(
            (
                f"viewer frame {viewer['size'][0]}x{viewer['size'][1]}",
                f"{viewer['frame_ms']:.1f} ms ({viewer['fps']:.1f} fps)",
                f"≥ {TARGETS['viewer_fps']:.0f} fps",
            )
        )
    nerfs = (get("bench", "training_runs", "nerf") or []) + ([get("nerf")] if get("nerf") else [])
    for n in nerfs:
        rows.append(
            (
                f"NeRF engine, {n['preset']} sizes ({n['rays']} rays) train / render rays/s",
                f"{fmt_rate(n['train_rays_per_s'])} / {fmt_rate(n['render_rays_per_s'])}",
                "",
            )
        )
    return rows


def markdown(report: dict) -> str:
    env = report["sections"].get("env", {}).get("result", {})
    lines = [
        f"# gpu-check, {report['date']}",
        "",
        f"GPU: {env.get('gpu', '?')} (driver {env.get('driver', '?')}); torch {env.get('torch', '?')} "
        f"(CUDA {env.get('torch_cuda', '?')}), warp-lang {env.get('warp', '?')}, "
        f"Python {env.get('python', '?')}; disk {env.get('disk_write_mb_per_s', 0):.0f} MB/s synced.",
        f"Command: `{report['command']}`; {report['seconds']:.0f} s in all.",
        "",
        "| figure | measured | target |",
        "|---|---|---|",
    ]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in headline(report)]
    lines += ["", "| section | status | seconds |", "|---|---|---|"]
    lines += [f"| {name} | {e['status']} | {e['seconds']} |" for name, e in report["sections"].items()]
    failed = report["sections"].get("parity", {}).get("result", {}).get("failed") or []
    if failed:
        lines += ["", "Failed parity tests:", *[f"- {f}" for f in failed]]
    step = report["sections"].get("step", {}).get("result")
    if step:
        lines += [
            "",
            f"The spike step ({step['reso']}³) {'from the CUDA graph' if step['graph'] else 'launched'}, "
            "per variant and batch (benchmarks/graph_step.py; image: the largest difference from the "
            "default's render after the same steps):",
            "",
            "| variant @ rays | ms a step | train rays/s | image |",
            "|---|---|---|---|",
        ]
        for key, run in step["runs"].items():
            if "error" in run:
                lines.append(f"| {key} | failed: {run['error'][:80]} | | |")
            else:
                lines.append(
                    f"| {key} | {run['ms']:.3f} | {fmt_rate(run['train_rays_per_s'])} | "
                    f"{run['max_image_difference']:.1e} |"
                )
    lanes = report["sections"].get("lanes", {}).get("result")
    if lanes:
        lines += [
            "",
            f"Lanes per ray (spike, {lanes['rays']} rays, forward + backward rays/s): "
            + ", ".join(
                f"{k.split('_')[1]}: {fmt_rate(v)}" for k, v in lanes.items() if k.startswith("lanes_")
            ),
        ]
        sizes = sorted({int(k.split("_")[1]) for k in lanes if k.startswith("render_")})
        lines.append(
            "Forward alone, rays/s with a thread / a warp per ray: "
            + ", ".join(
                f"{n} rays {fmt_rate(lanes[f'render_{n}_lanes_0_rays_per_s'])} / "
                f"{fmt_rate(lanes[f'render_{n}_lanes_32_rays_per_s'])}"
                for n in sizes
            )
        )
    kernels = report["sections"].get("kernels", {}).get("result")
    if kernels:
        lines += [
            "",
            f"Kernel variants (spike; rays/s of {kernels['rays']}-ray forward + backward and of a "
            f"{kernels['render_rays']}-ray forward; the first call, compile included):",
        ]
        lines += [
            f"- {name}: {fmt_rate(kernels[f'{name}_train_rays_per_s'])} / "
            f"{fmt_rate(kernels[f'{name}_render_rays_per_s'])}; {kernels[f'{name}_first_call_s']:.1f} s"
            for name in KERNEL_CHOICES
            if f"{name}_train_rays_per_s" in kernels
        ]
    fused = report["sections"].get("fused", {}).get("result")
    if fused:
        sys.path.insert(0, str(BENCH))
        from fused_kernels import summary

        sizes = sorted({int(k.split("_")[3]) for k in fused if k.startswith("tone_loss_kernel_")})
        lines += ["", "Fused kernels against PyTorch's operators (ms per call):"]
        lines += [f"- {line}" for line in summary(fused, tuple(sizes))]
    bench = report["sections"].get("bench", {}).get("result")
    if bench:
        lines += [
            "",
            "| problem | rays | train rays/s | step rays/s | render rays/s | update ms | peak MB |",
            "|---|---|---|---|---|---|---|",
        ]
        for problem, by_backend in bench["results"].items():
            r = by_backend["warp"]
            lines.append(
                f"| {problem} | {r['rays']} | {fmt_rate(r['train_rays_per_s'])} | "
                f"{fmt_rate(r['step_rays_per_s'])} | {fmt_rate(r['render_rays_per_s'])} | "
                f"{r['update_ms']:.2f} | {r['peak_mb']:.0f} |"
            )
        paper = bench["training_runs"].get("paper_synthetic_scaled")
        if paper:
            sys.path.insert(0, str(BENCH))
            from run import level_rates

            lines += [
                "",
                f"paper-synthetic at 1/{paper['scale']} of its steps, grid sides / {paper['reso_scale']}: "
                f"{paper['seconds']:.0f} s; per level "
                + ", ".join(level_rates(lv, ".1f") for lv in paper["levels"]),
            ]
        demo = bench["training_runs"].get("demo")
        if demo:
            lines.append(
                f"Demo `fast` run (tone mapping): {demo['seconds']:.1f} s, {demo['steps']} steps, "
                f"{demo['psnr_right_halves']:.2f} dB right halves."
            )
    levels = report["sections"].get("levels", {}).get("result")
    if levels:
        sys.path.insert(0, str(BENCH))
        from profile_training import format_report

        lines += ["", "paper-synthetic's step at each level's end (benchmarks/profile_training.py):"]
        for run in levels.values():
            lines += ["```", *format_report(run), "```"]
    ncu = report["sections"].get("ncu", {}).get("result")
    if ncu:
        lines += [
            "",
            f"Nsight Compute over one {ncu['problem']} step of {ncu['rays']} rays, costliest first:",
            "",
        ]
        lines += ["| kernel | µs | registers | occupancy achieved | top stalls |", "|---|---|---|---|---|"]
        for k in sorted(ncu["launches"], key=lambda k: -k.get("duration", 0.0))[:8]:
            stalls = ", ".join(f"{r} {v:.1f}" for r, v in list(k.get("stalls", {}).items())[:3])
            lines.append(
                f"| {k['kernel'][:48]} | {k.get('duration', 0):.1f} | {k.get('registers', 0):.0f} | "
                f"{k.get('achieved_occupancy', 0):.0f} % | {stalls} |"
            )
    profile = report["sections"].get("profile", {}).get("result")
    if profile:
        lines += ["", "Profile (spike, per kernel):", "```", *profile["table"], "```"]
    return "\n".join(lines) + "\n"


def write_report(report: dict, out: Path) -> None:
    """Both files replaced whole, so an interrupted call leaves the last complete pair."""
    for name, text in (("gpu_check.json", json.dumps(report, indent=2)), ("gpu_check.md", markdown(report))):
        tmp = out / f".{name}.tmp"
        tmp.write_text(text)
        tmp.replace(out / name)


def no_cuda_message(device: str) -> str | None:
    """Why nothing can be checked here, or None."""
    if not device.startswith("cuda"):
        return None
    import torch

    if not torch.cuda.is_available():
        return f"gpu-check: no CUDA device here (torch {torch.__version__} sees none); nothing to check."
    return None


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("gpu_check"), help="where the JSON and markdown go")
    ap.add_argument(
        "--demo-data",
        type=Path,
        help="an `hdrplenoxels synth demo` folder (default: made now, which needs Mitsuba)",
    )
    ap.add_argument(
        "--sections", nargs="+", choices=list(SECTIONS), help="default: all (capture: with its data)"
    )
    ap.add_argument(
        "--capture-data",
        type=Path,
        help="a real capture's kit (benchmarks/capture_kit.py) for the capture section",
    )
    ap.add_argument("--deadline", type=float, default=450.0, help="seconds for all sections together")
    ap.add_argument("--device", default="cuda", help="cuda (cuda:N), or cpu to try the plumbing here")
    ap.add_argument("--repeats", type=int, default=7, help="timed repeats per measurement (median)")
    ap.add_argument("--problems", nargs="+", default=["spike", "demo"], help="bench's problems")
    ap.add_argument("--paper-scale", type=int, default=400, help="paper-synthetic's steps divided by this")
    ap.add_argument("--paper-reso-scale", type=int, default=1, help="its grid sides divided by this")
    ap.add_argument("--spike-rays", type=int, default=5000)
    ap.add_argument("--large-rays", type=int, default=100_000)
    ap.add_argument("--lanes", type=int, nargs="+", default=[0, 8, 16, 32])
    ap.add_argument("--render-rays", type=int, nargs="+", default=[16384, 65536, 262144, 640000])
    ap.add_argument("--viewer-size", type=int, default=800)
    ap.add_argument("--parity-files", nargs="+", help="test files (default: every kernel family's)")
    ap.add_argument("--quick-steps", type=int, help="train this many steps, not the preset's (plumbing)")
    ap.add_argument("--quick", action="store_true", help="stop the parity tests at the first failure")
    ap.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--limit-scale", type=float, default=1.0, help="each section's time limit times this")
    args = ap.parse_args(argv)
    if args.sections is None:
        args.sections = [s for s in SECTIONS if s != "capture" or args.capture_data is not None]
    if "capture" in args.sections and args.capture_data is None:
        ap.error("the capture section trains on a real capture: pass --capture-data KIT")
    args.argv = list(argv)
    if args.capture_data is not None:  # the workers run from the repository's root
        args.capture_data = args.capture_data.resolve()
        args.argv += ["--capture-data", str(args.capture_data)]
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.worker:
        from hdrplenoxels.core.process_settings import apply_process_settings

        apply_process_settings()
        args.worker_out.write_text(json.dumps(SECTION_FUNCTIONS[args.worker](args)))
        return 0
    message = no_cuda_message(args.device)
    if message:
        print(message)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="gpu-check-") as tmp:
        args.work = Path(tmp)
        args.argv += ["--work", tmp]
        if args.demo_data is None:
            args.demo_data = args.work / "demo"
            made = subprocess.run(
                [sys.executable, "-m", "hdrplenoxels", "synth", "demo", str(args.demo_data)],
                capture_output=True,
                text=True,
            )
            if made.returncode != 0:
                tail = (made.stderr.strip().splitlines() or ["?"])[-1]
                print(f"gpu-check: could not make the demo scene ({tail}); pass --demo-data", file=sys.stderr)
                return 2
        args.demo_data = args.demo_data.resolve()
        args.argv += ["--demo-data", str(args.demo_data)]
        report = {
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "command": "python benchmarks/gpu_check.py " + " ".join(argv),
            "deadline_s": args.deadline,
            "seconds": 0.0,
            "sections": {},
        }
        with open(args.out / "gpu_check.log", "w") as log:
            for name in args.sections:
                left = args.deadline - (time.perf_counter() - start)
                limit = SECTIONS[name] * args.limit_scale
                if left < limit / 3:
                    report["sections"][name] = {"status": "skipped (deadline)", "seconds": 0.0}
                else:
                    report["sections"][name] = run_section(name, args, min(limit, left), log)
                report["seconds"] = time.perf_counter() - start
                write_report(report, args.out)
                entry = report["sections"][name]
                print(f"gpu-check: {name}: {entry['status']} ({entry['seconds']} s)", flush=True)
    print(markdown(report))
    return 0 if all(e["status"] == "ok" for e in report["sections"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
