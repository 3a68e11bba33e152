"""A batch's rays from the pool's flat pixel indices in one Warp pass.

Drawn through PyTorch, a batch (the slot's search, rows and columns, the pixel's gather, the camera
ray, the NDC warp) is about 35 small operators, each a kernel of a replayed step on a GPU
(JOURNAL.md, "Fused kernels"); here one thread per ray does all of it.

Oracle: `hdrplenoxels.kernels.ray_draw_reference.draw_rays_reference`; parity: tests/test_ray_draw.py.
"""

from __future__ import annotations

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, to_warp, warp_device, warp_struct
from hdrplenoxels.geometry.cameras import NDCSpec
from hdrplenoxels.kernels.ray_draw import PooledPixels


@wp.struct
class NdcWarp:
    """`cameras.to_ndc`'s constants; `on` 0 for world rays."""

    on: int
    coeff_x: float
    coeff_y: float
    near: float


@wp.func
def slot_of(starts: wp.array(dtype=wp.int64), f: wp.int64) -> int:
    """The last slot starting at or before flat index `f` (`searchsorted(right=True) - 1`): an empty
    slot shares its start with the next, and the search passes over it."""
    lo = wp.int32(0)
    hi = starts.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if starts[mid] <= f:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@wp.struct
class _Pool:
    """`PooledPixels` as the kernel reads it."""

    starts: wp.array(dtype=wp.int64)
    """Each slot's first flat index in the pool."""
    used_width: wp.array(dtype=wp.int64)
    """The columns a slot draws from (a test view's left half, else every column)."""
    full_width: wp.array(dtype=wp.int64)
    """The slot's photo's width, its row stride in `pixels`."""
    slot_images: wp.array(dtype=wp.int64)
    """The photo of each slot."""
    pixel_offsets: wp.array(dtype=wp.int64)
    """Where each slot's photo starts in `pixels` (in pixels)."""
    pixels: wp.array2d(dtype=wp.uint8)
    """Every photo's 8-bit RGB, row after row, one after another."""
    c2w: wp.array3d(dtype=wp.float32)
    """Camera to world of each photo."""
    intrinsics: wp.array2d(dtype=wp.float32)
    """fx, fy, cx, cy of each photo."""
    ndc: NdcWarp


@wp.struct
class DrawnPixels:
    """Each drawn ray's photo, pixel and that pixel's value in [0, 1] (`tonemap.pixels.PixelTargets` as a
    kernel reads it): the draw writes it, the tone loss reads it."""

    target: wp.array2d(dtype=wp.float32)
    """(B, 3) the pixel's value."""
    image_ids: wp.array(dtype=wp.int64)
    rows: wp.array(dtype=wp.int64)
    """Its row in its photo (the vignetting's radius reads it)."""
    cols: wp.array(dtype=wp.int64)


def drawn_pixels(
    target: torch.Tensor, image_ids: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor
) -> DrawnPixels:
    """`DrawnPixels` over these tensors (contiguous: the kernels write or read them in place)."""
    return warp_struct(
        DrawnPixels,
        target=to_warp(target, "the target pixels"),
        image_ids=to_warp(image_ids, "the image ids"),
        rows=to_warp(rows, "the pixel rows"),
        cols=to_warp(cols, "the pixel columns"),
    )


