"""A processed capture made small enough to carry to a device machine: its photos reduced by a downscale
(area-filtered as `train --downscale` does, stored as JPEG), intrinsics and sizes scaled, sparse points
copied, every view kept (test views too: `make gpu-check`'s `capture` section scores their right halves,
the paper's protocol, beside the figure measured before on the same capture).

Usage: python benchmarks/capture_kit.py DATA OUT [--downscale 4] [--quality 95]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gpu_preset import write_kit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="a processed capture (`hdrplenoxels process`'s output)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--quality", type=int, default=95, help="JPEG quality (0: PNG, lossless and larger)")
    args = ap.parse_args()
    kit = write_kit(args.data, args.out, args.downscale, args.quality or None)
    size = sum(p.stat().st_size for p in kit.rglob("*") if p.is_file()) / 2**20
    print(f"{kit}: downscale {args.downscale}, {size:.1f} MiB")


if __name__ == "__main__":
    main()
