"""What a cascade's bulk passes cost (JOURNAL.md, "Constants justified by timings").

`balanced` ends on a resample of every level from 128^3 to 256^3, and writes checkpoints of that grid.
On a cascade shaped like asclepius's (6 levels, the occupied voxels in blobs around random surface
points), this times each pass the way it runs now and the way it ran before, in the same run:
- the density at every new voxel: torch's trilinear interpolation of each dense level, against the
  gather of every new voxel's 8 corners (`trilinear_rows_reference`, one chunk of points at a time);
- the SH of the kept voxels: the Warp sampler (`kernels/resample_kernel.py`) against the same gather;
- the two 26-neighbour dilations: byte ORs along each axis against a float 3-D max filter;
- the corner rows of 16 384 random points (the free-space prior's step) on the 256^3 cascade: one flat
  index per corner (all of `corner_weights`, its weights too) against a gather of the rows alone
  through four index tensors (median of 20 calls);
- the 256^3 link grid for a checkpoint or model file: its occupied cells and their rows (`sparse_links`,
  the file format's version 2) against version 1's deflate of the dense grid at zlib's fastest level.
Prints seconds and the ratio to the old way.

Usage: python benchmarks/studies/cascade_passes/cascade_passes.py [--levels 6] [--reso 128] [--voxels 1850000]
"""

from __future__ import annotations

import argparse
import statistics
import time
import zlib
from collections.abc import Callable

import torch
import torch.nn.functional as F

from hdrplenoxels.grid.io import sparse_links
from hdrplenoxels.grid.sparse_grid import corner_weights, dilate_mask, resample_axes, resampled_density
from hdrplenoxels.kernels.resample_kernel import trilinear_rows
from hdrplenoxels.kernels.resample_reference import trilinear_rows_reference


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
    """The reference sampler: `trilinear_rows_reference` a chunk of points at a time."""
    out = torch.empty((pts.shape[0], data.shape[1]))
    for i in range(0, pts.shape[0], chunk):
        out[i : i + chunk] = trilinear_rows_reference(links, data, pts[i : i + chunk])
    return out


def max_filter(mask: torch.Tensor, times: int) -> torch.Tensor:
    m = mask.reshape(-1, 1, *mask.shape[-3:]).float()
    for _ in range(times):
        m = F.max_pool3d(m, kernel_size=3, stride=1, padding=1)
    return (m > 0.5).reshape(mask.shape)


CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def four_index_rows(links: torch.Tensor, pos: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """`corner_weights`' rows the way it gathered them before: through four index tensors."""
    reso = torch.tensor(links.shape[1:])
    p = torch.minimum(pos.clamp(min=0.0), (reso - 1).to(pos.dtype))
    corner = torch.minimum(torch.floor(p).long(), reso - 2)[..., None, :] + CORNERS
    lv = level[..., None].expand_as(corner[..., 0])
    return links[lv, corner[..., 0], corner[..., 1], corner[..., 2]].long()


def seconds(fn: Callable[[], object], calls: int = 1) -> float:
    """One call's seconds (the median of `calls`)."""
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


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
        print(f"{name:40s} before {ref_s:8.3f} s  now {now_s:7.3f} s  ratio {now_s / ref_s:.3f}")
    fine_links = torch.full(keep.shape, -1, dtype=torch.int32)
    fine_links[keep] = torch.arange(int(keep.sum()), dtype=torch.int32)
    pos = torch.rand(16384, 3, generator=g) * (new[0] - 1)
    level = torch.randint(args.levels, (16384,), generator=g)
    assert torch.equal(four_index_rows(fine_links, pos, level), corner_weights(fine_links, pos, level)[0])
    raw = fine_links.numpy().tobytes()
    more = {
        "corner rows of 16 384 points (256^3)": (
            lambda: four_index_rows(fine_links, pos, level),
            lambda: corner_weights(fine_links, pos, level),
            20,
        ),
        "the 256^3 link grid for a file": (
            lambda: zlib.compress(raw, 1),
            lambda: sparse_links(fine_links),
            1,
        ),
    }
    for name, (reference, now, calls) in more.items():
        ref_s, now_s = seconds(reference, calls), seconds(now, calls)
        print(f"{name:40s} before {ref_s:8.3f} s  now {now_s:7.3f} s  ratio {now_s / ref_s:.3f}")
    sparse_mb = sum(a.nbytes for a in sparse_links(fine_links).values()) / 2**20
    deflated_mb = len(zlib.compress(raw, 1)) / 2**20
    print(f"link grid in a file: {deflated_mb:.1f} MB deflated, {sparse_mb:.1f} MB sparse")


if __name__ == "__main__":
    main()
