"""What a cascade's resample costs (docs/performance.md, "Constants justified by timings").

`balanced` ends on a resample of every level from 128^3 to 256^3. On a cascade shaped like asclepius's
(6 levels, the occupied voxels in blobs around random surface points), this times each of the
resample's three passes the way it runs now and by its reference, in the same run:
- the density at every new voxel: torch's trilinear interpolation of each dense level, against the
  gather of every new voxel's 8 corners (`trilinear_sample`, one chunk of points at a time);
- the SH of the kept voxels: the Warp sampler (`grid/resample_kernel.py`) against the same gather;
- the two 26-neighbour dilations: byte ORs along each axis against a float 3-D max filter.
Prints seconds (one call each: they take seconds) and the ratio to the reference.

Usage: python benchmarks/resample.py [--levels 6] [--reso 128] [--voxels 1850000]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from hdrplenoxels.grid.resample_kernel import trilinear_rows
from hdrplenoxels.grid.sparse_grid import dilate_mask, resample_axes, resampled_density, trilinear_sample


def blob_cascade(levels: int, reso: int, voxels: int, generator: torch.Generator) -> torch.Tensor:
    """Links (levels, R, R, R) with about `voxels` rows in blobs of radius 4 voxels."""
    occupied = torch.zeros((levels, reso, reso, reso), dtype=torch.bool)
    per_blob = 4 * 4 * 4 * 4  # a radius-4 ball holds ~270 voxels; blobs overlap a little
    centres = torch.randint(4, reso - 4, (voxels // per_blob, 3), generator=generator)
    level = torch.randint(levels, (centres.shape[0],), generator=generator)
    d = torch.arange(-4, 5)
    offsets = torch.stack(torch.meshgrid(d, d, d, indexing="ij"), -1).reshape(-1, 3)
    offsets = offsets[offsets.square().sum(-1) <= 16]
    pts = centres[:, None] + offsets
    occupied[level[:, None].expand(-1, offsets.shape[0]), pts[..., 0], pts[..., 1], pts[..., 2]] = True
    links = torch.full(occupied.shape, -1, dtype=torch.int32)
    links[occupied] = torch.arange(int(occupied.sum()), dtype=torch.int32)
    return links


def chunked_gather(links: torch.Tensor, data: torch.Tensor, pts: torch.Tensor, chunk: int = 1 << 18):
    """The reference sampler: `trilinear_sample` a chunk of points at a time."""
    out = torch.empty((pts.shape[0], data.shape[1]))
    for i in range(0, pts.shape[0], chunk):
        out[i : i + chunk] = trilinear_sample(links, data, pts[i : i + chunk])
    return out


def max_filter(mask: torch.Tensor, times: int) -> torch.Tensor:
    m = mask.reshape(-1, 1, *mask.shape[-3:]).float()
    for _ in range(times):
        m = F.max_pool3d(m, kernel_size=3, stride=1, padding=1)
    return (m > 0.5).reshape(mask.shape)


def seconds(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", type=int, default=6)
    parser.add_argument("--reso", type=int, default=128)
    parser.add_argument("--voxels", type=int, default=1_850_000)
    args = parser.parse_args()
    g = torch.Generator().manual_seed(0)
    links = blob_cascade(args.levels, args.reso, args.voxels, g)
    rows = int((links >= 0).sum())
    density = torch.rand(rows, generator=g) * 20
    sh = torch.randn(rows, 27, generator=g)
    new = (2 * args.reso,) * 3
    axes = resample_axes(links.shape[1:], new, "cpu")
    new_pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = dilate_mask(torch.stack([resampled_density(lk, density, new) for lk in links]) > 5.0, 2)
    idx = keep[0].nonzero()
    kept_pts = torch.stack([axes[a][idx[:, a]] for a in range(3)], -1)
    trilinear_rows(links[0], sh, kept_pts[:10])  # compile the kernel outside the timing
    kept = idx.shape[0]
    print(f"{args.levels} levels of {args.reso}^3 -> {new[0]}^3, {rows} voxels, {kept} kept on level 0")
    cases = {
        "density, every new voxel (all levels)": (
            lambda: [chunked_gather(lk, density[:, None], new_pts) for lk in links],
            lambda: [resampled_density(lk, density, new) for lk in links],
        ),
        "SH of level 0's kept voxels": (
            lambda: chunked_gather(links[0], sh, kept_pts),
            lambda: trilinear_rows(links[0], sh, kept_pts),
        ),
        "dilation, 2 passes (all levels)": (lambda: max_filter(keep, 2), lambda: dilate_mask(keep, 2)),
    }
    for name, (reference, now) in cases.items():
        ref_s, now_s = seconds(reference), seconds(now)
        print(f"{name:40s} reference {ref_s:7.2f} s  now {now_s:6.2f} s  ratio {now_s / ref_s:.3f}")


if __name__ == "__main__":
    main()
