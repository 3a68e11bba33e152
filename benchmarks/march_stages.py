"""Where the lane forward's time goes, with no hardware counters: the kernel timed beside copies of it
that stop after one of its stages, on the same rays, in the same run (differences between them place
the time; the device tool's notes suggest this where `ncu` cannot read the counters).

Stages, each a kernel of the lane forward's shape (`kernels/march_forward.py`, a warp per ray):
  march      the samples' placement and the empty-space skipping alone (`next_visit`), nothing fetched
  density    and each visited sample's corners and density, composited (colour a constant)
  sh         and each lane's SH coefficients of the 8 corners, without the block-wide colour sum
  full       the package's lane forward (the sum and the colour: what training runs)
  eager      the full kernel with the SH read beside the density instead of after its threshold test,
             so the two loads overlap (a candidate change; equal outputs, tests/test_march_stages.py)
and the lane backward's (`backward_stage_kernel`):
  bwd-march  the re-march and every sample's gradients, none scattered
  bwd-plain  and the 8 pending slots filled and flushed, with plain stores into a per-ray sum
  backward   the package's lane backward (the flushes are atomics into the grid's gradients)
On the CPU (one lane a block) it runs too, for the tests. Prints milliseconds per launch (median of
--repeats, CUDA events on a GPU) and each over `full`.

Usage: python benchmarks/march_stages.py [--problem spike] [--rays 5000] [--repeats 30] [--json F]
"""

import argparse
import functools
import json
import sys
import time
from pathlib import Path
from statistics import median

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, to_warp, warp_device
from hdrplenoxels.kernels import march_kernel as render_launch
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.march_forward import forward_for
from hdrplenoxels.kernels.march_funcs import (
    BackgroundLink,
    Cell,
    Corners,
    DistortionLink,
    GridView,
    MarchParams,
    Rays,
    composite,
    fetch_corners,
    finish_ray,
    first_slot,
    near_factor,
    next_visit,
    relu_color,
    sample_delta,
    setup_ray,
    sh_basis,
    vec8,
    vec8i,
)
from hdrplenoxels.kernels.march_lanes import (
    in_channel,
    lane_sh_for,
    per_lane_count,
    slot_rules_for,
)
from hdrplenoxels.kernels.march_threads import Record
from hdrplenoxels.render import RenderOptions

STAGES = ("march", "density", "sh", "full", "eager")
BACKWARD_STAGES = ("bwd-march", "bwd-plain", "backward")
_DEPTH = {"march": 0, "density": 1, "sh": 2, "eager": 3}


@functools.cache
def stage_kernel(stage: str, bdim: int, lanes: int):
    """The lane forward for `stage` (see the module's docstring); `full` is the package's kernel."""
    if stage == "full":
        return forward_for(bdim, lanes)
    depth = _DEPTH[stage]
    lane_vec, own_basis, own_preact = lane_sh_for(bdim, lanes)
    ncoef, per_lane = 3 * bdim, per_lane_count(bdim, lanes)

    @wp.func
    def own_part(sh: wp.array2d(dtype=wp.float32), c: Corners, own: lane_vec, lane: int) -> wp.vec3:
        """`own_preact` without its block-wide sum: this lane's share of SH . basis per channel."""
        part = wp.vec3(0.0, 0.0, 0.0)
        for j in range(per_lane):
            k = lane + j * lanes
            if k < ncoef:
                coef = wp.float32(0.0)
                for n in range(8):
                    coef += c.weights[n] * sh[c.rows[n], k]
                part = part + in_channel(k // bdim, coef * own[j])
        return part

    @KERNEL
    def stage_forward(
        grid: GridView,
        sh: wp.array2d(dtype=wp.float32),
        params: MarchParams,
        rays: Rays,
        first_ray: int,
        out_rgb: wp.array(dtype=wp.vec3),
        bg: BackgroundLink,
        record: Record,
        dist: DistortionLink,
    ):
        i, lane = wp.tid()
        tid = i + first_ray
        r = setup_ray(rays.origins[tid], rays.dirs[tid], grid, params, grid.levels)
        inv_step = 1.0 / params.step
        own = own_basis(sh_basis(rays.dirs[tid]), lane)
        rgb = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_end = wp.float32(1.0)
        visit = next_visit(r, first_slot(r, grid, params), 0, inv_step, grid, params)
        while visit.s < r.num_samples:
            if depth == 0:
                rgb = rgb + wp.vec3(1.0, 0.0, 0.0)
            else:
                corners = fetch_corners(grid, visit.cell)
                sigma = corners.sigma
                pre = wp.vec3(0.0, 0.0, 0.0)
                if depth == 3:  # the SH read issued before the density's test (one sum for every visit)
                    pre = own_preact(sh, corners, own, lane)
                if sigma > params.sigma_thresh:
                    step = composite(t_end, log_t, sigma * sample_delta(r, visit.cell), params.stop_thresh)
                    if depth == 1:
                        rgb = rgb + wp.vec3(step[0])
                    elif depth == 2:
                        rgb = rgb + step[0] * relu_color(own_part(sh, corners, own, lane))
                    else:
                        rgb = rgb + step[0] * relu_color(pre)
                    log_t = step[1]
                    t_end = step[2]
                    if step[3] != 0.0:
                        t_end = 0.0
                        break
            visit = next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)
        if lane == 0:
            out_rgb[tid] = finish_ray(tid, rgb, t_end, params, bg, False)

    return stage_forward


