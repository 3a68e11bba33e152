"""Warp ray-march kernels (one thread per ray) with a hand-written backward, for CPU and CUDA.

The math is exactly that of `render/reference.py` (method-spec §2); `tests/test_render_parity.py`
holds the two together. Warp's automatic adjoint is wrong for this loop (dynamic trip count, early
break), so it is switched off and the backward kernel re-marches each ray svox2-style:
with G = <dL, L> and G <- G - w_k <dL, c_k> after each sample,
  dLoss/dsigma_k = delta * (T_{k+1} <dL, c_k> - G),  dLoss/dsh_k = w_k dL_c [pre_c > 0] Y_j,
each spread over the 8 trilinear corners (empty corners receive nothing).

Given a `SampleRecord` (training on the CPU), the forward also writes each ray's contributing samples
(index, density, colour) and the backward replays them, re-marching only past a full record: the
same arithmetic on the same values, so the same gradients, without reading density and SH again.

Both kernels fetch a sample's 8 corners once for density and SH, jump over empty blocks of cells and
pass empty cells after a one-byte check (`render/occupancy.py`: exact, no output changes). On CPU
they run on every core by splitting the rays between threads, each backward thread with its own
gradient buffers (`GridGradients`). The backward marks the rows it adds to (`GridGradients.touched`).
"""

import functools

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, split
from hdrplenoxels.core.warp_runtime import KERNEL, launch_parts, mark_touched, warp_device
from hdrplenoxels.geometry.sh import SH_C0, SH_C1, SH_C2
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.render.occupancy import BlockOccupancy, occupancy_for
from hdrplenoxels.render.options import RenderOptions
from hdrplenoxels.render.reference import FAR_FACE_SLACK, TINY_DIR
from hdrplenoxels.render.sample_record import SampleRecord

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
    inv_direction: wp.vec3  # 1 / direction (zero components replaced by TINY_DIR), for block exits
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
    r.inv_direction = wp.vec3(1.0 / safe_dir(d[0]), 1.0 / safe_dir(d[1]), 1.0 / safe_dir(d[2]))
    r.delta = step / nrm
    r.t_min = t_min
    r.num_samples = 0
    if t_min <= t_max:
        r.num_samples = int(wp.floor((t_max - t_min) / step + FAR_FACE_SLACK)) + 1
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


vec8i = wp.types.vector(length=8, dtype=wp.int32)
vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.struct
class Corners:
    """A sample's 8 trilinear corners, fetched once and shared by density and SH.

    An empty corner (link -1) gets row 0 and weight 0, so interpolation needs no branch; only
    gradient scatters check `present`.
    """

    rows: vec8i
    weights: vec8
    present: vec8i
    sigma: float


@wp.func
def corner_rows(links: wp.array3d(dtype=wp.int32), c: Cell) -> Corners:
    """The cell's corner rows and trilinear weights (`sigma` left 0)."""
    out = Corners()
    for n in range(8):
        i = n >> 2
        j = (n >> 1) & 1
        k = n & 1
        wx = c.frac[0]
        if i == 0:
            wx = 1.0 - c.frac[0]
        wy = c.frac[1]
        if j == 0:
            wy = 1.0 - c.frac[1]
        wz = c.frac[2]
        if k == 0:
            wz = 1.0 - c.frac[2]
        row = links[c.base[0] + i, c.base[1] + j, c.base[2] + k]
        present = wp.where(row >= 0, 1, 0)
        out.rows[n] = wp.max(row, 0)
        out.weights[n] = wx * wy * wz * float(present)
        out.present[n] = present
    return out


@wp.func
def fetch_corners(links: wp.array3d(dtype=wp.int32), density: wp.array(dtype=wp.float32), c: Cell) -> Corners:
    out = corner_rows(links, c)
    sigma = wp.float32(0.0)
    for n in range(8):
        sigma += out.weights[n] * density[out.rows[n]]
    out.sigma = sigma
    return out


