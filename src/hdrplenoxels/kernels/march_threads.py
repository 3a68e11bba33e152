"""The one-thread-per-ray backward kernel (the CPU's, and the only one that replays a `SampleRecord`),
and the SH functions of the one-thread-per-ray layout, which the forward of `kernels/march_forward.py`
shares.

The math is exactly that of `kernels/march_reference.py` (`docs/method.md`, "Rendering");
`tests/test_render_parity.py` holds the two together. Warp's automatic adjoint is wrong for this loop
(dynamic trip count, early break), so it is switched off and the backward kernel re-marches each ray
svox2-style: with G = <dL, L> and G <- G - w_k <dL, c_k> after each sample,
  dLoss/dsigma_k = delta * (T_{k+1} <dL, c_k> - G),  dLoss/dsh_k = w_k dL_c [pre_c > 0] Y_j,
each spread over the 8 trilinear corners (empty corners receive nothing).

Given a `SampleRecord`, the forward writes each ray's contributing samples (index, density,
colour) and the backward replays them, re-marching only past a full record: the same arithmetic on
the same values, so the same gradients, without reading density and SH again.

Oracle: `hdrplenoxels.kernels.march_reference.render_reference`; parity: tests/test_render_parity.py.
"""

# No `from __future__ import annotations` here: Warp evaluates a struct's annotations, and those of
# `gradient_targets_for` name a closure variable.
import functools

import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, mark_touched
from hdrplenoxels.kernels import march_funcs as mf


@wp.struct
class Record:
    """A `SampleRecord` as a kernel argument (`capacity` 0: none, its arrays never read)."""

    capacity: int
    index: wp.array2d(dtype=wp.int32)
    values: wp.array2d(dtype=wp.vec4)
    count: wp.array(dtype=wp.int32)


@wp.struct
class Composite:
    """The backward's running state along a ray: log and value of the transmittance after the
    current sample, <dL, colour still to come behind it> (background included), and for the distortion
    loss the sums over the samples so far and the weighted gradient still to come."""

    log_t: float
    t_after: float
    remaining: float
    dist_before: wp.vec3
    dist_remaining: float


@functools.cache
def gradient_targets_for(bdim: int):
    """The struct of one backward thread's gradient buffers, SH rows as vectors of 3 * `bdim`."""

    @wp.struct
    class GradientTargets:
        """Where a backward thread adds: d(loss)/d(density), d(loss)/d(SH rows), and the rows it
        added to (`GridGradients.touched`, shared by all threads: every writer stores 1)."""

        density: wp.array(dtype=wp.float32)
        sh: wp.array(dtype=mf.sh_row(bdim))
        touched: wp.array(dtype=wp.uint8)

    return GradientTargets


@functools.cache
def sh_rules_for(bdim: int):
    """The SH functions of the thread kernels for `bdim` coefficients per channel (a compile-time
    constant, so their loops are unrolled): interpolation at a sample, colour before the ReLU, and the
    colour's gradient with respect to the coefficients."""
    vec_sh = mf.sh_row(bdim)

    @wp.func
    def interpolate_sh(sh: wp.array(dtype=vec_sh), c: mf.Corners) -> vec_sh:
        out = vec_sh()
        for n in range(8):
            out += c.weights[n] * sh[c.rows[n]]
        return out

    @wp.func
    def sample_preact(coeffs: vec_sh, basis: mf.vec9) -> wp.vec3:
        """SH . basis per channel at the sample (before the +0.5 and the ReLU)."""
        pre = wp.vec3(0.0, 0.0, 0.0)
        for ch in range(3):
            acc = wp.float32(0.0)
            for b in range(bdim):
                acc += coeffs[ch * bdim + b] * basis[b]
            pre[ch] = acc
        return pre

    @wp.func
    def sh_gradient(color: wp.vec3, scale: wp.vec3, basis: mf.vec9) -> vec_sh:
        """d(<scale, colour>)/d(SH coefficients): ReLU-gated outer product of channel and basis
        (colour = ReLU(pre + 0.5) is > 0 exactly where the ReLU passes its gradient)."""
        out = vec_sh()
        for ch in range(3):
            gated = wp.where(color[ch] > 0.0, scale[ch], 0.0)
            for b in range(bdim):
                out[ch * bdim + b] = gated * basis[b]
        return out

    return interpolate_sh, sample_preact, sh_gradient