@functools.cache
def backward_stage_kernel(stage: str, bdim: int, lanes: int):
    """The lane backward (`kernels/march_lanes.py`) cut short: `bwd-march` re-marches and computes
    every sample's gradients but scatters none (their sum kept per lane, so none is optimised away);
    `bwd-plain` also fills the 8 pending slots and flushes them as the package does, into a per-ray,
    per-lane sum with plain stores instead of atomics into the grid's gradients. The package's kernel
    minus `bwd-plain` is the atomics; `bwd-plain` minus `bwd-march` the slots."""
    lane_vec, own_basis, own_preact = lane_sh_for(bdim, lanes)
    gated_gradient = slot_rules_for(bdim, lanes)[1]
    ncoef, per_lane = 3 * bdim, per_lane_count(bdim, lanes)
    slot_mat = wp.types.matrix(shape=(8, per_lane), dtype=wp.float32)
    scatter = stage == "bwd-plain"

    @wp.struct
    class Pending:
        rows: vec8i
        density: vec8
        sh: slot_mat

    @wp.func
    def none_pending() -> Pending:
        out = Pending()
        out.rows = vec8i(-1, -1, -1, -1, -1, -1, -1, -1)
        return out

    @wp.func
    def flush_plain(
        row: int,
        slot: int,
        d_density: float,
        d_sh: lane_vec,
        lane: int,
        sink: wp.array2d(dtype=float),
        tid: int,
    ):
        if row >= 0:
            acc = wp.where(slot % lanes == lane, d_density, 0.0)
            for j in range(per_lane):
                if lane + j * lanes < ncoef:
                    acc += d_sh[j]
            sink[tid, lane] = sink[tid, lane] + acc

    @wp.func
    def add_plain(
        pending: Pending,
        links: wp.array4d(dtype=wp.int32),
        cell: Cell,
        scale: float,
        d_sigma: float,
        gated: lane_vec,
        lane: int,
        sink: wp.array2d(dtype=float),
        tid: int,
    ) -> Pending:
        """`slot_rules_for`'s `add_to_slots`, flushing with `flush_plain`."""
        out = pending
        base = cell.base
        frac = cell.frac
        for slot in range(8):
            ci = ((slot >> 2) & 1) ^ (base[0] & 1)
            cj = ((slot >> 1) & 1) ^ (base[1] & 1)
            ck = (slot & 1) ^ (base[2] & 1)
            row = links[cell.level, base[0] + ci, base[1] + cj, base[2] + ck]
            if row != out.rows[slot]:
                flush_plain(out.rows[slot], slot, out.density[slot], out.sh[slot], lane, sink, tid)
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

    @KERNEL
    def stage_backward(
        grid: GridView,
        sh: wp.array2d(dtype=wp.float32),
        params: MarchParams,
        rays: Rays,
        first_ray: int,
        out_rgb: wp.array(dtype=wp.vec3),
        grad_rgb: wp.array(dtype=wp.vec3),
        sink: wp.array2d(dtype=float),
    ):
        i, lane = wp.tid()
        tid = i + first_ray
        g = grad_rgb[tid]
        r = setup_ray(rays.origins[tid], rays.dirs[tid], grid, params, grid.levels)
        near_on = params.near_grad > 0.0
        inv_step = 1.0 / params.step
        own = own_basis(sh_basis(rays.dirs[tid]), lane)
        remaining = wp.dot(g, out_rgb[tid])
        log_t = wp.float32(0.0)
        t_after = wp.float32(1.0)
        pending = none_pending()
        kept = wp.float32(0.0)
        visit = next_visit(r, first_slot(r, grid, params), 0, inv_step, grid, params)
        while visit.s < r.num_samples:
            corners = fetch_corners(grid, visit.cell)
            sigma = corners.sigma
            if sigma > params.sigma_thresh:
                delta = sample_delta(r, visit.cell)
                step = composite(t_after, log_t, sigma * delta, params.stop_thresh)
                weight = step[0]
                pre = own_preact(sh, corners, own, lane)
                g_dot_c = wp.dot(g, relu_color(pre))
                log_t = step[1]
                t_after = step[2]
                remaining = remaining - weight * g_dot_c
                d_sigma = delta * (t_after * g_dot_c - remaining)
                gated = gated_gradient(pre, g, weight, own, lane)
                near = near_factor(visit.slot, visit.s, params, near_on)
                if scatter:
                    pending = add_plain(
                        pending, grid.links, visit.cell, near, d_sigma, gated, lane, sink, tid
                    )
                else:
                    kept += near * d_sigma
                    for j in range(per_lane):
                        kept += gated[j]
                if step[3] != 0.0:
                    break
            visit = next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)
        if scatter:
            for slot in range(8):
                flush_plain(
                    pending.rows[slot], slot, pending.density[slot], pending.sh[slot], lane, sink, tid
                )
        else:
            sink[tid, lane] = kept

    return stage_backward


