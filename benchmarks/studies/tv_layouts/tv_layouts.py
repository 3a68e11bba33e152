"""The TV kernel's two layouts timed on one device: `tv_grad_` of a random 1 % run of a dense grid's cells
over its 27 SH channels, a thread per cell and a thread per (cell, channel), alternating, median of each.

Usage: python benchmarks/studies/tv_layouts/tv_layouts.py [--reso 128] [--calls 12] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import time
from statistics import median

import torch

from hdrplenoxels.kernels.tv import TVTerm, sample_tv_cells
from hdrplenoxels.kernels.tv_kernel import tv_grad_


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reso", type=int, default=128)
    ap.add_argument("--calls", type=int, default=12)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    dev = torch.device(args.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    reso = (args.reso,) * 3
    n = args.reso**3
    links = torch.arange(n, dtype=torch.int32, device=dev).reshape(reso)
    values = torch.randn(n, 27, generator=torch.Generator().manual_seed(0)).to(dev)
    grad, touched = torch.zeros_like(values), torch.zeros(n, dtype=torch.uint8, device=dev)
    g = torch.Generator().manual_seed(1)
    times: dict[bool, list[float]] = {False: [], True: []}
    for call in range(2 * args.calls + 2):
        per_channel = bool(call % 2)
        cells = sample_tv_cells(reso, 0.01, g).to(dev)
        sync()
        t = time.perf_counter()
        tv_grad_(TVTerm(links, values, 0.1, cells, "self"), grad, touched, per_channel=per_channel)
        sync()
        if call >= 2:  # the first of each compiles
            times[per_channel].append(time.perf_counter() - t)
    for per_channel, label in ((False, "a thread per cell"), (True, "a thread per (cell, channel)")):
        print(f"{label}: {1e3 * median(times[per_channel]):.2f} ms a call ({args.device}, {args.reso}^3)")


if __name__ == "__main__":
    main()
