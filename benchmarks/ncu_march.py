"""What holds the training kernels back on a GPU: Nsight Compute's counters over training steps.

The march is most of a CUDA step's time (`benchmarks/RESULTS.md`, "GPU, 2026-11-27"), and timings alone
do not say whether its lanes wait on memory, on the block-wide colour sum, or on their own arithmetic.
`ncu` (on the device image; it reads the counters on some machines' runtimes, not others: KINDS.md of
the device tool) profiles every kernel (Warp's and torch's) of `--steps` steps of a benchmark problem
(`run.py`'s), after warm-up steps that compile and load them, with Warp's kernels built with line
information so that the source page maps the stalls to lines of Warp's generated CUDA. It writes, under
--out:

    ncu_summary.json  per kernel: duration, registers, occupancy, throughputs, issue rate, and its
                      costliest stall reasons (warp-cycles stalled per issued instruction)
    ncu_details.csv   ncu's details page (every section of `--set full`)
    ncu_raw.csv       ncu's raw page (every metric collected)
    ncu_source.csv    the source pages of the two costliest kernels: per line, its samples and stalls

and prints the summary. Without `ncu`, or where it cannot read the counters, it says so and exits 1.

Usage: python benchmarks/ncu_march.py --out DIR [--problem spike] [--rays 5000] [--steps 1]
"""

from __future__ import annotations

import argparse
import csv
import glob
import io
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

STALL = re.compile(r"^smsp__average_warps_issue_stalled_(?P<reason>.+)_per_issue_active\.ratio$")
NOT_STALLS = ("selected", "not_selected")  # issuing, and eligible but not picked: not waits
TO_MICROSECONDS = {"nsecond": 1e-3, "ns": 1e-3, "msecond": 1e3, "ms": 1e3, "second": 1e6, "s": 1e6}
NCU_PLACES = ("/usr/local/cuda/bin/ncu", "/opt/nvidia/nsight-compute/*/ncu", "/usr/local/cuda-*/bin/ncu")
SOURCE_CAP = 15 * 2**20  # the device tool brings back files of up to 16 MiB
# What the summary keeps of ncu's details page, by (section, metric) as the page names them.
KEPT = {
    ("GPU Speed Of Light Throughput", "Duration"): "duration",
    ("GPU Speed Of Light Throughput", "Memory Throughput"): "memory_throughput",
    ("GPU Speed Of Light Throughput", "DRAM Throughput"): "dram_throughput",
    ("GPU Speed Of Light Throughput", "Compute (SM) Throughput"): "compute_throughput",
    ("GPU Speed Of Light Throughput", "L1/TEX Hit Rate"): "l1_hit_rate",
    ("GPU Speed Of Light Throughput", "L2 Hit Rate"): "l2_hit_rate",
    ("Launch Statistics", "Registers Per Thread"): "registers",
    ("Launch Statistics", "Block Size"): "block_size",
    ("Launch Statistics", "Grid Size"): "grid_size",
    ("Occupancy", "Theoretical Occupancy"): "theoretical_occupancy",
    ("Occupancy", "Achieved Occupancy"): "achieved_occupancy",
    ("Compute Workload Analysis", "Executed Ipc Active"): "ipc_active",
    ("Warp State Statistics", "Warp Cycles Per Issued Instruction"): "cycles_per_issue",
    ("Memory Workload Analysis", "L1/TEX Hit Rate"): "l1_hit_rate",
    ("Memory Workload Analysis", "L2 Hit Rate"): "l2_hit_rate",
}


def short_name(kernel: str) -> str:
    """A Warp kernel's name without its module hash and suffix (`render_forward_lanes_1a2b3c4d_cuda_
    kernel_forward(...)` -> `render_forward_lanes`); another kernel's name up to its arguments."""
    name = kernel.split("(", 1)[0].strip()
    name = re.sub(r"_cuda_kernel_forward$", "", name)
    return re.sub(r"_[0-9a-f]{6,}$", "", name)