@KERNEL
def _draw_rays(
    flat: wp.array(dtype=wp.int64),
    pool: _Pool,
    origins: wp.array2d(dtype=wp.float32),
    dirs: wp.array2d(dtype=wp.float32),
    drawn: DrawnPixels,
):
    r = wp.tid()
    f = flat[r]
    slot = slot_of(pool.starts, f)
    local = f - pool.starts[slot]
    row = local // pool.used_width[slot]
    col = local - row * pool.used_width[slot]
    i = int(pool.slot_images[slot])
    p = pool.pixel_offsets[slot] + row * pool.full_width[slot] + col
    for c in range(3):
        drawn.target[r, c] = float(pool.pixels[p, c]) / 255.0
    drawn.image_ids[r] = wp.int64(i)
    drawn.rows[r] = row
    drawn.cols[r] = col
    # The camera ray through the pixel's centre (`cameras.pixel_rays`).
    k = pool.intrinsics
    x = (float(col) + 0.5 - k[i, 2]) / k[i, 0]
    y = (float(row) + 0.5 - k[i, 3]) / k[i, 1]
    c2w = pool.c2w
    d = wp.vec3(
        c2w[i, 0, 0] * x + c2w[i, 0, 1] * y + c2w[i, 0, 2],
        c2w[i, 1, 0] * x + c2w[i, 1, 1] * y + c2w[i, 1, 2],
        c2w[i, 2, 0] * x + c2w[i, 2, 1] * y + c2w[i, 2, 2],
    )
    d = d / wp.length(d)
    o = wp.vec3(c2w[i, 0, 3], c2w[i, 1, 3], c2w[i, 2, 3])
    ndc = pool.ndc
    if ndc.on != 0:
        # `cameras.to_ndc`: a ray not pointing forward starts beyond the far plane and points away.
        if d[2] > 1e-6:
            t = (ndc.near - o[2]) / d[2]
            ox = o[0] + t * d[0]
            oy = o[1] + t * d[1]
            oz = ndc.near
            o = wp.vec3(ndc.coeff_x * ox / oz, ndc.coeff_y * oy / oz, 1.0 - 2.0 * ndc.near / oz)
            d = wp.vec3(
                ndc.coeff_x * (d[0] / d[2] - ox / oz),
                ndc.coeff_y * (d[1] / d[2] - oy / oz),
                2.0 * ndc.near / oz,
            )
            d = d / wp.length(d)
        else:
            o = wp.vec3(0.0, 0.0, 2.0)
            d = wp.vec3(0.0, 0.0, 1.0)
    for c in range(3):
        origins[r, c] = o[c]
        dirs[r, c] = d[c]


def _ndc_warp(ndc: NDCSpec | None) -> NdcWarp:
    if ndc is None:
        return warp_struct(NdcWarp, on=0, coeff_x=0.0, coeff_y=0.0, near=1.0)
    coeffs = {"coeff_x": float(ndc.coeff_x), "coeff_y": float(ndc.coeff_y), "near": float(ndc.near)}
    return warp_struct(NdcWarp, on=1, **coeffs)


def draw_rays(flat: torch.Tensor, pool: PooledPixels) -> tuple[torch.Tensor, ...]:
    """Exactly `ray_draw_reference.draw_rays_reference`'s contract: (origins, dirs, target, image_ids,
    rows, cols) of the pooled pixels `flat` (B,), each index in [0, the pool's size) (an index outside
    it is the caller's bug; checking would make a GPU step wait)."""
    n = flat.shape[0]
    f32 = dict(dtype=torch.float32, device=flat.device)
    origins, dirs, target = (torch.empty(n, 3, **f32) for _ in range(3))
    image_ids, rows, cols = (torch.empty(n, dtype=torch.long, device=flat.device) for _ in range(3))
    if n:
        device = warp_device(flat)
        pooled = warp_struct(
            _Pool,
            starts=to_warp(pool.starts, "the pool's slot starts"),
            used_width=to_warp(pool.used_width, "the pool's used widths"),
            full_width=to_warp(pool.full_width, "the pool's image widths"),
            slot_images=to_warp(pool.slot_images, "the pool's images"),
            pixel_offsets=to_warp(pool.pixel_offsets, "the pool's pixel offsets"),
            pixels=to_warp(pool.pixels, "the pool's pixels"),
            c2w=to_warp(pool.c2w, "the camera poses"),
            intrinsics=to_warp(pool.intrinsics, "the camera intrinsics"),
            ndc=_ndc_warp(pool.ndc),
        )
        inputs = [
            to_warp(flat.contiguous(), "the flat pixel indices"),
            pooled,
            to_warp(origins, "the drawn origins"),
            to_warp(dirs, "the drawn directions"),
            drawn_pixels(target, image_ids, rows, cols),
        ]
        launch_kernel(_draw_rays, dim=n, inputs=inputs, device=device)
    return origins, dirs, target, image_ids, rows, cols
