"""The view prior's update of a grid while it acts (the first two thirds of a tone-mapped schedule).

Dense, it visits every voxel at every step; on a GPU that pass is bound by memory. Two measurements:
- the SH's dense pass reading every row's gradient parts against only the touched rows'
  (`fused_rmsprop_(touched=...)`, the same result to the bit, tests/test_optim.py);
- a step of the grid's optimiser (density and SH) dense against owed (`owe_pull`: the rows a step
  reads pay what they owe first, `pay_owed`, and every row every `OWED_SETTLE_EVERY` steps, `settle`;
  the same result to the bit, tests/test_owed_pull.py), timed over whole settling windows, so the
  settle is in the mean (JOURNAL.md, "The view prior's pull, owed").
Prints milliseconds per update (median of repeats; per step over windows for the second; CUDA
synchronised) and the ratios.

Usage: python benchmarks/prior_update.py [--rows 4000000] [--touched 0.05] [--read 0.08] [--repeats 20]
       [--windows 3] [--json F]
"""

import argparse
import contextlib
import functools
import json
import time
from pathlib import Path
from statistics import median

import torch

from hdrplenoxels.core.parallel import cpu_workers
from hdrplenoxels.kernels import rmsprop_kernel
from hdrplenoxels.kernels.grad_buffers import part_buffers
from hdrplenoxels.kernels.rmsprop import RMSPropStep
from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_
from hdrplenoxels.train.engines.grid_engine import view_prior_pull
from hdrplenoxels.train.engines.warp_grid import OWED_SETTLE_EVERY
from hdrplenoxels.train.optim import PARAM_FLOOR, Svox2RMSProp

COLUMNS = 27  # SH degree 2, three colours


