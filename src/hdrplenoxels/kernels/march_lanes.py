"""The lane layout, CUDA's default: a block of lanes (a warp of 32 on CUDA) marches one ray. Here its SH
functions and its backward kernel; its forward is `kernels/march_forward.py`'s in this layout.

One thread per ray leaves a GPU mostly idle on a 5000-ray batch and strides through SH rows; here
every lane walks the same samples (the shared march of `kernels/march_funcs.py`, recomputed identically in
each) and owns a share of the SH coefficients, so loads are contiguous across the block and the
colour is a block-wide sum (svox2's layout). They keep no `SampleRecord`. On the CPU they run with
`wp.config.enable_cpu_blocks` in the tests, one lane wide otherwise.

Oracle: `hdrplenoxels.kernels.march_reference.render_reference`; parity: tests/test_render_parity.py.
"""

import functools
from typing import Any

import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, mark_touched
from hdrplenoxels.kernels import march_funcs as mf


@wp.struct
class LaneGradientTargets:
    """Where the lane backward adds: d(loss)/d(density), d(loss)/d(SH) as (rows, coefficients), and
    the rows it added to (`GridGradients.touched`)."""

    density: wp.array(dtype=wp.float32)
    sh: wp.array2d(dtype=wp.float32)
    touched: wp.array(dtype=wp.uint8)


@wp.func
def pick9(v: mf.vec9, i: int) -> float:
    """`v[i]` for a run-time `i` by selects: a run-time index would put `v` in local memory on CUDA
    (`benchmarks/kernel_resources.py` reports each kernel's local memory)."""
    out = wp.float32(0.0)
    for m in range(9):
        out = wp.where(m == i, v[m], out)
    return out


@wp.func
def pick8i(v: mf.vec8i, i: int) -> int:
    """`v[i]` for a run-time `i`, by selects (see `pick9`)."""
    out = v[0]
    for m in range(1, 8):
        out = wp.where(m == i, v[m], out)
    return out


@wp.func
def pick3(v: wp.vec3, i: int) -> float:
    """`v[i]` for a run-time `i`, by selects (see `pick9`)."""
    return wp.where(i == 0, v[0], wp.where(i == 1, v[1], v[2]))


@wp.func
def in_channel(ch: int, x: float) -> wp.vec3:
    """`x` in channel `ch` (a run-time index), zero in the others."""
    return wp.vec3(wp.where(ch == 0, x, 0.0), wp.where(ch == 1, x, 0.0), wp.where(ch == 2, x, 0.0))


def per_lane_count(bdim: int, lanes: int) -> int:
    """SH coefficients a lane owns (of 3 `bdim`), at most: c, c + lanes, ..."""
    return (3 * bdim + lanes - 1) // lanes


# A float summed over the `width` lanes of a warp that hold this thread's ray (aligned runs of `width`, a
# power of two: a block's rays are consecutive runs of its threads) by a butterfly of register shuffles,
# every lane left with the sum; on a CPU (one lane a ray) the value itself.
_SHUFFLE_SUM = """
#if defined(__CUDA_ARCH__)
    const unsigned lane = threadIdx.x & 31u;
    const unsigned mask = width >= 32 ? 0xffffffffu : (((1u << width) - 1u) << (lane - lane % width));
    float r = x;
    for (int offset = width >> 1; offset > 0; offset >>= 1)
        r += __shfl_xor_sync(mask, r, offset, width);
    return r;
#else
    return x;
#endif
"""


@wp.func_native(_SHUFFLE_SUM)
def shuffle_sum(x: float, width: int) -> float: ...