@wp.func
def block_exit(r: Ray, base: wp.vec3i, shift: int) -> float:
    """Ray parameter where the ray leaves the block (2^shift cells a side) holding cell `base`."""
    t = wp.float32(1.0e30)
    for a in range(3):
        b = base[a] >> shift
        face = float(b << shift)
        if r.inv_direction[a] > 0.0:
            face = float((b + 1) << shift)
        t = wp.min(t, (face - r.origin[a]) * r.inv_direction[a])
    return t


@wp.func
def block_occupied(occupancy: wp.array3d(dtype=wp.uint8), cell: Cell, shift: int) -> bool:
    b = cell.base  # shifts, not divisions: this runs for every sample
    return occupancy[b[0] >> shift, b[1] >> shift, b[2] >> shift] != wp.uint8(0)


@wp.func
def skip_block(r: Ray, cell: Cell, s: int, inv_step: float, shift: int) -> int:
    """The first sample at or past the exit of the empty block holding sample `s`.

    Every sample before it lies in the closed block, whose corner voxels all have density <= 0, so
    it contributes nothing (a sample on the exit face reads only face voxels, corners of this block).
    """
    t_exit = block_exit(r, cell.base, shift)
    return wp.max(s + 1, int(wp.ceil((t_exit - r.t_min) * inv_step)))


