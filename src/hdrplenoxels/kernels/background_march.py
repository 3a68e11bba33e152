"""The MSI background's Warp kernels: forward and hand-written backward, one thread per ray.

The math is exactly that of `kernels/background_reference.py` (docs/method.md, "Background");
`tests/test_background.py` holds the two together. The march has a fixed trip count but an early stop,
so, as for the foreground, Warp's adjoint is off and the backward re-marches svox2-style: with
G = <dL, C_bg> and G <- G - w_k <dL, c_k> after each sample,
  dLoss/dsigma_k = dz (T_{k+1} <dL, c_k> - G),  dLoss/dcolour_k = w_k dL [pre_k > 0],
each spread over the sample's 8 (layer, row, column) corners.

Oracle: `hdrplenoxels.kernels.background_reference.render_background_reference`; parity:
tests/test_background.py.
"""

import math

import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL
from hdrplenoxels.kernels.march_funcs import MarchParams, Rays, composite

PI = wp.constant(math.pi)


@wp.struct
class MSIView:
    """An `MSIBackground` as a kernel argument."""

    density: wp.array3d(dtype=wp.float32)
    color: wp.array3d(dtype=wp.vec3)
    center: wp.vec3
    radius: float
    layers: int
    height: int
    width: int
    samples_per_layer: int


@wp.struct
class MSIGradientTargets:
    """Where a backward thread adds: d(loss)/d(density) and d(loss)/d(colour), its own part."""

    density: wp.array3d(dtype=wp.float32)
    color: wp.array3d(dtype=wp.vec3)


@wp.struct
class MSICell:
    """A background sample's corners: first layer, row and the two (wrapped) columns, and fractions."""

    valid: int
    layer: int
    row: int
    col0: int
    col1: int
    frac: wp.vec3  # layer, row, column


@wp.func
def msi_locate(msi: MSIView, o_world: wp.vec3, d: wp.vec3, k: int) -> MSICell:
    """Sample `k` of the ray: where it leaves the sphere of inverse radius (1 - (k + 1/2) / K) / r0."""
    count = msi.samples_per_layer * (msi.layers - 1)
    s = 1.0 - (float(k) + 0.5) / float(count)
    radius = msi.radius / s
    o = o_world - msi.center
    b = wp.dot(o, d)
    disc = b * b - (wp.dot(o, o) - radius * radius)
    t = -b + wp.sqrt(wp.max(disc, 0.0))
    cell = MSICell()
    cell.valid = 0
    if disc < 0.0 or t <= 0.0:
        return cell  # no sample: nothing below is read
    cell.valid = 1
    p = o + t * d
    v = p / wp.length(p)
    theta = wp.acos(wp.clamp(v[2], -1.0, 1.0))
    phi = wp.atan2(v[1], v[0])
    row = wp.clamp(theta * (float(msi.height) / PI) - 0.5, 0.0, float(msi.height) - 1.0)
    col = (phi + PI) * (float(msi.width) / (2.0 * PI)) - 0.5
    z = wp.clamp((float(k) + 0.5) / float(msi.samples_per_layer), 0.0, float(msi.layers) - 1.0)
    layer = wp.min(int(wp.floor(z)), msi.layers - 2)
    r0 = wp.min(int(wp.floor(row)), msi.height - 2)
    c0f = wp.floor(col)
    c0 = int(c0f)
    cell.layer = layer
    cell.row = r0
    cell.col0 = ((c0 % msi.width) + msi.width) % msi.width
    cell.col1 = (((c0 + 1) % msi.width) + msi.width) % msi.width
    cell.frac = wp.vec3(z - float(layer), row - float(r0), col - c0f)
    return cell


@wp.func
def corner_weight(cell: MSICell, n: int) -> float:
    wz = wp.where(((n >> 2) & 1) == 1, cell.frac[0], 1.0 - cell.frac[0])
    wr = wp.where(((n >> 1) & 1) == 1, cell.frac[1], 1.0 - cell.frac[1])
    wc = wp.where((n & 1) == 1, cell.frac[2], 1.0 - cell.frac[2])
    return wz * wr * wc


@wp.func
def corner_col(cell: MSICell, n: int) -> int:
    return wp.where((n & 1) == 1, cell.col1, cell.col0)