@functools.cache
def lane_sh_for(bdim: int, lanes: int, shuffle: bool = False):
    """The SH part of the lane forward and backward for `bdim` coefficients per channel and blocks of
    `lanes` lanes (a compile-time constant): the vector of one lane's coefficients, that lane's basis
    values, and the colour before the ReLU summed over the block (`shuffle`: by warp shuffles, CUDA only,
    see `KernelVariant.shuffle_sum`)."""
    ncoef = 3 * bdim
    per_lane = per_lane_count(bdim, lanes)
    lane_vec = wp.types.vector(length=per_lane, dtype=wp.float32)

    @wp.func
    def own_basis(basis: mf.vec9, lane: int) -> lane_vec:
        """The SH basis values of this lane's coefficients, taken once per ray: the march then keeps
        `per_lane` of them (one with 32 lanes) rather than all 9."""
        out = lane_vec()
        for j in range(per_lane):
            k = lane + j * lanes
            if k < ncoef:
                out[j] = pick9(basis, k - (k // bdim) * bdim)
        return out

    @wp.func
    def own_preact(sh: wp.array2d(dtype=wp.float32), c: mf.Corners, own: lane_vec, lane: int) -> wp.vec3:
        """SH . basis per channel at the sample (before the +0.5 and the ReLU), each lane adding its own
        coefficients (`own_basis`), summed over the block."""
        part = wp.vec3(0.0, 0.0, 0.0)
        for j in range(per_lane):
            k = lane + j * lanes
            if k < ncoef:
                coef = wp.float32(0.0)
                for n in range(8):
                    coef += c.weights[n] * sh[c.rows[n], k]
                part = part + in_channel(k // bdim, coef * own[j])
        if wp.static(shuffle):
            return wp.vec3(
                shuffle_sum(part[0], lanes), shuffle_sum(part[1], lanes), shuffle_sum(part[2], lanes)
            )
        return wp.tile_extract(wp.tile_sum(wp.tile(part, preserve_type=True)), 0)

    return lane_vec, own_basis, own_preact


@functools.cache
def ray_of_thread_for(lanes: int, per_block: int):
    """The ray and lane of block `i`'s thread `thread` when a block holds `per_block` rays, each `lanes`
    threads (`KernelVariant.rays_per_block`): with several, ray -1 for the last block's threads past the
    last ray, which must return at once (whole rays, so no block-wide sum waits on them). The kernels test
    for -1 only where a block holds several rays (`wp.static`): with one, the test cost the lane forward 2
    registers (benchmarks/RESULTS.md, "One forward kernel")."""

    @wp.func
    def ray_of_thread(i: int, thread: int, first_ray: int, n: int):
        if wp.static(per_block > 1):
            ray = i * per_block + thread // lanes + first_ray
            return wp.where(ray < n, ray, -1), thread % lanes
        return i + first_ray, thread

    return ray_of_thread


@functools.cache
def slot_rules_for(bdim: int, lanes: int, rows_from_corners: bool = False):
    """The pending-gradient slots of `lane_backward_for` (its docstring says why) for `bdim` SH
    coefficients per channel and blocks of `lanes` lanes: their struct, a sample's gated SH gradient,
    what one sample adds to the slots, and their flush into the grid (`rows_from_corners`: see
    `KernelVariant.rows_from_corners`)."""
    ncoef = 3 * bdim
    per_lane = per_lane_count(bdim, lanes)
    lane_vec = lane_sh_for(bdim, lanes)[0]
    slot_mat = wp.types.matrix(shape=(8, per_lane), dtype=wp.float32)

    @wp.struct
    class PendingSlots:
        """The vertex (grid row, -1: none) each slot holds and its pending density and SH gradients
        (this lane's coefficients)."""

        rows: mf.vec8i
        density: mf.vec8
        sh: slot_mat

    @wp.func
    def no_pending() -> PendingSlots:
        out = PendingSlots()
        out.rows = mf.vec8i(-1, -1, -1, -1, -1, -1, -1, -1)
        out.density = mf.vec8()
        out.sh = slot_mat()
        return out

    @wp.func
    def gated_gradient(pre: wp.vec3, g: wp.vec3, weight: float, own: lane_vec, lane: int) -> lane_vec:
        """d(loss)/d(interpolated coefficient) of this lane's coefficients at a sample of `weight`."""
        gated = lane_vec()
        for j in range(per_lane):
            k = lane + j * lanes
            if k < ncoef:
                ch = k // bdim
                passed = pick3(pre, ch) + 0.5 > 0.0
                gated[j] = wp.where(passed, weight * pick3(g, ch), 0.0) * own[j]
        return gated

    @wp.func
    def flush_slot(
        row: int, slot: int, d_density: float, d_sh: lane_vec, lane: int, grads: LaneGradientTargets
    ):
        """Add one slot's pending gradient into vertex `row` (nothing for an empty slot, row -1)."""
        if row >= 0:
            if slot % lanes == lane:
                wp.atomic_add(grads.density, row, d_density)
                mark_touched(grads.touched, row)
            for j in range(per_lane):
                k = lane + j * lanes
                if k < ncoef:
                    wp.atomic_add(grads.sh, row, k, d_sh[j])

    @wp.func
    def add_to_slots(
        pending: PendingSlots,
        rows_from: Any,
        cell: mf.Cell,
        scale: float,
        d_sigma: float,
        gated: lane_vec,
        lane: int,
        grads: LaneGradientTargets,
    ) -> PendingSlots:
        """One sample's gradient (d_sigma, `gated`) into the slots of its 8 corners, times their trilinear
        weights and `scale`; a slot whose vertex changes is flushed first. Each slot's row comes from
        `rows_from`: the grid's links (the default), or with `rows_from_corners` the sample's `Corners`
        (an empty corner -1, as its link), picked by selects. The corner's row and weight are computed
        again rather than read from `Corners` at index slot ^ parity: a run-time index would put `Corners`
        and the slots in local memory on CUDA; the reads of the links hit L1."""
        out = pending
        base = cell.base
        frac = cell.frac
        for slot in range(8):  # slot bits = vertex parity
            ci = ((slot >> 2) & 1) ^ (base[0] & 1)
            cj = ((slot >> 1) & 1) ^ (base[1] & 1)
            ck = (slot & 1) ^ (base[2] & 1)
            if wp.static(rows_from_corners):
                n = (ci << 2) | (cj << 1) | ck  # `corner_rows`' order
                row = wp.where(pick8i(rows_from.present, n) != 0, pick8i(rows_from.rows, n), -1)
            else:
                row = rows_from[cell.level, base[0] + ci, base[1] + cj, base[2] + ck]
            if row != out.rows[slot]:
                flush_slot(out.rows[slot], slot, out.density[slot], out.sh[slot], lane, grads)
                out.rows[slot] = row
                out.density[slot] = 0.0
                out.sh[slot] = lane_vec()
            wx = wp.where(ci == 1, frac[0], 1.0 - frac[0])
            wy = wp.where(cj == 1, frac[1], 1.0 - frac[1])
            wz = wp.where(ck == 1, frac[2], 1.0 - frac[2])
            w = wx * wy * wz * scale
            out.density[slot] = out.density[slot] + w * d_sigma
            out.sh[slot] = out.sh[slot] + w * gated
        return out

    @wp.func
    def flush_all(pending: PendingSlots, lane: int, grads: LaneGradientTargets):
        for slot in range(8):
            flush_slot(pending.rows[slot], slot, pending.density[slot], pending.sh[slot], lane, grads)

    return no_pending, gated_gradient, add_to_slots, flush_all


@functools.cache
def lane_backward_for(bdim: int, lanes: int, variant: mf.KernelVariant = mf.GENERAL):
    """The backward kernel for blocks of `lanes` lanes per ray and `variant` (see
    `march_forward.forward_for`).

    A ray's consecutive samples share most corners (a step is half a cell, and a cell shares 4 corners
    with the next), so adding every sample's gradient to all 8 corners at once would repeat the same
    global atomics. Instead gradients wait in 8 slots, one per vertex parity ((x, y, z) mod 2): the 8
    corners of any cell fill the 8 slots, and a vertex keeps its slot from cell to cell. A slot is
    added to the grid only when a new corner takes it, or at the end of the ray: a third of the row
    additions (docs/design.md, "Speed"). Lane `c` holds coefficients c, c + lanes, ... (`lanes` is a
    compile-time constant: with 32 lanes a lane holds one coefficient, and its 8 slots fit in
    registers); slot `s`'s density is added by lane `s % lanes` (`slot_rules_for`).
    """
    _, own_basis, own_preact = lane_sh_for(bdim, lanes, variant.shuffle_sum)
    ray_of_thread = ray_of_thread_for(lanes, variant.rays_per_block)
    no_pending, gated_gradient, add_to_slots, flush_all = slot_rules_for(
        bdim, lanes, variant.rows_from_corners
    )
    levels_fixed, distortion_fixed, near_fixed, _, _ = variant.switches()

    @KERNEL(cuda_max_registers=variant.max_registers)
    def render_backward_lanes(
        grid: mf.GridView,
        sh: wp.array2d(dtype=wp.float32),
        params: mf.MarchParams,
        rays: mf.Rays,
        first_ray: int,
        out_rgb: wp.array(dtype=wp.vec3),
        grad_rgb: wp.array(dtype=wp.vec3),
        dist: mf.DistortionLink,
        grads: LaneGradientTargets,
    ):
        i, thread = wp.tid()
        tid, lane = ray_of_thread(i, thread, first_ray, rays.origins.shape[0])
        if wp.static(variant.rays_per_block > 1):  # noqa: SIM102 (a compile-time test, then a run-time one)
            if tid < 0:
                return
        g = grad_rgb[tid]
        r = mf.setup_ray(
            rays.origins[tid], rays.dirs[tid], grid, params, mf.fixed_levels(levels_fixed, grid.levels)
        )
        near_on = mf.feature_on(near_fixed, params.near_grad > 0.0)
        inv_step = 1.0 / params.step
        own = own_basis(mf.sh_basis(rays.dirs[tid]), lane)
        remaining = wp.dot(g, out_rgb[tid])
        dist_total = wp.vec3(0.0, 0.0, 0.0)
        dist_weight = wp.float32(0.0)
        dist_remaining = wp.float32(0.0)  # sum_k w_k dL/dw_k = 2 loss
        if mf.feature_on(distortion_fixed, dist.enabled != 0):
            dist_total = dist.stats[tid]
            dist_weight = dist.weight[tid] * mf.distortion_scale(r)  # per unit of the index loss
            dist_remaining = dist.weight[tid] * 2.0 * dist_total[2]
        dist_before = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_after = wp.float32(1.0)
        pending = no_pending()
        visit = mf.next_visit(r, mf.first_slot(r, grid, params), 0, inv_step, grid, params)
        while visit.s < r.num_samples:
            corners = mf.fetch_corners(grid, visit.cell)
            sigma = corners.sigma
            if sigma > params.sigma_thresh:
                delta = mf.sample_delta(r, visit.cell)
                step = mf.composite(t_after, log_t, sigma * delta, params.stop_thresh)
                weight = step[0]
                pre = own_preact(sh, corners, own, lane)
                g_dot_c = wp.dot(g, mf.relu_color(pre))
                log_t = step[1]
                t_after = step[2]
                remaining = remaining - weight * g_dot_c
                d_sigma = delta * (t_after * g_dot_c - remaining)
                if dist_weight != 0.0:
                    g_w = dist_weight * mf.distortion_dw(dist_before, dist_total, weight, float(visit.s))
                    dist_remaining = dist_remaining - weight * g_w
                    d_sigma += delta * (t_after * g_w - dist_remaining)
                    dist_before = mf.distortion_add(dist_before, weight, float(visit.s))
                gated = gated_gradient(pre, g, weight, own, lane)
                near = mf.near_factor(visit.slot, visit.s, params, near_on)
                if wp.static(variant.rows_from_corners):
                    pending = add_to_slots(pending, corners, visit.cell, near, d_sigma, gated, lane, grads)
                else:
                    pending = add_to_slots(pending, grid.links, visit.cell, near, d_sigma, gated, lane, grads)
                if step[3] != 0.0:
                    break
            visit = mf.next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)
        flush_all(pending, lane, grads)

    return render_backward_lanes