@wp.func
def sample_cell(r: Ray, s: int, step: float, reso: wp.vec3i) -> Cell:
    return locate(r.origin + (r.t_min + float(s) * step) * r.direction, reso)


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
    current sample, and <dL, colour still to come behind it> (background included)."""

    log_t: float
    t_after: float
    remaining: float


@wp.struct
class Visit:
    """A sample the march must evaluate (index `s`, in `cell`); `s == num_samples`: none is left."""

    s: int
    cell: Cell


@wp.func
def next_visit(
    r: Ray,
    s: int,
    step: float,
    inv_step: float,
    reso: wp.vec3i,
    cells: wp.array3d(dtype=wp.uint8),
    occupancy: wp.array3d(dtype=wp.uint8),
    shift: int,
) -> Visit:
    """The first sample from index `s` on whose cell is occupied: empty blocks are jumped over and
    empty cells passed after a one-byte check. Forward and backward march through the same samples."""
    v = Visit()
    v.s = s
    while v.s < r.num_samples:
        v.cell = sample_cell(r, v.s, step, reso)
        if not block_occupied(occupancy, v.cell, shift):
            v.s = skip_block(r, v.cell, v.s, inv_step, shift)
        elif cells[v.cell.base[0], v.cell.base[1], v.cell.base[2]] == wp.uint8(0):
            v.s = v.s + 1
        else:
            return v
    return v


@functools.cache
def kernels_for(bdim: int):
    """Forward and backward kernels specialised for `bdim` SH coefficients per channel.

    `bdim` is captured as a compile-time constant, so the per-coefficient loops are unrolled.
    """

    vec_sh = _vec_sh(bdim)  # one voxel's SH row, loaded at once

    @wp.func
    def interpolate_sh(sh: wp.array(dtype=vec_sh), c: Corners) -> vec_sh:
        out = vec_sh()
        for n in range(8):
            out += c.weights[n] * sh[c.rows[n]]
        return out

    @wp.func
    def sample_preact(coeffs: vec_sh, basis: vec9) -> wp.vec3:
        """SH . basis per channel at the sample (before the +0.5 and the ReLU)."""
        pre = wp.vec3(0.0, 0.0, 0.0)
        for ch in range(3):
            acc = wp.float32(0.0)
            for b in range(bdim):
                acc += coeffs[ch * bdim + b] * basis[b]
            pre[ch] = acc
        return pre

    @wp.func
    def sh_gradient(color: wp.vec3, scale: wp.vec3, basis: vec9) -> vec_sh:
        """d(<scale, colour>)/d(SH coefficients): ReLU-gated outer product of channel and basis
        (colour = ReLU(pre + 0.5) is > 0 exactly where the ReLU passes its gradient)."""
        out = vec_sh()
        for ch in range(3):
            gated = wp.where(color[ch] > 0.0, scale[ch], 0.0)
            for b in range(bdim):
                out[ch * bdim + b] = gated * basis[b]
        return out

    @wp.func
    def relu_color(pre: wp.vec3) -> wp.vec3:
        return wp.vec3(wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0))

    @wp.func
    def backprop_sample(
        state: Composite,
        corners: Corners,
        sigma: float,
        color: wp.vec3,
        g: wp.vec3,
        basis: vec9,
        delta: float,
        grad_density: wp.array(dtype=wp.float32),
        grad_sh: wp.array(dtype=vec_sh),
        touched: wp.array(dtype=wp.uint8),
    ) -> Composite:
        """Add one contributing sample's gradient to its 8 corners; returns the state behind it."""
        tau = sigma * delta
        weight = state.t_after * (1.0 - wp.exp(-tau))
        g_dot_c = wp.dot(g, color)
        out = Composite()
        out.log_t = state.log_t - tau
        out.t_after = wp.exp(out.log_t)
        out.remaining = state.remaining - weight * g_dot_c
        d_sigma = delta * (out.t_after * g_dot_c - out.remaining)
        d_sh = sh_gradient(color, weight * g, basis)
        for n in range(8):
            if corners.present[n] != 0:
                row = corners.rows[n]
                cw = corners.weights[n]
                wp.atomic_add(grad_density, row, cw * d_sigma)
                wp.atomic_add(grad_sh, row, cw * d_sh)
                mark_touched(touched, row)
        return out

    @KERNEL
    def render_forward_kernel(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array(dtype=vec_sh),
        cells: wp.array3d(dtype=wp.uint8),
        occupancy: wp.array3d(dtype=wp.uint8),
        block_shift: int,
        first_ray: int,
        scale: wp.vec3,
        offset: wp.vec3,
        reso: wp.vec3i,
        step: float,
        sigma_thresh: float,
        stop_thresh: float,
        t_far: float,
        background: float,
        out_rgb: wp.array(dtype=wp.vec3),
        record: Record,
    ):
        tid = wp.tid() + first_ray
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        inv_step = 1.0 / step
        basis = sh_basis(dirs[tid])
        rgb = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_end = wp.float32(1.0)
        recorded = wp.int32(0)
        visit = next_visit(r, 0, step, inv_step, reso, cells, occupancy, block_shift)
        while visit.s < r.num_samples:
            corners = fetch_corners(links, density, visit.cell)
            sigma = corners.sigma
            if sigma > sigma_thresh:
                tau = sigma * r.delta
                weight = t_end * (1.0 - wp.exp(-tau))  # t_end = exp(log_t): transmittance so far
                color = relu_color(sample_preact(interpolate_sh(sh, corners), basis))
                rgb = rgb + weight * color
                if recorded < record.capacity:
                    record.index[tid, recorded] = visit.s
                    record.values[tid, recorded] = wp.vec4(sigma, color[0], color[1], color[2])
                    recorded += 1
                log_t = log_t - tau
                t_end = wp.exp(log_t)
                if t_end < stop_thresh:
                    t_end = 0.0
                    break
            visit = next_visit(r, visit.s + 1, step, inv_step, reso, cells, occupancy, block_shift)
        out_rgb[tid] = rgb + wp.vec3(t_end * background)
        if record.capacity > 0:
            record.count[tid] = recorded

    @KERNEL
    def render_backward_kernel(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array(dtype=vec_sh),
        cells: wp.array3d(dtype=wp.uint8),
        occupancy: wp.array3d(dtype=wp.uint8),
        block_shift: int,
        first_ray: int,
        scale: wp.vec3,
        offset: wp.vec3,
        reso: wp.vec3i,
        step: float,
        sigma_thresh: float,
        stop_thresh: float,
        t_far: float,
        out_rgb: wp.array(dtype=wp.vec3),
        grad_rgb: wp.array(dtype=wp.vec3),
        record: Record,
        grad_density: wp.array(dtype=wp.float32),
        grad_sh: wp.array(dtype=vec_sh),
        touched: wp.array(dtype=wp.uint8),
    ):
        tid = wp.tid() + first_ray
        g = grad_rgb[tid]
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        inv_step = 1.0 / step
        basis = sh_basis(dirs[tid])
        state = Composite()
        state.log_t = 0.0
        state.t_after = 1.0
        state.remaining = wp.dot(g, out_rgb[tid])
        # First the samples the forward recorded: their density and colour need no grid reads.
        recorded = wp.int32(0)
        if record.capacity > 0:
            recorded = record.count[tid]
        resume = wp.int32(0)  # the first sample the march below must look at
        for k in range(recorded):
            s = record.index[tid, k]
            v = record.values[tid, k]
            corners = corner_rows(links, sample_cell(r, s, step, reso))
            state = backprop_sample(
                state,
                corners,
                v[0],
                wp.vec3(v[1], v[2], v[3]),
                g,
                basis,
                r.delta,
                grad_density,
                grad_sh,
                touched,
            )
            if state.t_after < stop_thresh:
                return
            resume = s + 1
        if recorded < record.capacity:
            return  # the record holds every contributing sample of this ray
        # Then march the rest (all of it without a record), recomputing density and colour.
        visit = next_visit(r, resume, step, inv_step, reso, cells, occupancy, block_shift)
        while visit.s < r.num_samples:
            corners = fetch_corners(links, density, visit.cell)
            sigma = corners.sigma
            if sigma > sigma_thresh:
                color = relu_color(sample_preact(interpolate_sh(sh, corners), basis))
                state = backprop_sample(
                    state, corners, sigma, color, g, basis, r.delta, grad_density, grad_sh, touched
                )
                if state.t_after < stop_thresh:
                    break
            visit = next_visit(r, visit.s + 1, step, inv_step, reso, cells, occupancy, block_shift)

    return render_forward_kernel, render_backward_kernel