def update_times(rows: int, touched: float, repeats: int, device: torch.device) -> dict:
    g = torch.Generator().manual_seed(0)
    sh = (torch.randn(rows, COLUMNS, generator=g) * 0.1).to(device)
    state = torch.full_like(sh, 1e-4)
    parts = 1 if device.type == "cuda" else cpu_workers()  # as the training engine's buffers
    grads = part_buffers(parts, (rows, COLUMNS), 1, device)
    hit = (torch.rand(rows, generator=g) < touched).to(device)
    marks = hit.to(torch.uint8)
    pull = view_prior_pull(9, 1e-6, device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def run(scope: torch.Tensor | None) -> float:
        times = []
        for i in range(repeats + 3):
            grads[0].masked_fill_(hit[:, None], 1e-3)  # a step's gradients, on the touched rows
            sync()
            t = time.perf_counter()
            fused_rmsprop_(RMSPropStep(sh, state, grads, 1e-2, 0.95, 1e-8, PARAM_FLOOR, pull), touched=scope)
            sync()
            if i >= 3:
                times.append(time.perf_counter() - t)
        return 1e3 * median(times)

    every, scoped = run(None), run(marks)
    return {
        "device": str(device),
        "rows": rows,
        "touched": touched,
        "parts": parts,
        "every_row_ms": every,
        "touched_rows_ms": scoped,
        "ratio": every / scoped,
    }


def step_times(rows: int, touched: float, read: float, windows: int, device: torch.device) -> dict:
    """Milliseconds per optimiser step of a grid (density, SH) with the pull, dense and owed, each the
    mean over `windows` windows of `OWED_SETTLE_EVERY` steps (median of the windows) after one to warm
    up. Each step's gradients are on a `touched` share of the rows; the owed one first pays a `read`
    share (a forward's reads: the touched rows and more). The rows are drawn anew for every step of a
    window (drawn before the clock starts, on the device), as a training step's rays are: a row then
    owes a gap that varies from row to row, and the rows a paying pass visits are scattered with
    different gaps, which on a GPU leaves lanes of a warp waiting for the row that owes the most. The
    same rows every step would pay one step each, a paying pass's best case."""
    g = torch.Generator().manual_seed(1)
    density = torch.rand(rows, generator=g).to(device)
    sh = (torch.randn(rows, COLUMNS, generator=g) * 0.1).to(device)
    parts = 1 if device.type == "cuda" else cpu_workers()
    grads = [part_buffers(parts, (rows,), 1, device), part_buffers(parts, (rows, COLUMNS), 1, device)]
    draws = torch.Generator(device=device).manual_seed(2)
    hits, reads = [], []  # a window's steps (the settle pays every row, so windows may repeat them)
    for _ in range(OWED_SETTLE_EVERY):
        hit = torch.rand(rows, generator=draws, device=device) < touched
        hits.append(hit)
        reads.append(
            (hit | (torch.rand(rows, generator=draws, device=device) < read - touched)).to(torch.uint8)
        )
    marks = torch.zeros(rows, dtype=torch.uint8, device=device)
    pull = view_prior_pull(9, 1e-6, device)
    lrs = torch.tensor([1.0, 1e-2], device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    touched_rows = torch.zeros(rows, dtype=torch.uint8, device=device)

    def run(owe: bool, per_element: bool | None = None) -> tuple[float, list[torch.Tensor]]:
        """`per_element`: the paying passes' layout (None: the device's default)."""
        if per_element is not None:
            with paying_layout(per_element):
                return run(owe)
        params = [density.clone(), sh.clone()]
        opt = Svox2RMSProp(0.95)
        means = []
        for window in range(windows + 1):
            sync()
            t = time.perf_counter()
            for hit, read_rows in zip(hits, reads, strict=True):
                grads[0][0].masked_fill_(hit, 1e-3)
                grads[1][0].masked_fill_(hit[:, None], 1e-3)
                touched_rows.copy_(hit)
                if opt.owing_pull:
                    marks.copy_(read_rows)
                    opt.pay_owed(marks)
                opt.step_accumulated(
                    params, grads, lrs, touched=touched_rows, pulls=[None, pull], owe_pull=owe
                )
            opt.settle()
            sync()
            if window:
                means.append((time.perf_counter() - t) / OWED_SETTLE_EVERY)
        return 1e3 * median(means), params

    (dense, want), (by_row, got), (by_value, also) = run(False), run(True, False), run(True, True)
    # the same training (to the bit on a CPU; on CUDA the dense pass is a thread per element, rounded apart)
    differs = max(float((a - b).abs().max()) for got_ in (got, also) for a, b in zip(want, got_, strict=True))
    owed = by_value if device.type == "cuda" else by_row  # `pay_owed_rows_`'s default layout
    return {
        "read": read,
        "dense_step_ms": dense,
        "owed_step_ms": owed,
        "owed_rows_step_ms": by_row,
        "owed_values_step_ms": by_value,
        "step_ratio": dense / owed,
        "max_difference": differs,
    }


@contextlib.contextmanager
def paying_layout(per_element: bool):
    """The owed pull's paying passes (`pay_owed_rows_`) a thread per value or per row, whatever the
    device's default, while timed."""
    default = rmsprop_kernel.pay_owed_rows_
    rmsprop_kernel.pay_owed_rows_ = functools.partial(default, per_element=per_element)
    try:
        yield
    finally:
        rmsprop_kernel.pay_owed_rows_ = default


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=4_000_000)
    ap.add_argument("--touched", type=float, default=0.05, help="the fraction of rows a step touches")
    ap.add_argument("--read", type=float, default=0.08, help="the fraction of rows a step's forward reads")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--windows", type=int, default=3, help="settling windows timed per optimiser step")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--json", type=Path)
    return ap.parse_args(argv)


def main() -> None:
    args = parse_args()
    device = torch.device(args.device)
    out = update_times(args.rows, args.touched, args.repeats, device)
    print(
        f"{out['rows']} rows x {COLUMNS}, {out['parts']} gradient part(s), {out['touched']:.0%} touched, "
        f"{out['device']}: every row {out['every_row_ms']:.2f} ms, touched rows {out['touched_rows_ms']:.2f} "
        f"ms ({out['ratio']:.2f}x)"
    )
    out |= step_times(args.rows, args.touched, args.read, args.windows, device)
    print(
        f"a grid's step (density and SH), {out['read']:.0%} read: dense {out['dense_step_ms']:.2f} ms, "
        f"owed {out['owed_step_ms']:.2f} ms ({out['step_ratio']:.2f}x; paid a thread per row "
        f"{out['owed_rows_step_ms']:.2f} ms, per value {out['owed_values_step_ms']:.2f} ms), settled every "
        f"{OWED_SETTLE_EVERY}; "
        f"the two grids differ by at most {out['max_difference']:.2g}"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