@functools.cache
def backprop_for(bdim: int):
    """`backprop_sample` for `bdim` SH coefficients per channel: one sample's gradient, the backward's
    step along the ray."""
    _, _, sh_gradient = sh_rules_for(bdim)
    GradientTargets = gradient_targets_for(bdim)

    @wp.func
    def backprop_sample(
        state: Composite,
        corners: mf.Corners,
        sigma: float,
        color: wp.vec3,
        g: wp.vec3,
        basis: mf.vec9,
        delta: float,
        s: float,
        dist_total: wp.vec3,
        dist_weight: float,
        near: float,
        grads: GradientTargets,
    ) -> Composite:
        """Add one contributing sample's gradient, scaled by `near` (`march_funcs.near_factor`), to its 8
        corners; returns the state behind it."""
        step = mf.composite(state.t_after, state.log_t, sigma * delta, 0.0)  # the caller tests the stop
        weight = step[0]
        g_dot_c = wp.dot(g, color)
        out = Composite()
        out.log_t = step[1]
        out.t_after = step[2]
        out.remaining = state.remaining - weight * g_dot_c
        d_sigma = delta * (out.t_after * g_dot_c - out.remaining)
        out.dist_before = state.dist_before
        out.dist_remaining = state.dist_remaining
        if dist_weight != 0.0:
            g_w = dist_weight * mf.distortion_dw(state.dist_before, dist_total, weight, s)
            out.dist_remaining = state.dist_remaining - weight * g_w
            d_sigma += delta * (out.t_after * g_w - out.dist_remaining)
            out.dist_before = mf.distortion_add(state.dist_before, weight, s)
        d_sh = sh_gradient(color, weight * g, basis)
        for n in range(8):
            if corners.present[n] != 0:
                row = corners.rows[n]
                cw = corners.weights[n] * near
                wp.atomic_add(grads.density, row, cw * d_sigma)
                wp.atomic_add(grads.sh, row, cw * d_sh)
                mark_touched(grads.touched, row)
        return out

    return backprop_sample


@functools.cache
def thread_backward_for(bdim: int, variant: mf.KernelVariant = mf.GENERAL):
    """The backward kernel for `bdim` SH coefficients per channel and `variant` (see
    `march_forward.forward_for`): the re-march of this module's docstring."""
    vec_sh = mf.sh_row(bdim)
    interpolate_sh, sample_preact, _ = sh_rules_for(bdim)
    backprop_sample = backprop_for(bdim)
    GradientTargets = gradient_targets_for(bdim)
    levels_fixed, distortion_fixed, near_fixed, _, record_fixed = variant.switches()

    @KERNEL(cuda_max_registers=variant.max_registers)
    def render_backward_kernel(
        grid: mf.GridView,
        sh: wp.array(dtype=vec_sh),
        params: mf.MarchParams,
        rays: mf.Rays,
        first_ray: int,
        out_rgb: wp.array(dtype=wp.vec3),
        grad_rgb: wp.array(dtype=wp.vec3),
        record: Record,
        dist: mf.DistortionLink,
        grads: GradientTargets,
    ):
        tid = wp.tid() + first_ray
        g = grad_rgb[tid]
        r = mf.setup_ray(
            rays.origins[tid], rays.dirs[tid], grid, params, mf.fixed_levels(levels_fixed, grid.levels)
        )
        near_on = mf.feature_on(near_fixed, params.near_grad > 0.0)
        record_on = mf.feature_on(record_fixed, record.capacity > 0)
        inv_step = 1.0 / params.step
        basis = mf.sh_basis(rays.dirs[tid])
        state = Composite()
        state.log_t = 0.0
        state.t_after = 1.0
        state.remaining = wp.dot(g, out_rgb[tid])
        dist_total = wp.vec3(0.0, 0.0, 0.0)
        dist_weight = wp.float32(0.0)
        state.dist_before = wp.vec3(0.0, 0.0, 0.0)
        state.dist_remaining = 0.0  # sum_k w_k dL/dw_k = 2 loss
        if mf.feature_on(distortion_fixed, dist.enabled != 0):
            dist_total = dist.stats[tid]
            dist_weight = dist.weight[tid] * mf.distortion_scale(r)  # per unit of the index loss
            state.dist_remaining = dist.weight[tid] * 2.0 * dist_total[2]
        # First the samples the forward recorded: their density and colour need no grid reads.
        recorded = wp.int32(0)
        if record_on:
            recorded = record.count[tid]
        resume = wp.int32(0)  # the first sample the march below must look at
        slot = mf.first_slot(r, grid, params)
        for k in range(recorded):
            s = record.index[tid, k]
            v = record.values[tid, k]
            slot = mf.slot_holding(r, slot, s, grid, params)
            cell = mf.sample_cell(r, s, slot, grid.reso)
            corners = mf.corner_rows(grid.links, cell)
            delta = mf.sample_delta(r, cell)
            color = wp.vec3(v[1], v[2], v[3])
            near = mf.near_factor(slot, s, params, near_on)
            state = backprop_sample(
                state, corners, v[0], color, g, basis, delta, float(s), dist_total, dist_weight, near, grads
            )
            if state.t_after < params.stop_thresh:
                return
            resume = s + 1
        if record_on and recorded < record.capacity:
            return  # the record holds every contributing sample of this ray
        # Then march the rest (all of it without a record), recomputing density and colour.
        visit = mf.next_visit(r, slot, resume, inv_step, grid, params)
        while visit.s < r.num_samples:
            corners = mf.fetch_corners(grid, visit.cell)
            sigma = corners.sigma
            if sigma > params.sigma_thresh:
                color = mf.relu_color(sample_preact(interpolate_sh(sh, corners), basis))
                delta = mf.sample_delta(r, visit.cell)
                state = backprop_sample(
                    state,
                    corners,
                    sigma,
                    color,
                    g,
                    basis,
                    delta,
                    float(visit.s),
                    dist_total,
                    dist_weight,
                    mf.near_factor(visit.slot, visit.s, params, near_on),
                    grads,
                )
                if state.t_after < params.stop_thresh:
                    break
            visit = mf.next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)

    return render_backward_kernel
