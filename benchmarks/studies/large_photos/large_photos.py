"""Peak memory and time of training on full-size photos with `--downscale` (JOURNAL.md).

Issue 25's target: 50 photos of 1080 x 1920 train with `--downscale 2` in at most 8 GB. Rendering 50 such
views with Mitsuba takes hours on 2 cores, so the photos are made from a smaller synthetic capture
(`synth` output, e.g. the courtyard's varying captures): each image is enlarged with a Lanczos filter to
1920 pixels wide and cropped to 1080 rows about its centre, and the intrinsics are scaled and shifted to
match exactly. The content is softer than a real 1080p photo, but what the memory depends on is all there:
the files' size (they are read at full size, then area-filtered), the ray pool, the grid and the
background model. The training itself runs as `hdrplenoxels train` in a child process; its peak resident
memory is read from the kernel when it exits.

Example: python benchmarks/studies/large_photos/large_photos.py CAPTURE_DIR /tmp/large --preset balanced
         --downscale 2
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from PIL import Image

WIDTH, HEIGHT = 1920, 1080


def enlarge_capture(src: Path, dst: Path) -> int:
    """Write `src`'s images at WIDTH x HEIGHT into `dst` with matching intrinsics; returns the view count."""
    meta = json.loads((src / "transforms.json").read_text())
    scale = WIDTH / meta["w"]
    enlarged_height = round(meta["h"] * scale)
    crop = (enlarged_height - HEIGHT) // 2
    if crop < 0:
        raise SystemExit(
            f"{src}: aspect {meta['w']}x{meta['h']} is wider than 16:9; cannot crop to 1080 rows"
        )
    (dst / "images").mkdir(parents=True, exist_ok=True)
    for frame in meta["frames"]:
        image = Image.open(src / frame["file_path"]).convert("RGB")
        big = image.resize((WIDTH, enlarged_height), Image.Resampling.LANCZOS)
        big.crop((0, crop, WIDTH, crop + HEIGHT)).save(dst / frame["file_path"])
    meta.update(
        fl_x=meta["fl_x"] * scale,
        fl_y=meta["fl_y"] * scale,
        cx=meta["cx"] * scale,
        cy=meta["cy"] * scale - crop,
        w=WIDTH,
        h=HEIGHT,
    )
    (dst / "transforms.json").write_text(json.dumps(meta, indent=1))
    return len(meta["frames"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "capture", type=Path, help="a dataset folder with transforms.json (e.g. synth's varying/)"
    )
    parser.add_argument("out", type=Path)
    parser.add_argument("--preset", default="balanced")
    parser.add_argument("--downscale", type=int, default=2)
    args = parser.parse_args()
    data = args.out / "data"
    views = enlarge_capture(args.capture, data)
    run = args.out / f"run_{args.preset}_downscale{args.downscale}"
    command = [sys.executable, "-m", "hdrplenoxels", "train", str(data), "--out", str(run), "--preset",
               args.preset, "--tonemap", "--downscale", str(args.downscale), "--overwrite"]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(command, check=True)
    seconds = time.perf_counter() - start
    peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e9
    print(
        f"{views} photos of {WIDTH}x{HEIGHT}, --preset {args.preset} --downscale {args.downscale}: "
        f"train command {seconds:.0f} s, peak resident memory {peak_gb:.2f} GB"
    )


if __name__ == "__main__":
    main()
