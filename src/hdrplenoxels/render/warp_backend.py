"""Warp ray-march kernels (one thread per ray) with a hand-written backward, for CPU and CUDA.

The math is exactly that of `render/reference.py` (method-spec §2); `tests/test_render_parity.py`
holds the two together. Warp's automatic adjoint is wrong for this loop (dynamic trip count, early
break), so it is switched off and the backward kernel re-marches each ray svox2-style:
with G = <dL, L> and G <- G - w_k <dL, c_k> after each sample,
  dLoss/dsigma_k = delta * (T_{k+1} <dL, c_k> - G),  dLoss/dsh_k = w_k dL_c [pre_c > 0] Y_j,
each spread over the 8 trilinear corners (empty corners receive nothing).
"""

from __future__ import annotations

import functools
import logging

import torch
import warp as wp

from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.render.options import RenderOptions
from hdrplenoxels.render.reference import TINY_DIR
from hdrplenoxels.sh import SH_C0, SH_C1, SH_C2

wp.config.log_level = logging.WARNING  # no start-up banner or per-module load lines
wp.init()
wp.set_module_options({"enable_backward": False})
# Loop-carried scalars are declared as wp.float32(...) so Warp treats them as dynamic variables.

vec9 = wp.types.vector(length=9, dtype=wp.float32)

C0 = wp.constant(SH_C0)
C1 = wp.constant(SH_C1)
C20 = wp.constant(SH_C2[0])
C21 = wp.constant(SH_C2[1])
C22 = wp.constant(SH_C2[2])
C23 = wp.constant(SH_C2[3])
C24 = wp.constant(SH_C2[4])


@wp.func
def sh_basis(d: wp.vec3) -> vec9:
    x = d[0]
    y = d[1]
    z = d[2]
    return vec9(
        C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C20 * x * y,
        C21 * y * z,
        C22 * (2.0 * z * z - x * x - y * y),
        C23 * x * z,
        C24 * (x * x - y * y),
    )


@wp.func
def safe_dir(v: float) -> float:
    if v == 0.0:
        return float(TINY_DIR)
    return v


@wp.struct
class Ray:
    origin: wp.vec3  # grid units
    direction: wp.vec3  # unit, grid space
    delta: float  # segment length of one step in world/NDC units
    t_min: float
    num_samples: int


@wp.func
def setup_ray(
    o_world: wp.vec3,
    d_world: wp.vec3,
    scale: wp.vec3,
    offset: wp.vec3,
    reso: wp.vec3i,
    step: float,
    t_far: float,
) -> Ray:
    o = wp.cw_mul(o_world, scale) + offset
    d = wp.cw_mul(d_world, scale)
    nrm = wp.length(d)
    d = wp.vec3(d[0] / nrm, d[1] / nrm, d[2] / nrm)
    t_min = wp.float32(0.0)
    t_max = t_far
    lo = wp.float32(-1.0e30)
    hi = wp.float32(1.0e30)
    for a in range(3):
        da = safe_dir(d[a])
        t1 = (-0.5 - o[a]) / da
        t2 = (float(reso[a]) - 0.5 - o[a]) / da
        lo = wp.max(lo, wp.min(t1, t2))
        hi = wp.min(hi, wp.max(t1, t2))
    t_min = wp.max(lo, t_min)
    t_max = wp.min(hi, t_max)
    r = Ray()
    r.origin = o
    r.direction = d
    r.delta = step / nrm
    r.t_min = t_min
    r.num_samples = 0
    if t_min <= t_max:
        r.num_samples = int(wp.floor((t_max - t_min) / step)) + 1
    return r


@wp.struct
class Cell:
    base: wp.vec3i
    frac: wp.vec3


@wp.func
def locate(p: wp.vec3, reso: wp.vec3i) -> Cell:
    c = Cell()
    for a in range(3):
        pa = wp.min(wp.max(p[a], 0.0), float(reso[a] - 1))
        b = wp.min(int(wp.floor(pa)), reso[a] - 2)
        c.base[a] = b
        c.frac[a] = pa - float(b)
    return c


