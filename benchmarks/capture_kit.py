"""A processed capture made small enough to carry to a device machine: its photos reduced by a downscale
(area-filtered as `train --downscale` does, stored as JPEG), intrinsics and sizes scaled, sparse points
copied, every view kept (test views too: `make gpu-check`'s `capture` section scores their right halves,
the paper's protocol, beside the figure measured before on the same capture).

`--reshoots` writes three kits in OUT: `photos`, and the capture's `static` and `varying` re-shoots
(`benchmarks/real_captures.py`'s simulated cameras, shot from the full-size photos, then reduced), the
datasets the peers table compares ours and gsplat on (JOURNAL.md, "3D Gaussian Splatting on
the same captures").

Usage: python benchmarks/capture_kit.py DATA OUT [--downscale 4] [--quality 95] [--reshoots]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from gpu_preset import kit_size, write_kit
from real_captures import reshoot

RESHOOTS = ("static", "varying")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="a processed capture (`hdrplenoxels process`'s output)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--quality", type=int, default=95, help="JPEG quality (0: PNG, lossless and larger)")
    ap.add_argument("--reshoots", action="store_true", help="OUT/photos, OUT/static and OUT/varying")
    args = ap.parse_args()
    quality = args.quality or None
    if not args.reshoots:
        kit = write_kit(args.data, args.out, args.downscale, quality)
        print(f"{kit}: downscale {args.downscale}, {kit_size(kit):.1f} MiB")
        return
    for kit in reshoot_kits(args.data, args.out, args.downscale, quality):
        print(f"{kit}: downscale {args.downscale}, {kit_size(kit):.1f} MiB")


def reshoot_kits(data: Path, out: Path, downscale: int, quality: int | None) -> list[Path]:
    """OUT/photos, OUT/static and OUT/varying: `data` and its two re-shoots, each shot at full size and
    then reduced (JPEG at `quality`, or PNG with None)."""
    out.mkdir(parents=True, exist_ok=True)
    kits = [write_kit(data, out / "photos", downscale, quality)]
    with tempfile.TemporaryDirectory(dir=out) as work:  # each full-size re-shoot gone once reduced
        for variant in RESHOOTS:
            full = reshoot(data, Path(work), variant)
            kits.append(write_kit(full, out / variant, downscale, quality))
            shutil.rmtree(full)
    return kits


if __name__ == "__main__":
    main()
