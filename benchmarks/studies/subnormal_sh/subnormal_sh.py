"""The dense SH pass of the optimiser on a grid whose pull-only rows froze at subnormal values, with
Warp's CPU kernels run as the package runs them (subnormals flushed, `warp_runtime.flushing_subnormals`)
and without that mode, beside the same pass over random SH (the reference: no subnormal anywhere).

A trained grid's rows that only the view prior's pull moves fall to subnormal SH and stall there
(JOURNAL.md, "Why that pass is slow here: frozen subnormal SH"); this builds such a grid
synthetically: `--frozen` of the rows with every non-DC value at -1.05e-41 (the value a pulled row
freezes at, simulated in float32) and their mean squares at the floor, the rest random. Each case
times `--passes` dense passes with the pull and no gradient (as between the prior's rays) on a fresh
copy of the grid and keeps the best.

Usage: python benchmarks/studies/subnormal_sh/subnormal_sh.py [--rows 2000000] [--frozen 0.38] [--passes 5]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch

from hdrplenoxels.core import warp_runtime
from hdrplenoxels.kernels.rmsprop import MEAN_SQUARE_FLOOR, RMSPropStep
from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

SH_COLUMNS = 27
FROZEN_VALUE = -1.05e-41
PULL = 2e-6  # the view prior's 2 lambda at lambda 1e-6
RATE = 4.96e-3  # `fine`'s SH rate where the checkpoint was taken


def grid(rows: int, frozen: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    sh = torch.randn(rows, SH_COLUMNS, generator=g) * 0.1
    state = torch.rand(rows, SH_COLUMNS, generator=g) * 1e-4
    rows_frozen = torch.rand(rows, generator=g) < frozen
    sh[rows_frozen, 1:] = FROZEN_VALUE
    state[rows_frozen, 1:] = MEAN_SQUARE_FLOOR
    return sh, state, torch.zeros(1, rows, SH_COLUMNS)


def best_pass_ms(rows: int, frozen: float, passes: int) -> tuple[float, float]:
    """The best pass in ms, and the fraction of SH values subnormal after the passes."""
    sh, state, grads = grid(rows, frozen)
    pull = torch.full((SH_COLUMNS,), PULL)
    pull[0] = 0.0
    touched = torch.zeros(rows, dtype=torch.uint8)  # no gradient anywhere: the pull alone
    best = float("inf")
    for _ in range(passes):
        start = time.perf_counter()
        fused_rmsprop_(RMSPropStep(sh, state, grads, RATE, 0.95, 1e-8, -1e9, pull), touched=touched)
        best = min(best, time.perf_counter() - start)
    subnormal = ((sh != 0) & (sh.abs() < MEAN_SQUARE_FLOOR)).float().mean().item()
    return best * 1e3, subnormal


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=2_000_000)
    parser.add_argument("--frozen", type=float, default=0.38, help="fraction of rows frozen subnormal")
    parser.add_argument("--passes", type=int, default=5)
    args = parser.parse_args()
    print(f"{args.rows} rows x {SH_COLUMNS} SH, {torch.get_num_threads()} threads, best of {args.passes}")
    flushed = warp_runtime.flushing_subnormals
    random_ms, _ = best_pass_ms(args.rows, 0.0, args.passes)
    cases = {"flushed (as the package runs)": flushed, "not flushed": contextlib.nullcontext}
    for name, mode in cases.items():
        warp_runtime.flushing_subnormals = mode
        ms, subnormal = best_pass_ms(args.rows, args.frozen, args.passes)
        print(
            f"{args.frozen:.0%} rows frozen, {name}: {ms:.1f} ms a pass, {ms / random_ms:.2f}x the random "
            f"grid's {random_ms:.1f} ms; {subnormal:.1%} of SH subnormal after"
        )
    warp_runtime.flushing_subnormals = flushed


if __name__ == "__main__":
    main()