@wp.func
def msi_sigma(msi: MSIView, cell: MSICell) -> float:
    sigma = wp.float32(0.0)
    for n in range(8):
        sigma += (
            corner_weight(cell, n)
            * msi.density[cell.layer + (n >> 2), cell.row + ((n >> 1) & 1), corner_col(cell, n)]
        )
    return sigma


@wp.func
def msi_sample(
    msi: MSIView, o: wp.vec3, d: wp.vec3, k: int, params: MarchParams, dz: float, t: float, log_t: float
):
    """Sample `k` of a ray: its cell, whether it is live (in the MSI with a density above
    `sigma_thresh`), and the `composite` step (optical length `dz`) it takes from transmittance `t`
    (= exp(`log_t`))."""
    cell = msi_locate(msi, o, d, k)
    step = wp.vec4(0.0, log_t, t, 0.0)
    live = False
    if cell.valid != 0:
        sigma = msi_sigma(msi, cell)
        if sigma > params.sigma_thresh:
            live = True
            step = composite(t, log_t, sigma * dz, params.stop_thresh)
    return cell, live, step


@wp.func
def msi_preact(msi: MSIView, cell: MSICell) -> wp.vec3:
    """Interpolated raw colour (before the ReLU)."""
    pre = wp.vec3(0.0, 0.0, 0.0)
    for n in range(8):
        pre += (
            corner_weight(cell, n)
            * msi.color[cell.layer + (n >> 2), cell.row + ((n >> 1) & 1), corner_col(cell, n)]
        )
    return pre


@wp.func
def relu3(v: wp.vec3) -> wp.vec3:
    return wp.vec3(wp.max(v[0], 0.0), wp.max(v[1], 0.0), wp.max(v[2], 0.0))


@KERNEL
def msi_forward_kernel(
    msi: MSIView, params: MarchParams, rays: Rays, first_ray: int, out_rgb: wp.array(dtype=wp.vec3)
):
    tid = wp.tid() + first_ray
    o = rays.origins[tid]
    d = rays.dirs[tid]
    dz = 1.0 / float(msi.samples_per_layer)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    log_t = wp.float32(0.0)
    t_end = wp.float32(1.0)
    for k in range(msi.samples_per_layer * (msi.layers - 1)):
        cell, live, step = msi_sample(msi, o, d, k, params, dz, t_end, log_t)
        if live:
            rgb = rgb + step[0] * relu3(msi_preact(msi, cell))
            log_t = step[1]
            t_end = step[2]
            if step[3] != 0.0:
                t_end = 0.0
                break
    out_rgb[tid] = rgb + wp.vec3(t_end * params.background_brightness)


@KERNEL
def msi_backward_kernel(
    msi: MSIView,
    params: MarchParams,
    rays: Rays,
    first_ray: int,
    out_rgb: wp.array(dtype=wp.vec3),
    grad_rgb: wp.array(dtype=wp.vec3),
    grads: MSIGradientTargets,
):
    tid = wp.tid() + first_ray
    o = rays.origins[tid]
    d = rays.dirs[tid]
    g = grad_rgb[tid]
    dz = 1.0 / float(msi.samples_per_layer)
    remaining = wp.dot(g, out_rgb[tid])
    log_t = wp.float32(0.0)
    t_after = wp.float32(1.0)
    for k in range(msi.samples_per_layer * (msi.layers - 1)):
        cell, live, step = msi_sample(msi, o, d, k, params, dz, t_after, log_t)
        if live:
            weight = step[0]
            pre = msi_preact(msi, cell)
            g_dot_c = wp.dot(g, relu3(pre))
            log_t = step[1]
            t_after = step[2]
            remaining = remaining - weight * g_dot_c
            d_sigma = dz * (t_after * g_dot_c - remaining)
            d_color = wp.vec3(
                wp.where(pre[0] > 0.0, weight * g[0], 0.0),
                wp.where(pre[1] > 0.0, weight * g[1], 0.0),
                wp.where(pre[2] > 0.0, weight * g[2], 0.0),
            )
            for n in range(8):
                w = corner_weight(cell, n)
                li = cell.layer + (n >> 2)
                ri = cell.row + ((n >> 1) & 1)
                ci = corner_col(cell, n)
                wp.atomic_add(grads.density, li, ri, ci, w * d_sigma)
                wp.atomic_add(grads.color, li, ri, ci, w * d_color)
            if step[3] != 0.0:
                break