@wp.func
def corner_weight(c: Cell, i: int, j: int, k: int) -> float:
    wx = c.frac[0]
    if i == 0:
        wx = 1.0 - c.frac[0]
    wy = c.frac[1]
    if j == 0:
        wy = 1.0 - c.frac[1]
    wz = c.frac[2]
    if k == 0:
        wz = 1.0 - c.frac[2]
    return wx * wy * wz


@wp.func
def corner_row(links: wp.array3d(dtype=wp.int32), c: Cell, i: int, j: int, k: int) -> int:
    return links[c.base[0] + i, c.base[1] + j, c.base[2] + k]


@wp.func
def sample_sigma(links: wp.array3d(dtype=wp.int32), density: wp.array(dtype=wp.float32), c: Cell) -> float:
    s = wp.float32(0.0)
    for n in range(8):
        i = n >> 2
        j = (n >> 1) & 1
        k = n & 1
        row = corner_row(links, c, i, j, k)
        if row >= 0:
            s += corner_weight(c, i, j, k) * density[row]
    return s


@functools.cache
def kernels_for(bdim: int):
    """Forward and backward kernels specialised for `bdim` SH coefficients per channel.

    `bdim` is captured as a compile-time constant, so the per-coefficient loops are unrolled.
    """

    @wp.func
    def sample_preact(
        links: wp.array3d(dtype=wp.int32), sh: wp.array2d(dtype=wp.float32), c: Cell, basis: vec9
    ) -> wp.vec3:
        """SH . basis per channel at the sample (before the +0.5 and the ReLU)."""
        pre = wp.vec3(0.0, 0.0, 0.0)
        for n in range(8):
            i = n >> 2
            j = (n >> 1) & 1
            k = n & 1
            row = corner_row(links, c, i, j, k)
            if row >= 0:
                w = corner_weight(c, i, j, k)
                for ch in range(3):
                    acc = wp.float32(0.0)
                    for b in range(bdim):
                        acc += sh[row, ch * bdim + b] * basis[b]
                    pre[ch] = pre[ch] + w * acc
        return pre

    @wp.func
    def relu_color(pre: wp.vec3) -> wp.vec3:
        return wp.vec3(wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0))

    @wp.kernel(module="unique")
    def render_forward_kernel(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array2d(dtype=wp.float32),
        scale: wp.vec3,
        offset: wp.vec3,
        reso: wp.vec3i,
        step: float,
        sigma_thresh: float,
        stop_thresh: float,
        t_far: float,
        background: float,
        out_rgb: wp.array(dtype=wp.vec3),
    ):
        tid = wp.tid()
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        basis = sh_basis(dirs[tid])
        rgb = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_end = wp.float32(1.0)
        for s in range(r.num_samples):
            t = r.t_min + float(s) * step
            cell = locate(r.origin + t * r.direction, reso)
            sigma = sample_sigma(links, density, cell)
            if sigma > sigma_thresh:
                tau = sigma * r.delta
                weight = wp.exp(log_t) * (1.0 - wp.exp(-tau))
                rgb = rgb + weight * relu_color(sample_preact(links, sh, cell, basis))
                log_t = log_t - tau
                t_end = wp.exp(log_t)
                if t_end < stop_thresh:
                    t_end = 0.0
                    break
        out_rgb[tid] = rgb + wp.vec3(t_end * background)

    @wp.kernel(module="unique")
    def render_backward_kernel(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array2d(dtype=wp.float32),
        scale: wp.vec3,
        offset: wp.vec3,
        reso: wp.vec3i,
        step: float,
        sigma_thresh: float,
        stop_thresh: float,
        t_far: float,
        out_rgb: wp.array(dtype=wp.vec3),
        grad_rgb: wp.array(dtype=wp.vec3),
        grad_density: wp.array(dtype=wp.float32),
        grad_sh: wp.array2d(dtype=wp.float32),
    ):
        tid = wp.tid()
        g = grad_rgb[tid]
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        basis = sh_basis(dirs[tid])
        remaining = wp.dot(g, out_rgb[tid])  # <g, everything behind the current sample, background included>
        log_t = wp.float32(0.0)
        for s in range(r.num_samples):
            t = r.t_min + float(s) * step
            cell = locate(r.origin + t * r.direction, reso)
            sigma = sample_sigma(links, density, cell)
            if sigma > sigma_thresh:
                tau = sigma * r.delta
                t_before = wp.exp(log_t)
                weight = t_before * (1.0 - wp.exp(-tau))
                pre = sample_preact(links, sh, cell, basis)
                color = relu_color(pre)
                g_dot_c = wp.dot(g, color)
                log_t = log_t - tau
                t_after = wp.exp(log_t)
                remaining = remaining - weight * g_dot_c
                d_sigma = r.delta * (t_after * g_dot_c - remaining)
                for n in range(8):
                    i = n >> 2
                    j = (n >> 1) & 1
                    k = n & 1
                    row = corner_row(links, cell, i, j, k)
                    if row >= 0:
                        cw = corner_weight(cell, i, j, k)
                        wp.atomic_add(grad_density, row, cw * d_sigma)
                        for ch in range(3):
                            if pre[ch] + 0.5 > 0.0:
                                gc = cw * weight * g[ch]
                                for b in range(bdim):
                                    wp.atomic_add(grad_sh, row, ch * bdim + b, gc * basis[b])
                if t_after < stop_thresh:
                    break

    return render_forward_kernel, render_backward_kernel


