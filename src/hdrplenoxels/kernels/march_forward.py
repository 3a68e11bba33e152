"""The forward kernel: each ray's radiance, in both layouts from one source.

- One thread per ray (`lanes` 0): the CPU's, and the only layout that writes a `SampleRecord` (each ray's
  contributing samples, which the backward of `kernels/march_threads.py` replays).
- A block of `lanes` lanes per ray (CUDA's default; `kernels/march_lanes.py` holds its SH functions): every
  lane walks the same samples and owns a share of the SH coefficients, so loads are contiguous across the
  block and the colour is a block-wide sum.

The layout is a compile-time constant (`wp.static`), so each layout's kernel holds only its own code, and
both march through `kernels/march_funcs.py`: the same samples with the same arithmetic.

Oracle: `hdrplenoxels.kernels.march_reference.render_reference`; parity: tests/test_render_parity.py.
"""

import functools

import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL
from hdrplenoxels.kernels import march_funcs as mf
from hdrplenoxels.kernels.march_lanes import lane_sh_for, ray_of_thread_for
from hdrplenoxels.kernels.march_threads import Record, sh_rules_for


@functools.cache
def forward_for(bdim: int, lanes: int, variant: mf.KernelVariant = mf.GENERAL):
    """The forward kernel for `bdim` SH coefficients per channel, blocks of `lanes` lanes per ray (0: one
    thread per ray) and `variant`, whose switches are compile-time constants
    (`march_funcs.KernelVariant`). With lanes, lane `c` owns SH coefficients c, c + lanes, ... of the 8
    corners; on the CPU a block has one lane (unless `wp.config.enable_cpu_blocks`) that owns them all."""
    ShArray = wp.array2d(dtype=wp.float32) if lanes else wp.array(dtype=mf.sh_row(bdim))
    levels_fixed, distortion_fixed, _, background_fixed, record_fixed = variant.switches()
    own_basis = own_preact = ray_of_thread = interpolate_sh = sample_preact = None  # the other layout's
    if lanes:
        _, own_basis, own_preact = lane_sh_for(bdim, lanes, variant.shuffle_sum)
        ray_of_thread = ray_of_thread_for(lanes, variant.rays_per_block)
        record_fixed = 0  # the lanes write no record: the compiler drops its code
    else:
        interpolate_sh, sample_preact, _ = sh_rules_for(bdim)

    @KERNEL(cuda_max_registers=variant.max_registers)
    def render_forward(
        grid: mf.GridView,
        sh: ShArray,
        params: mf.MarchParams,
        rays: mf.Rays,
        first_ray: int,
        out_rgb: wp.array(dtype=wp.vec3),
        bg: mf.BackgroundLink,
        record: Record,
        dist: mf.DistortionLink,
    ):
        if wp.static(lanes > 0):
            i, thread = wp.tid()
            tid, lane = ray_of_thread(i, thread, first_ray, rays.origins.shape[0])
            if wp.static(variant.rays_per_block > 1):  # noqa: SIM102 (a compile-time test, then a run-time one)
                if tid < 0:
                    return
        else:
            tid = wp.tid() + first_ray
            lane = 0
        r = mf.setup_ray(
            rays.origins[tid], rays.dirs[tid], grid, params, mf.fixed_levels(levels_fixed, grid.levels)
        )
        distortion_on = mf.feature_on(distortion_fixed, dist.enabled != 0)
        record_on = mf.feature_on(record_fixed, record.capacity > 0)
        inv_step = 1.0 / params.step
        basis = mf.sh_basis(rays.dirs[tid])
        if wp.static(lanes > 0):
            own = own_basis(basis, lane)
        recorded = wp.int32(0)
        rgb = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_end = wp.float32(1.0)
        dist_acc = wp.vec3(0.0, 0.0, 0.0)
        visit = mf.next_visit(r, mf.first_slot(r, grid, params), 0, inv_step, grid, params)
        while visit.s < r.num_samples:
            corners = mf.fetch_corners(grid, visit.cell)
            sigma = corners.sigma
            if sigma > params.sigma_thresh:
                tau = sigma * mf.sample_delta(r, visit.cell)
                step = mf.composite(t_end, log_t, tau, params.stop_thresh)
                weight = step[0]
                if wp.static(lanes > 0):
                    color = mf.relu_color(own_preact(sh, corners, own, lane))
                else:
                    color = mf.relu_color(sample_preact(interpolate_sh(sh, corners), basis))
                rgb = rgb + weight * color
                if distortion_on:
                    dist_acc = mf.distortion_add(dist_acc, weight, float(visit.s))
                if record_on and recorded < record.capacity:
                    record.index[tid, recorded] = visit.s
                    record.values[tid, recorded] = wp.vec4(sigma, color[0], color[1], color[2])
                    recorded += 1
                log_t = step[1]
                t_end = step[2]
                if step[3] != 0.0:
                    t_end = 0.0
                    break
            visit = mf.next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)
        if lane != 0:  # the block's sums left every lane the same radiance: one writes it
            return
        out_rgb[tid] = mf.finish_ray(
            tid, rgb, t_end, params, bg, mf.feature_on(background_fixed, bg.per_ray != 0)
        )
        if distortion_on:  # what lies behind the grid is the ray's last sample
            acc = mf.distortion_add(dist_acc, t_end, float(r.num_samples))
            dist.stats[tid] = wp.vec3(acc[0], acc[1], acc[2] * mf.distortion_scale(r))
        if record_on:
            record.count[tid] = recorded

    return render_forward