@functools.cache
def _lane_preact_for(bdim: int):
    ncoef = 3 * bdim

    @wp.func
    def lane_preact(
        sh: wp.array2d(dtype=wp.float32), c: Corners, basis: vec9, lane: int, lanes: int
    ) -> wp.vec3:
        """SH . basis per channel at the sample (before the +0.5 and the ReLU), summed over lanes."""
        part = wp.vec3(0.0, 0.0, 0.0)
        for k in range(lane, ncoef, lanes):
            coef = wp.float32(0.0)
            for n in range(8):
                coef += c.weights[n] * sh[c.rows[n], k]
            ch = k // bdim
            part[ch] = part[ch] + coef * basis[k - ch * bdim]
        return wp.tile_extract(wp.tile_sum(wp.tile(part, preserve_type=True)), 0)

    return lane_preact


@functools.cache
def lane_forward_for(bdim: int):
    """The forward kernel where a block of lanes marches one ray together (svox2's layout).

    Every lane walks the same samples (the march is recomputed, identically, in each); lane `c` owns
    SH coefficients c, c + lanes, ... of the 8 corners, so its loads are contiguous across the block,
    and the colour is a block-wide sum. On CUDA a ray gets a warp of 32 lanes: a 5000-ray batch then
    fills the GPU, where one thread per ray would leave it mostly idle. On the CPU a block has one
    lane (unless `wp.config.enable_cpu_blocks`) that owns every coefficient.
    """
    lane_preact = _lane_preact_for(bdim)

    @KERNEL
    def render_forward_lanes(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array2d(dtype=wp.float32),
        cells: wp.array3d(dtype=wp.uint8),
        occupancy: wp.array3d(dtype=wp.uint8),
        block_shift: int,
        first_ray: int,
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
        i, lane = wp.tid()
        lanes = wp.block_dim()
        tid = i + first_ray
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        inv_step = 1.0 / step
        basis = sh_basis(dirs[tid])
        rgb = wp.vec3(0.0, 0.0, 0.0)
        log_t = wp.float32(0.0)
        t_end = wp.float32(1.0)
        visit = next_visit(r, 0, step, inv_step, reso, cells, occupancy, block_shift)
        while visit.s < r.num_samples:
            corners = fetch_corners(links, density, visit.cell)
            sigma = corners.sigma
            if sigma > sigma_thresh:
                tau = sigma * r.delta
                weight = t_end * (1.0 - wp.exp(-tau))
                pre = lane_preact(sh, corners, basis, lane, lanes)
                rgb = rgb + weight * wp.vec3(
                    wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0)
                )
                log_t = log_t - tau
                t_end = wp.exp(log_t)
                if t_end < stop_thresh:
                    t_end = 0.0
                    break
            visit = next_visit(r, visit.s + 1, step, inv_step, reso, cells, occupancy, block_shift)
        if lane == 0:
            out_rgb[tid] = rgb + wp.vec3(t_end * background)

    return render_forward_lanes