def number(text: str) -> float | None:
    """ncu's printed value ("1,234.5", "12") as a float; None for text ("n/a", a name)."""
    try:
        return float(text.replace(",", ""))
    except ValueError:
        return None


def csv_rows(text: str) -> list[list[str]]:
    """The CSV rows of ncu's output, from its header on (ncu prints `==PROF==` lines before it)."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith('"')), len(lines))
    return list(csv.reader(io.StringIO("\n".join(lines[start:]))))


def parse_details(text: str) -> dict[str, dict]:
    """Per launch ID of ncu's details page (`--page details --csv`): the kernel's short name and the
    metrics of `KEPT` (the duration in microseconds, whichever unit ncu printed)."""
    rows = csv_rows(text)
    if not rows:
        return {}
    head = {name: i for i, name in enumerate(rows[0])}
    need = ("ID", "Kernel Name", "Section Name", "Metric Name", "Metric Unit", "Metric Value")
    if any(n not in head for n in need):
        raise ValueError(f"ncu's details page lacks the columns {[n for n in need if n not in head]}")
    out: dict[str, dict] = {}
    for row in rows[1:]:
        if len(row) < len(head):
            continue
        launch = out.setdefault(row[head["ID"]], {"kernel": short_name(row[head["Kernel Name"]])})
        key = KEPT.get((row[head["Section Name"]], row[head["Metric Name"]]))
        value = number(row[head["Metric Value"]])
        if key is not None and value is not None:
            unit = row[head["Metric Unit"]]
            launch[key] = value * TO_MICROSECONDS.get(unit, 1.0) if key == "duration" else value
    return out


def parse_stalls(text: str, top: int = 6) -> dict[str, dict[str, float]]:
    """Per launch ID of ncu's raw page (`--page raw --csv`: a row of metric names, a row of units, a row
    per launch): its `top` stall reasons by warp-cycles stalled per issued instruction."""
    rows = csv_rows(text)
    if len(rows) < 3:
        return {}
    names = rows[0]
    ids = names.index("ID") if "ID" in names else None
    out: dict[str, dict[str, float]] = {}
    for n, row in enumerate(rows[2:]):
        stalls = {}
        for name, value in zip(names, row):
            m = STALL.match(name)
            m = m if m and m["reason"] not in NOT_STALLS else None
            v = number(value) if m else None
            if m and v is not None and v > 0:
                stalls[m["reason"]] = v
        best = sorted(stalls.items(), key=lambda kv: -kv[1])[:top]
        out[row[ids] if ids is not None else str(n)] = dict(best)
    return out


def summarise(details: str, raw: str) -> list[dict]:
    """One entry per profiled launch: `parse_details`' metrics with `parse_stalls`' reasons."""
    launches = parse_details(details)
    stalls = parse_stalls(raw)
    return [dict(launch, id=i, stalls=stalls.get(i, {})) for i, launch in launches.items()]


def find_ncu() -> str | None:
    """`ncu` on the PATH, else where CUDA's toolkit or Nsight Compute put it."""
    found = shutil.which("ncu")
    if found:
        return found
    for pattern in NCU_PLACES:
        hits = sorted(glob.glob(pattern))
        if hits:
            return hits[-1]
    return None


def worker(problem: str, rays: int, steps: int) -> None:
    """The profiled program: warm-up steps, then `steps` steps between cudaProfilerStart and Stop
    (ncu runs with --profile-from-start off, so it sees only these)."""
    from hdrplenoxels.core.process_settings import apply_process_settings

    apply_process_settings()
    import torch
    import warp as wp

    wp.config.lineinfo = True  # before any module loads: ncu maps its samples to source lines
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run import make_problem, step_functions

    grid, o, d, background = make_problem(problem, rays, None)
    grid, o, d = grid.to("cuda"), o.to("cuda"), d.to("cuda")
    step = step_functions(grid, o, d, background, "warp")["step"]
    for _ in range(3):
        step()
    torch.cuda.synchronize()
    torch.cuda.profiler.start()
    for _ in range(steps):
        step()
    torch.cuda.synchronize()
    torch.cuda.profiler.stop()


