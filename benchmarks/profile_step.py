"""Where one training step's time goes: torch's profiler over a few steps of a benchmark problem.

Lists the kernels (Warp's and torch's) by total time, so a slow piece is found before it is
optimised. Usage: python benchmarks/profile_step.py [--problem spike] [--rays 5000] [--steps 20]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402
from run import checked_device, make_problem, step_functions  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default="spike", choices=("spike", "paper"))
    ap.add_argument("--rays", type=int, default=5000)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")
    ap.add_argument("--rows", type=int, default=25, help="table rows")
    ap.add_argument("--trace", type=Path, help="also write a Chrome trace here")
    args = ap.parse_args()
    device = torch.device(checked_device(args.device))
    grid, o, d, background = make_problem(args.problem, args.rays, None)
    grid, o, d = grid.to(device), o.to(device), d.to(device)
    step = step_functions(grid, o, d, background, "warp")["step"]
    for _ in range(3):  # kernels compiled and loaded, optimiser state created
        step()
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
        torch.cuda.synchronize()
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(args.steps):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
    sort = "cuda_time_total" if device.type == "cuda" else "cpu_time_total"
    print(prof.key_averages().table(sort_by=sort, row_limit=args.rows, max_name_column_width=60))
    if args.trace:
        prof.export_chrome_trace(str(args.trace))


if __name__ == "__main__":
    main()