@functools.cache
def lane_backward_for(bdim: int, lanes: int):
    """The backward kernel for blocks of `lanes` lanes per ray (see `lane_forward_for`).

    A ray's consecutive samples share most corners (a step is half a cell, and a cell shares 4 corners
    with the next), so adding every sample's gradient to all 8 corners at once would repeat the same
    global atomics. Instead gradients wait in 8 slots, one per vertex parity ((x, y, z) mod 2): the 8
    corners of any cell fill the 8 slots, and a vertex keeps its slot from cell to cell. A slot is
    added to the grid only when a new corner takes it, or at the end of the ray: on the 128^3
    benchmark, 34 % of the row additions (`benchmarks/RESULTS.md`). Lane `c` holds coefficients
    c, c + lanes, ... (`lanes` is a compile-time constant: with 32 lanes a lane holds one coefficient,
    and its 8 slots fit in registers); slot `s`'s density is added by lane `s % lanes`.
    """
    ncoef = 3 * bdim
    per_lane = (ncoef + lanes - 1) // lanes
    lane_vec = wp.types.vector(length=per_lane, dtype=wp.float32)
    slot_mat = wp.types.matrix(shape=(8, per_lane), dtype=wp.float32)  # a slot's pending SH gradients
    lane_preact = _lane_preact_for(bdim)

    @wp.func
    def flush_slot(
        row: int,
        slot: int,
        d_density: float,
        d_sh: lane_vec,
        lane: int,
        grad_density: wp.array(dtype=wp.float32),
        grad_sh: wp.array2d(dtype=wp.float32),
        touched: wp.array(dtype=wp.uint8),
    ):
        """Add one slot's pending gradient into vertex `row` (nothing for an empty slot, row -1)."""
        if row >= 0:
            if slot % lanes == lane:
                wp.atomic_add(grad_density, row, d_density)
                mark_touched(touched, row)
            for j in range(per_lane):
                k = lane + j * lanes
                if k < ncoef:
                    wp.atomic_add(grad_sh, row, k, d_sh[j])

    @KERNEL
    def render_backward_lanes(
        origins: wp.array(dtype=wp.vec3),
        dirs: wp.array(dtype=wp.vec3),
        links: wp.array3d(dtype=wp.int32),
        density: wp.array(dtype=wp.float32),
        sh: wp.array2d(dtype=wp.float32),
        cells: wp.array3d(dtype=wp.uint8),
        occupancy: wp.array3d(dtype=wp.uint8),
        block_shift: int,
        first_ray: int,
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
        touched: wp.array(dtype=wp.uint8),
    ):
        i, lane = wp.tid()
        tid = i + first_ray
        g = grad_rgb[tid]
        r = setup_ray(origins[tid], dirs[tid], scale, offset, reso, step, t_far)
        inv_step = 1.0 / step
        basis = sh_basis(dirs[tid])
        remaining = wp.dot(g, out_rgb[tid])
        log_t = wp.float32(0.0)
        t_after = wp.float32(1.0)
        slot_row = vec8i(-1, -1, -1, -1, -1, -1, -1, -1)  # the vertex (grid row) each slot holds
        slot_density = vec8()
        slot_sh = slot_mat()
        visit = next_visit(r, 0, step, inv_step, reso, cells, occupancy, block_shift)
        while visit.s < r.num_samples:
            corners = fetch_corners(links, density, visit.cell)
            sigma = corners.sigma
            if sigma > sigma_thresh:
                tau = sigma * r.delta
                weight = t_after * (1.0 - wp.exp(-tau))
                pre = lane_preact(sh, corners, basis, lane, lanes)
                color = wp.vec3(
                    wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0)
                )
                g_dot_c = wp.dot(g, color)
                log_t = log_t - tau
                t_after = wp.exp(log_t)
                remaining = remaining - weight * g_dot_c
                d_sigma = r.delta * (t_after * g_dot_c - remaining)
                gated = lane_vec()  # d(loss)/d(interpolated coefficient) of this lane's coefficients
                for j in range(per_lane):
                    k = lane + j * lanes
                    if k < ncoef:
                        ch = k // bdim
                        gated[j] = wp.where(pre[ch] + 0.5 > 0.0, weight * g[ch], 0.0) * basis[k - ch * bdim]
                base = visit.cell.base
                frac = visit.cell.frac
                # Slot bits = vertex parity. The corner's row and weight are computed again rather than
                # read from `corners` at index slot ^ parity: a run-time index would put `corners` and
                # the slots in local memory on CUDA; these reads of `links` hit L1.
                for slot in range(8):
                    ci = ((slot >> 2) & 1) ^ (base[0] & 1)
                    cj = ((slot >> 1) & 1) ^ (base[1] & 1)
                    ck = (slot & 1) ^ (base[2] & 1)
                    row = links[base[0] + ci, base[1] + cj, base[2] + ck]
                    if row != slot_row[slot]:
                        flush_slot(
                            slot_row[slot], slot, slot_density[slot], slot_sh[slot], lane,
                            grad_density, grad_sh, touched,
                        )  # fmt: skip
                        slot_row[slot] = row
                        slot_density[slot] = 0.0
                        slot_sh[slot] = lane_vec()
                    wx = wp.where(ci == 1, frac[0], 1.0 - frac[0])
                    wy = wp.where(cj == 1, frac[1], 1.0 - frac[1])
                    wz = wp.where(ck == 1, frac[2], 1.0 - frac[2])
                    w = wx * wy * wz
                    slot_density[slot] = slot_density[slot] + w * d_sigma
                    slot_sh[slot] = slot_sh[slot] + w * gated
                if t_after < stop_thresh:
                    break
            visit = next_visit(r, visit.s + 1, step, inv_step, reso, cells, occupancy, block_shift)
        for slot in range(8):
            flush_slot(
                slot_row[slot], slot, slot_density[slot], slot_sh[slot], lane, grad_density, grad_sh, touched
            )

    return render_backward_lanes