def _device_of(t: torch.Tensor) -> str:
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


def _march_inputs(density, sh, links, origins, dirs, scale, offset, opt: RenderOptions) -> list:
    """The leading kernel arguments shared by the forward and backward kernels (same order in both)."""
    return [
        wp.from_torch(origins, dtype=wp.vec3, requires_grad=False),
        wp.from_torch(dirs, dtype=wp.vec3, requires_grad=False),
        wp.from_torch(links, requires_grad=False),
        wp.from_torch(density.detach(), requires_grad=False),
        wp.from_torch(sh.detach(), requires_grad=False),
        wp.vec3(*scale.tolist()),
        wp.vec3(*offset.tolist()),
        wp.vec3i(*links.shape),
        opt.step_size,
        opt.sigma_thresh,
        opt.stop_thresh,
        opt.t_max,
    ]


class _WarpRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, sh, links, origins, dirs, scale, offset, opt: RenderOptions):
        device = _device_of(density)
        origins = origins.contiguous().float()
        dirs = dirs.contiguous().float()
        out = torch.empty_like(origins)
        forward_kernel, _ = kernels_for(sh.shape[1] // 3)
        inputs = _march_inputs(density, sh, links, origins, dirs, scale, offset, opt) + [opt.background]
        with _stream_for(device):
            wp.launch(
                forward_kernel,
                dim=origins.shape[0],
                inputs=inputs,
                outputs=[wp.from_torch(out, dtype=wp.vec3, requires_grad=False)],
                device=device,
            )
        ctx.save_for_backward(density, sh, links, origins, dirs, out, scale, offset)
        ctx.opt = opt
        return out

    @staticmethod
    def backward(ctx, grad_out):
        density, sh, links, origins, dirs, out, scale, offset = ctx.saved_tensors
        device = _device_of(density)
        grad_density = torch.zeros_like(density)
        grad_sh = torch.zeros_like(sh)
        _, backward_kernel = kernels_for(sh.shape[1] // 3)
        inputs = _march_inputs(density, sh, links, origins, dirs, scale, offset, ctx.opt) + [
            wp.from_torch(out, dtype=wp.vec3, requires_grad=False),
            wp.from_torch(grad_out.contiguous().float(), dtype=wp.vec3, requires_grad=False),
            wp.from_torch(grad_density, requires_grad=False),
            wp.from_torch(grad_sh, requires_grad=False),
        ]
        with _stream_for(device):
            wp.launch(backward_kernel, dim=origins.shape[0], inputs=inputs, device=device)
        return grad_density, grad_sh, None, None, None, None, None, None


class _NullContext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _stream_for(device: str):
    """Run Warp on torch's current CUDA stream so both see the same ordering; nothing to do on CPU."""
    if device == "cpu":
        return _NullContext()
    return wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream()))


def render_warp(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions = RenderOptions()
) -> torch.Tensor:
    """Linear radiance (N, 3); differentiable w.r.t. `grid.density` and `grid.sh`."""
    scale, offset = grid.world_to_grid_affine()
    if origins.shape[0] == 0:
        return origins.new_zeros((0, 3))
    return _WarpRender.apply(grid.density, grid.sh, grid.links, origins, dirs, scale, offset, opt)
