"""The view prior's dense update of a grid's SH: every row's gradient parts read and cleared, against
only the touched rows' (`fused_rmsprop_(touched=...)`), the same result to the bit
(tests/test_optim.py). While the prior acts (the first two thirds of a tone-mapped schedule) the update
visits every voxel at every step; on a GPU that pass is bound by memory, and the untouched rows' zero
gradients were a third of its traffic (docs/performance.md, "The paper-synthetic estimate").
Prints milliseconds per update each way (median; CUDA synchronised) and the ratio.

Usage: python benchmarks/prior_update.py [--rows 4000000] [--touched 0.05] [--repeats 20] [--json F]
"""

import argparse
import json
import time
from pathlib import Path
from statistics import median

import torch

from hdrplenoxels.core.parallel import cpu_workers
from hdrplenoxels.render.grad_buffers import part_buffers
from hdrplenoxels.train.engines.grid_engine import view_prior_pull
from hdrplenoxels.train.optim import PARAM_FLOOR
from hdrplenoxels.train.rmsprop_kernels import fused_rmsprop_

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
            fused_rmsprop_(sh, state, grads, 1e-2, 0.95, 1e-8, PARAM_FLOOR, pull=pull, touched=scope)
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


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=4_000_000)
    ap.add_argument("--touched", type=float, default=0.05, help="the fraction of rows a step touches")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--json", type=Path)
    return ap.parse_args(argv)


def main() -> None:
    args = parse_args()
    out = update_times(args.rows, args.touched, args.repeats, torch.device(args.device))
    print(
        f"{out['rows']} rows x {COLUMNS}, {out['parts']} gradient part(s), {out['touched']:.0%} touched, "
        f"{out['device']}: every row {out['every_row_ms']:.2f} ms, touched rows {out['touched_rows_ms']:.2f} "
        f"ms ({out['ratio']:.2f}x)"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