@functools.cache
def _vec_sh(bdim: int):
    return wp.types.vector(length=3 * bdim, dtype=wp.float32)


CUDA_LANES = 32  # a warp per ray


def lanes_for(device: str, lanes: int | None) -> int:
    """Lanes per ray: `lanes` if given (0: the one-thread-per-ray kernels), else a warp on CUDA and
    one thread per ray on the CPU, whose threads each take a range of rays instead."""
    if lanes is not None:
        return lanes
    return 0 if device == "cpu" else CUDA_LANES


def records_samples(device: str) -> bool:
    """Whether the default kernels on `device` keep a `SampleRecord` (the one-thread-per-ray kernels
    do; the lane kernels, CUDA's default, recompute instead)."""
    return lanes_for(device, None) == 0


def _block_lanes(device: str, lanes: int) -> int:
    """The lanes a block really gets: Warp runs CPU blocks one lane wide unless
    `wp.config.enable_cpu_blocks` (more lanes would each redo every coefficient)."""
    return 1 if device == "cpu" and not wp.config.enable_cpu_blocks else lanes


def _launch_lanes(kernel, n: int, lanes: int, march: list, rest: list, device: str) -> None:
    lanes = _block_lanes(device, lanes)
    launch_parts(
        device,
        n,
        [(0, n)],
        lambda start, stop, _part: wp.launch(
            kernel, dim=(stop - start, lanes), inputs=[*march, start, *rest], block_dim=lanes, device=device
        ),
    )