def run_ncu(ncu: str, args: list[str], out: Path | None = None) -> str:
    """`ncu args`, its output text (also written to `out`); a RuntimeError with its tail if it fails."""
    done = subprocess.run([ncu, *args], capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stdout + done.stderr)[-3000:]
        raise RuntimeError(f"ncu {' '.join(args[:4])} ... exited {done.returncode}:\n{tail}")
    if out is not None:
        out.write_text(done.stdout)
    return done.stdout


def profile(ncu: str, out: Path, problem: str, rays: int, steps: int) -> list[dict]:
    report = Path("/tmp") / f"ncu_march_{problem}"
    run_ncu(ncu, [
        "--profile-from-start", "off", "--clock-control", "none", "--set", "full", "--import-source", "yes",
        "--target-processes", "all", "-f", "-o", str(report), sys.executable, __file__, "--worker",
        "--problem", problem, "--rays", str(rays), "--steps", str(steps),
    ])  # fmt: skip
    rep = f"{report}.ncu-rep"
    details = run_ncu(ncu, ["--import", rep, "--csv", "--page", "details"], out / "ncu_details.csv")
    raw = run_ncu(ncu, ["--import", rep, "--csv", "--page", "raw"], out / "ncu_raw.csv")
    launches = summarise(details, raw)
    costliest = sorted(launches, key=lambda k: -k.get("duration", 0.0))[:2]  # the march's two, as a rule
    pages = []
    for launch in costliest:  # best effort: older ncu has no source page
        try:
            pages.append(run_ncu(ncu, [
                "--import", rep, "--csv", "--page", "source", "--print-source", "cuda,sass",
                "--launch-skip", str(int(launch["id"])), "--launch-count", "1",
            ]))  # fmt: skip
        except (RuntimeError, ValueError) as e:
            print(f"ncu_march: no source page for {launch['kernel']} ({e})", file=sys.stderr)
    if pages:
        (out / "ncu_source.csv").write_text("\n".join(pages)[:SOURCE_CAP])
    return launches


def print_summary(launches: list[dict]) -> None:
    head = f"{'kernel':32} {'us':>8} {'regs':>5} {'occ th/ach':>11} {'mem%':>5} {'sm%':>5} {'cyc/iss':>7}"
    print(f"{head}  stalls")
    for k in sorted(launches, key=lambda k: -k.get("duration", 0.0)):
        stalls = ", ".join(f"{r} {v:.1f}" for r, v in list(k["stalls"].items())[:4])
        occ = f"{k.get('theoretical_occupancy', 0):.0f}/{k.get('achieved_occupancy', 0):.0f}"
        print(
            f"{k['kernel'][:32]:32} {k.get('duration', 0):8.1f} {k.get('registers', 0):5.0f} {occ:>11} "
            f"{k.get('memory_throughput', 0):5.1f} {k.get('compute_throughput', 0):5.1f} "
            f"{k.get('cycles_per_issue', 0):7.1f}  {stalls}"
        )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("ncu_out"))
    ap.add_argument("--problem", default="spike", choices=("spike", "paper"))
    ap.add_argument("--rays", type=int, default=5000)
    ap.add_argument("--steps", type=int, default=1)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main() -> None:
    args = parse_args()
    if args.worker:
        worker(args.problem, args.rays, args.steps)
        return
    ncu = find_ncu()
    if ncu is None:
        sys.exit("ncu_march: no ncu here (Nsight Compute is on the device image)")
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        launches = profile(ncu, args.out, args.problem, args.rays, args.steps)
    except RuntimeError as e:
        sys.exit(f"ncu_march: {e}")
    summary = {"problem": args.problem, "rays": args.rays, "steps": args.steps, "launches": launches}
    (args.out / "ncu_summary.json").write_text(json.dumps(summary, indent=1))
    print_summary(launches)


if __name__ == "__main__":
    main()