def stage_calls(
    grid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions,
    lanes: int,
    stages=STAGES + BACKWARD_STAGES,
) -> dict:
    """A launch of each of `stages` over the rays (outputs kept on `.out`); the backward ones take the
    package's forward radiance and a constant upstream gradient."""
    device = warp_device(grid.density)
    n = origins.shape[0]
    origins, dirs, _ = render_launch.prepared_rays(origins, dirs)
    block = render_launch._block_lanes(device, lanes)
    head = [
        render_launch._grid_view(grid),
        render_launch._sh(grid, lanes),
        render_launch.march_params(opt, grid),
        render_launch.rays_input(origins, dirs),
    ]
    unused = render_launch._unused(device)
    rgb = render_launch.render_forward(grid, origins, dirs, opt, lanes=lanes)
    grad = torch.full_like(rgb, 1e-3)
    grads = GridGradients(grid, parts=1)
    calls = {}
    for stage in stages:
        if stage == "backward":

            def call() -> None:
                render_launch.accumulate_backward(grid, origins, dirs, rgb, grad, opt, grads, lanes=lanes)

            call.out = grads
        else:
            if stage in BACKWARD_STAGES:
                out = torch.zeros(n, block, device=grid.density.device)
                kernel = backward_stage_kernel(stage, grid.basis_dim, block)
                tail = [render_launch.vec3s(rgb), render_launch.vec3s(grad), to_warp(out, "a stage's sums")]
            else:
                out = torch.zeros(n, 3, device=grid.density.device)
                kernel = stage_kernel(stage, grid.basis_dim, block)
                radiance = to_warp(out, "a stage's radiance", dtype=wp.vec3)
                tail = [radiance, unused.background, unused.record, unused.distortion]

            def call(kernel=kernel, tail=tail) -> None:
                render_launch._launch_lanes(kernel, n, lanes, head, tail, device)

            call.out = out
        calls[stage] = call
    return calls


def timed(fn, repeats: int, cuda: bool) -> float:
    """Median milliseconds of `fn` over `repeats` calls after three untimed ones."""
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        if cuda:
            start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            stop.record()
            stop.synchronize()
            times.append(start.elapsed_time(stop))
        else:
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) * 1e3)
    return median(times)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default="spike", choices=("spike", "paper"))
    ap.add_argument("--rays", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--lanes", type=int, default=render_launch.CUDA_LANES)
    ap.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")
    ap.add_argument("--json", type=Path)
    return ap.parse_args(argv)


def main() -> None:
    args = parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run import checked_device, make_problem

    device = torch.device(checked_device(args.device))
    grid, o, d, background = make_problem(args.problem, args.rays, None)
    grid, o, d = grid.to(device), o.to(device), d.to(device)
    calls = stage_calls(grid, o, d, RenderOptions(background_brightness=background), args.lanes)
    ms = {name: timed(fn, args.repeats, device.type == "cuda") for name, fn in calls.items()}
    same = torch.equal(calls["eager"].out, calls["full"].out)
    print(f"{args.problem}, {args.rays} rays, {args.lanes} lanes, {device}: ms a launch (x full)")
    for name, t in ms.items():
        print(f"  {name:9} {t:9.3f}  {t / ms['full']:5.2f}")
    print(f"  eager's radiance equal to full's: {same}")
    if args.json:
        result = dict(vars(args), device=str(device), json=None, ms=ms, eager_equal=same)
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