def _march_inputs(grid: SparseGrid, occ: BlockOccupancy, origins, dirs, flat_sh: bool = False) -> list:
    """The leading kernel arguments shared by the forward and backward kernels, up to `first_ray`
    (SH as rows of vectors, or with `flat_sh` as a 2-D array for the lane kernels)."""
    sh = grid.sh.detach()
    return [
        wp.from_torch(origins, dtype=wp.vec3, requires_grad=False),
        wp.from_torch(dirs, dtype=wp.vec3, requires_grad=False),
        wp.from_torch(grid.links, requires_grad=False),
        wp.from_torch(grid.density.detach(), requires_grad=False),
        wp.from_torch(sh, requires_grad=False)
        if flat_sh
        else wp.from_torch(sh, dtype=_vec_sh(grid.basis_dim), requires_grad=False),
        wp.from_torch(occ.cells, requires_grad=False),
        wp.from_torch(occ.blocks, requires_grad=False),
        occ.shift,
    ]


def _ray_constants(grid: SparseGrid, opt: RenderOptions) -> list:
    scale, offset = grid.world_to_grid_affine("cpu")
    return [
        wp.vec3(*scale.tolist()),
        wp.vec3(*offset.tolist()),
        wp.vec3i(*grid.reso),
        opt.step_size,
        opt.sigma_thresh,
        opt.stop_thresh,
        opt.t_max,
    ]


@functools.cache
def _no_record(device: str) -> Record:
    """The kernel argument for "no sample record"."""
    r = Record()
    r.capacity = 0
    r.index = wp.zeros((1, 1), dtype=wp.int32, device=device)
    r.values = wp.zeros((1, 1), dtype=wp.vec4, device=device)
    r.count = wp.zeros(1, dtype=wp.int32, device=device)
    return r


def _record_input(record: SampleRecord | None, n: int, device: str) -> Record:
    if record is None:
        return _no_record(device)
    if record.rays != n:
        raise ValueError(f"the sample record holds {record.rays} rays, the batch {n}")
    r = Record()
    r.capacity = record.capacity
    r.index = wp.from_torch(record.index, requires_grad=False)
    r.values = wp.from_torch(record.values, dtype=wp.vec4, requires_grad=False)
    r.count = wp.from_torch(record.count, requires_grad=False)
    return r


def _launch_split(kernel, n: int, parts: list[tuple[int, int]], march: list, rest_for, device: str) -> None:
    """Launch `kernel` (arguments: `march`, the part's first ray, `rest_for(part)`) over the rays [0, n)."""

    def launch(start: int, stop: int, part: int) -> None:
        wp.launch(kernel, dim=stop - start, inputs=[*march, start, *rest_for(part)], device=device)

    launch_parts(device, n, parts, launch)


def render_forward(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions,
    lanes: int | None = None,
    record: SampleRecord | None = None,
) -> torch.Tensor:
    """Linear radiance (N, 3) of rays with unit directions (no autograd); `lanes`: see `lanes_for`;
    `record`: filled for `accumulate_backward` (one thread per ray only, see `records_samples`)."""
    device = warp_device(grid.density)
    origins = origins.detach().contiguous().float()
    dirs = dirs.detach().contiguous().float()
    n = origins.shape[0]
    out = torch.empty_like(origins)
    if n == 0:
        return out
    occ = occupancy_for(grid)
    lanes = lanes_for(device, lanes)
    rest = _ray_constants(grid, opt) + [
        opt.background,
        wp.from_torch(out, dtype=wp.vec3, requires_grad=False),
    ]
    if lanes:
        if record is not None:
            raise ValueError("the lane kernels keep no sample record")
        forward_kernel = lane_forward_for(grid.basis_dim)
        march = _march_inputs(grid, occ, origins, dirs, flat_sh=True)
        _launch_lanes(forward_kernel, n, lanes, march, rest, device)
        return out
    forward_kernel, _ = kernels_for(grid.basis_dim)
    march = _march_inputs(grid, occ, origins, dirs)
    # More parts than threads: a thread done early takes the next part (image rows vary in cost).
    workers = cpu_workers()
    parts = split(n, workers if n < 16384 else 4 * workers)
    rest.append(_record_input(record, n, device))
    _launch_split(forward_kernel, n, parts, march, lambda part: rest, device)
    return out


