"""What writing a checkpoint costs, in the grid file's version 2 against version 1 (JOURNAL.md,
"Checkpoint writes").

Version 1 stored the dense link grid deflated at zlib's fastest level, and deflated every other integer
array too; version 2 stores the link grid as its occupied cells and their rows, and deflates nothing.
Given any native grid file (a run's checkpoint or model), this reads it once, then writes its arrays both
ways to a folder on the disk being measured, each synced as `write_npz` syncs, and prints the seconds,
the file's size and the ratio. The file is read with the package's reader, so a version 1 file works as
well as a version 2 one.

Usage: python benchmarks/studies/checkpoint_write/checkpoint_write.py RUN/checkpoints/step_0003000.npz
       [--out /tmp/ckpt-bench]
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
import zipfile
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.npy_files import read_npz
from hdrplenoxels.grid.io import LINKS_PREFIX, dense_links, sparse_links, write_npz


def write_version_1(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """The reference: version 1's writer, integer arrays deflated at level 1, the file synced."""
    with open(path, "wb") as f:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                if value.dtype.kind in "iub":
                    info.compress_type = zipfile.ZIP_DEFLATED
                    level = "compress_level" if hasattr(info, "compress_level") else "_compresslevel"
                    setattr(info, level, 1)
                with zf.open(info, "w", force_zip64=True) as entry:
                    np.lib.format.write_array(entry, value, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", type=Path, help="a native grid file: a checkpoint or a model")
    parser.add_argument("--out", type=Path, default=Path("/tmp/checkpoint-write-bench"))
    args = parser.parse_args()
    z = {name: np.asarray(value) for name, value in read_npz(args.file).items()}
    dense = z.pop("links") if "links" in z else dense_links(args.file, z)
    common = {k: v for k, v in z.items() if not k.startswith(LINKS_PREFIX) and k != "version"}
    args.out.mkdir(parents=True, exist_ok=True)
    before, now = args.out / "version1.npz", args.out / "version2.npz"
    links = torch.from_numpy(dense)
    version_1 = {"version": np.array(1, dtype=np.int64), "links": dense, **common}
    print(f"{args.file}: link grid {tuple(dense.shape)}, {int((dense >= 0).sum())} occupied cells")
    try:
        ref_s = timed(lambda: write_version_1(before, version_1))
        # Version 2's cost includes finding the occupied cells (here on the CPU; a GPU run finds them there).
        now_s = timed(
            lambda: write_npz(now, {"version": np.array(2, dtype=np.int64), **sparse_links(links), **common})
        )
        ref_mb, now_mb = before.stat().st_size / 1e6, now.stat().st_size / 1e6
        print(f"version 1 (dense links deflated)  {ref_s:7.2f} s  {ref_mb:8.1f} MB")
        ratio = now_s / ref_s
        print(f"version 2 (sparse links, stored)  {now_s:7.2f} s  {now_mb:8.1f} MB  ratio {ratio:.3f}")
        print(f"disk rate of version 2's write: {now_mb / now_s:.0f} MB/s")
    finally:
        shutil.rmtree(args.out, ignore_errors=True)


if __name__ == "__main__":
    main()