def accumulate_backward(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    rgb: torch.Tensor,
    grad_rgb: torch.Tensor,
    opt: RenderOptions,
    grads: GridGradients,
    lanes: int | None = None,
    record: SampleRecord | None = None,
) -> None:
    """Add d(loss)/d(density, SH) for rays whose forward output was `rgb` and upstream gradient
    `grad_rgb` into `grads` (the re-march of the module docstring); `lanes`: see `lanes_for`;
    `record`: what the forward over the same rays and the same grid recorded."""
    device = warp_device(grid.density)
    origins = origins.detach().contiguous().float()
    dirs = dirs.detach().contiguous().float()
    n = origins.shape[0]
    if n == 0:
        return
    occ = occupancy_for(grid)
    lanes = lanes_for(device, lanes)
    rest = _ray_constants(grid, opt) + [
        wp.from_torch(rgb.detach().contiguous().float(), dtype=wp.vec3, requires_grad=False),
        wp.from_torch(grad_rgb.detach().contiguous().float(), dtype=wp.vec3, requires_grad=False),
    ]
    if lanes:
        if record is not None:
            raise ValueError("the lane kernels keep no sample record")
        if grads.density.shape[0] != 1:
            raise ValueError("lane kernels add into one gradient buffer (their atomics must be real)")
        backward_kernel = lane_backward_for(grid.basis_dim, _block_lanes(device, lanes))
        march = _march_inputs(grid, occ, origins, dirs, flat_sh=True)
        buffer = [
            wp.from_torch(grads.density[0], requires_grad=False),
            wp.from_torch(grads.sh[0], requires_grad=False),
            wp.from_torch(grads.touched, requires_grad=False),
        ]
        _launch_lanes(backward_kernel, n, lanes, march, rest + buffer, device)
        return
    _, backward_kernel = kernels_for(grid.basis_dim)
    march = _march_inputs(grid, occ, origins, dirs)
    touched = wp.from_torch(grads.touched, requires_grad=False)  # shared: every writer stores 1
    buffers = [  # one pair per part: CPU threads never add into the same buffer
        [
            wp.from_torch(d, requires_grad=False),
            wp.from_torch(s, dtype=_vec_sh(grid.basis_dim), requires_grad=False),
            touched,
        ]
        for d, s in zip(grads.density, grads.sh)
    ]
    rest.append(_record_input(record, n, device))
    parts = split(n, len(buffers))
    _launch_split(backward_kernel, n, parts, march, lambda part: rest + buffers[part], device)


class _WarpRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, sh, grid: SparseGrid, origins, dirs, opt: RenderOptions):
        out = render_forward(grid, origins, dirs, opt)
        ctx.save_for_backward(origins, dirs, out)
        ctx.grid = grid
        ctx.opt = opt
        return out

    @staticmethod
    def backward(ctx, grad_out):
        origins, dirs, out = ctx.saved_tensors
        grads = GridGradients(ctx.grid, gradient_parts(ctx.grid))
        accumulate_backward(ctx.grid, origins, dirs, out, grad_out, ctx.opt, grads)
        grad_density, grad_sh = grads.total()
        return grad_density, grad_sh, None, None, None, None


def render_warp(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions = RenderOptions()
) -> torch.Tensor:
    """Linear radiance (N, 3); differentiable w.r.t. `grid.density` and `grid.sh`."""
    if origins.shape[0] == 0:
        return origins.new_zeros((0, 3))
    return _WarpRender.apply(grid.density, grid.sh, grid, origins, dirs, opt)
