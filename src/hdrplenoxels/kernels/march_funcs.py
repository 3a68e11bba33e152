"""The ray march every render kernel shares, as Warp functions, and the structs kernels take.

A grid is a cascade of `levels` nested boxes (one for a plain box); each ray is cut into `2 levels - 1`
slots, each rendered by one level at that level's step (`kernels/march_reference.py`, `RaySegments`), and a
sample's index along the ray names its slot, level and position.

The forward (`kernels/march_forward.py`, in both layouts) and the backward kernels, a thread per ray
(`kernels/march_threads.py`) or a block of lanes (`kernels/march_lanes.py`), must visit exactly the same
samples with exactly the same arithmetic, or their outputs and gradients would differ from each other and
from `kernels/march_reference.py` (`docs/method.md`, "Rendering"). So ray setup, sample placement, corner
fetching and empty-space skipping (`kernels/occupancy_kernel.py`) live here once.
Loop-carried scalars are declared as wp.float32(...) so Warp treats them as dynamic variables.
"""

import functools
from dataclasses import dataclass

import warp as wp

from hdrplenoxels.geometry.sh import SH_C0, SH_C1, SH_C2
from hdrplenoxels.kernels.options import FAR_FACE_SLACK, TINY_DIR

vec9 = wp.types.vector(length=9, dtype=wp.float32)
vec8i = wp.types.vector(length=8, dtype=wp.int32)
vec8 = wp.types.vector(length=8, dtype=wp.float32)

C0 = wp.constant(SH_C0)
C1 = wp.constant(SH_C1)
C20 = wp.constant(SH_C2[0])
C21 = wp.constant(SH_C2[1])
C22 = wp.constant(SH_C2[2])
C23 = wp.constant(SH_C2[3])
C24 = wp.constant(SH_C2[4])


@dataclass(frozen=True)
class KernelVariant:
    """What a march kernel is compiled for. `None`: read from the kernel's arguments at run time (the
    general kernel, the CPU's: one compile serves every run); a value: fixed when it is compiled, so the
    compiler drops what the run does not use and keeps no registers for it (JOURNAL.md,
    "Kernel variants")."""

    levels: int | None = None
    """The grid's cascade levels (1: one box)."""
    distortion: bool | None = None
    """Whether the distortion loss is on (`DistortionLink.enabled`)."""
    near_grad: bool | None = None
    """Whether gradients near the camera are scaled down (`MarchParams.near_grad` > 0)."""
    per_ray_background: bool | None = None
    """Whether the radiance behind the grid comes per ray (`BackgroundLink.per_ray`)."""
    record: bool | None = None
    """Whether a `SampleRecord` is kept (the one-thread-per-ray kernels only)."""
    max_registers: int | None = None
    """CUDA only: registers a thread may use (None: the compiler's choice); fewer let more warps run
    at once, at the cost of spills to local memory."""
    shuffle_sum: bool = False
    """CUDA only, the lane kernels: a sample's colour summed over a ray's lanes by warp shuffles, rather
    than by a tile sum through shared memory between two barriers."""
    rays_per_block: int = 1
    """The lane kernels: rays that share a block, each on its own `lanes` of it (4 rays of 8 lanes, 2 of
    16: a warp's 32 threads all at work, where a block of 8 or 16 lanes leaves the rest of its warp
    idle). More than one needs `shuffle_sum` (a tile sum would add every ray's lanes together)."""
    rows_from_corners: bool = False
    """The lane backward: each sample's corner rows for its pending slots picked by selects from the
    `Corners` the sample already fetched, rather than read from the links again (8 reads a sample, from
    L1), at the cost of keeping the corners' rows live."""

    def switches(self) -> tuple[int, int, int, int, int]:
        """The variant as the compile-time integers the kernels capture: levels (0: at run time), then
        distortion, near_grad, per_ray_background and record (-1: at run time, 0: off, 1: on)."""

        def switch(value: bool | None) -> int:
            return -1 if value is None else int(value)

        return (
            self.levels or 0,
            switch(self.distortion),
            switch(self.near_grad),
            switch(self.per_ray_background),
            switch(self.record),
        )


GENERAL = KernelVariant()


@wp.func
def feature_on(fixed: int, runtime: bool) -> bool:
    """Whether a feature is on: `fixed` (a compile-time constant from `KernelVariant.switches`) 0 or 1,
    which lets the compiler drop the other branch, or -1 to take `runtime`."""
    if fixed >= 0:
        return fixed != 0
    return runtime


@wp.func
def fixed_levels(fixed: int, runtime: int) -> int:
    """The cascade's levels: `fixed` when the kernel was compiled for it (> 0), else `runtime`."""
    if fixed > 0:
        return fixed
    return runtime


@functools.cache
def sh_row(bdim: int):
    """One voxel's SH row (3 channels of `bdim` coefficients) as a vector type, loaded at once."""
    return wp.types.vector(length=3 * bdim, dtype=wp.float32)


@wp.struct
class GridView:
    """What the march reads of a grid besides its SH (whose array type differs between the thread and
    the lane kernels): links, density, the world-to-grid transform and the occupancy marks."""

    links: wp.array4d(dtype=wp.int32)  # (levels, Rx, Ry, Rz)
    density: wp.array(dtype=wp.float32)
    scale: wp.vec3  # world -> level-0 grid units: p * scale + offset
    offset: wp.vec3
    reso: wp.vec3i
    levels: int
    cells: wp.array4d(dtype=wp.uint8)  # occupied cells per level (`kernels/occupancy_kernel.py`)
    blocks: wp.array4d(dtype=wp.uint8)  # occupied blocks of 2^shift cells a side
    shift: int


@wp.struct
class MarchParams:
    """The `RenderOptions` a kernel uses (`background` only by the forward)."""

    step: float
    sigma_thresh: float
    stop_thresh: float
    t_far: float
    background_brightness: float
    near_grad: float  # `RenderOptions.near_grad` times the finest box's half-side, level-0 voxels (0: off)


@wp.struct
class BackgroundLink:
    """What a forward kernel composites behind the march: `per_ray` 0, the constant
    `MarchParams.background_brightness`; 1, `radiance[ray]`, and then it writes the transmittance left in
    front of it to `transmittance[ray]` (docs/method.md, "Background")."""

    per_ray: int
    radiance: wp.array(dtype=wp.vec3)
    transmittance: wp.array(dtype=wp.float32)


@wp.struct
class DistortionLink:
    """The distortion loss along each ray (`kernels/march_reference.py`, `distortion_loss`): `enabled` 0,
    none; 1, the forward writes `stats[ray]` = (sum of weights w, sum of w i, the loss times n) and the
    backward adds `weight[ray]` times the loss's gradient (i: a sample's index along the ray, n: its
    samples; the background is one more sample, at i = n)."""

    enabled: int
    stats: wp.array(dtype=wp.vec3)
    weight: wp.array(dtype=wp.float32)


@wp.func
def distortion_add(acc: wp.vec3, w: float, s: float) -> wp.vec3:
    """(sum w, sum w s, n loss) after one more sample of weight `w` at index `s` (the loss of each pair of
    samples counted as it completes: 2 w_i w_j |s_i - s_j| for j < i, plus w_i^2 / 3)."""
    return wp.vec3(acc[0] + w, acc[1] + w * s, acc[2] + 2.0 * w * (s * acc[0] - acc[1]) + w * w / 3.0)


@wp.func
def distortion_dw(before: wp.vec3, total: wp.vec3, w: float, s: float) -> float:
    """d (n loss) / d w of the sample of weight `w` at index `s`, given the sums over the samples before it
    (`before`) and over the whole ray (`total`): 2 sum_j w_j |s - s_j| + 2 w / 3."""
    w_after = total[0] - before[0] - w
    ws_after = total[1] - before[1] - w * s
    return 2.0 * (s * before[0] - before[1] + ws_after - s * w_after) + 2.0 * w / 3.0


@wp.struct
class Rays:
    """A batch's rays in world space (directions of unit length)."""

    origins: wp.array(dtype=wp.vec3)
    dirs: wp.array(dtype=wp.vec3)


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
    """A ray in level-0 grid units. Its slots are not stored: the march carries the one it is in as a
    `Slot` of scalars (`enter_slot`), so no per-ray array is indexed at run time (on CUDA such arrays
    live in local memory, JOURNAL.md)."""

    origin: wp.vec3  # level-0 grid units
    direction: wp.vec3  # unit, grid space
    inv_direction: wp.vec3  # 1 / direction (zero components replaced by TINY_DIR), for block exits
    delta: float  # segment length of one level-0 step in world/NDC units
    levels: int
    num_samples: int


@wp.struct
class Slot:
    """The slot holding the current sample: its index j along the ray, its level, its samples
    [first, end), the first one's ray parameter t0 and their spacing (level-0 grid units)."""

    index: int
    level: int
    first: int
    end: int
    t0: float
    step: float


@wp.func
def box_in_out(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3, t_far: float) -> wp.vec2:
    """Where the ray crosses the box [lo, hi], clamped to [0, t_far]; x > y for a miss."""
    a = wp.float32(-1.0e30)
    b = wp.float32(1.0e30)
    for k in range(3):
        dk = safe_dir(d[k])
        t1 = (lo[k] - o[k]) / dk
        t2 = (hi[k] - o[k]) / dk
        a = wp.max(a, wp.min(t1, t2))
        b = wp.min(b, wp.max(t1, t2))
    return wp.vec2(wp.max(a, 0.0), wp.min(b, t_far))


@wp.func
def box_of_level(grid: GridView, level: int, t_far: float, o: wp.vec3, d: wp.vec3) -> wp.vec2:
    f = float(1 << level)
    mid = wp.vec3(float(grid.reso[0]) - 1.0, float(grid.reso[1]) - 1.0, float(grid.reso[2]) - 1.0) * 0.5
    half = wp.vec3(float(grid.reso[0]), float(grid.reso[1]), float(grid.reso[2])) * 0.5
    return box_in_out(o, d, mid - f * half, mid + f * half, t_far * f)


@wp.func
def enter_slot(r: Ray, j: int, first: int, grid: GridView, params: MarchParams) -> Slot:
    """Slot `j` of the ray, whose first sample has index `first`, exactly as `march_reference.ray_segments`
    places it: entry slots (and level 0) from the box's near face, exit slots back from its far face."""
    levels = r.levels
    level = wp.abs(j - (levels - 1))
    step = params.step * float(1 << level)
    box = box_of_level(grid, level, params.t_far, r.origin, r.direction)
    hit = box[0] <= box[1]
    inner = wp.vec2(1.0, 0.0)  # no finer box: a miss
    if level > 0:
        inner = box_of_level(grid, level - 1, params.t_far, r.origin, r.direction)
    inner_hit = inner[0] <= inner[1]
    n = wp.int32(0)
    start = box[0]
    if j < levels - 1 or level == 0:  # an entry slot (or level 0)
        if inner_hit:
            n = wp.max(int(wp.ceil((inner[0] - box[0]) / step - FAR_FACE_SLACK)), 0)
        elif hit:
            n = int(wp.floor((box[1] - box[0]) / step + FAR_FACE_SLACK)) + 1
    elif inner_hit and hit:  # an exit slot, counted back from the box's far face
        n = wp.max(int(wp.ceil((box[1] - inner[1]) / step - FAR_FACE_SLACK)), 0)
        start = box[1] - float(wp.max(n - 1, 0)) * step
    out = Slot()
    out.index = j
    out.level = level
    out.first = first
    out.end = first + n
    out.t0 = start
    out.step = step
    return out


@wp.func
def setup_ray(o_world: wp.vec3, d_world: wp.vec3, grid: GridView, params: MarchParams, levels: int) -> Ray:
    """The ray in level-0 grid units and its number of samples, exactly as `march_reference.ray_segments`
    (`levels`: the grid's, from `fixed_levels`)."""
    o = wp.cw_mul(o_world, grid.scale) + grid.offset
    d = wp.cw_mul(d_world, grid.scale)
    nrm = wp.length(d)
    d = wp.vec3(d[0] / nrm, d[1] / nrm, d[2] / nrm)
    r = Ray()
    r.origin = o
    r.direction = d
    r.inv_direction = wp.vec3(1.0 / safe_dir(d[0]), 1.0 / safe_dir(d[1]), 1.0 / safe_dir(d[2]))
    r.delta = params.step / nrm
    r.levels = levels
    total = wp.int32(0)
    for j in range(2 * levels - 1):
        total = enter_slot(r, j, total, grid, params).end
    r.num_samples = total
    return r


@wp.func
def first_slot(r: Ray, grid: GridView, params: MarchParams) -> Slot:
    return enter_slot(r, 0, 0, grid, params)


@wp.func
def slot_holding(r: Ray, slot: Slot, s: int, grid: GridView, params: MarchParams) -> Slot:
    """The slot holding sample `s` (< num_samples), from `slot` (at or before it) on: samples are
    visited in order, so the march only ever moves forward through the slots."""
    out = slot
    while out.index < 2 * r.levels - 2 and s >= out.end:
        out = enter_slot(r, out.index + 1, out.end, grid, params)
    return out


@wp.func
def distortion_scale(r: Ray) -> float:
    """1 / n: the index loss of `distortion_add` to the loss along the normalised coordinate i / n."""
    return 1.0 / float(wp.max(r.num_samples, 1))


@wp.struct
class Cell:
    base: wp.vec3i
    frac: wp.vec3
    level: int


@wp.func
def locate(p: wp.vec3, reso: wp.vec3i, level: int) -> Cell:
    c = Cell()
    for a in range(3):
        pa = wp.min(wp.max(p[a], 0.0), float(reso[a] - 1))
        b = wp.min(int(wp.floor(pa)), reso[a] - 2)
        c.base[a] = b
        c.frac[a] = pa - float(b)
    c.level = level
    return c


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
def corner_rows(links: wp.array4d(dtype=wp.int32), c: Cell) -> Corners:
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
        row = links[c.level, c.base[0] + i, c.base[1] + j, c.base[2] + k]
        present = wp.where(row >= 0, 1, 0)
        out.rows[n] = wp.max(row, 0)
        out.weights[n] = wx * wy * wz * float(present)
        out.present[n] = present
    return out


@wp.func
def fetch_corners(grid: GridView, c: Cell) -> Corners:
    out = corner_rows(grid.links, c)
    sigma = wp.float32(0.0)
    for n in range(8):
        sigma += out.weights[n] * grid.density[out.rows[n]]
    out.sigma = sigma
    return out


@wp.func
def near_factor(slot: Slot, s: int, params: MarchParams, on: bool) -> float:
    """The gradient scale of sample `s` of `slot` (`RenderOptions.near_grad`): min(1, (t / near)^2);
    1 unless `on` (`feature_on` of `params.near_grad` > 0)."""
    if not on:
        return 1.0
    q = (slot.t0 + float(s - slot.first) * slot.step) / params.near_grad
    return wp.min(q * q, 1.0)


@wp.func
def in_level(p: wp.vec3, reso: wp.vec3i, level: int) -> wp.vec3:
    """Level-0 grid coordinates `p` in level `level`'s: 2^-level times as far from the centre."""
    if level == 0:
        return p
    mid = wp.vec3(float(reso[0]) - 1.0, float(reso[1]) - 1.0, float(reso[2]) - 1.0) * 0.5
    return (p - mid) * (1.0 / float(1 << level)) + mid


@wp.func
def block_exit(origin: wp.vec3, inv_direction: wp.vec3, base: wp.vec3i, shift: int) -> float:
    """Ray parameter (of the level whose grid `origin` is in) where the ray leaves the block (2^shift
    cells a side) holding cell `base`."""
    t = wp.float32(1.0e30)
    for a in range(3):
        b = base[a] >> shift
        face = float(b << shift)
        if inv_direction[a] > 0.0:
            face = float((b + 1) << shift)
        t = wp.min(t, (face - origin[a]) * inv_direction[a])
    return t


@wp.func
def block_occupied(blocks: wp.array4d(dtype=wp.uint8), cell: Cell, shift: int) -> bool:
    b = cell.base  # shifts, not divisions: this runs for every sample
    return blocks[cell.level, b[0] >> shift, b[1] >> shift, b[2] >> shift] != wp.uint8(0)


@wp.func
def skip_block(r: Ray, cell: Cell, s: int, slot: Slot, inv_step: float, reso: wp.vec3i, shift: int) -> int:
    """The first sample at or past the exit of the empty block holding sample `s` (of `slot`), or the
    slot's end, where another level takes over.

    Every sample before it lies in the closed block, whose corner voxels all have density <= 0, so
    it contributes nothing (a sample on the exit face reads only face voxels, corners of this block).
    """
    f = float(1 << cell.level)
    t_exit = f * block_exit(in_level(r.origin, reso, cell.level), r.inv_direction, cell.base, shift)
    k = int(wp.ceil((t_exit - slot.t0) * (inv_step / f)))
    return wp.min(wp.max(s + 1, slot.first + k), slot.end)


@wp.func
def sample_cell(r: Ray, s: int, slot: Slot, reso: wp.vec3i) -> Cell:
    """The cell of sample `s` of `slot`."""
    t = slot.t0 + float(s - slot.first) * slot.step
    return locate(in_level(r.origin + t * r.direction, reso, slot.level), reso, slot.level)


@wp.func
def sample_delta(r: Ray, cell: Cell) -> float:
    """The sample's optical length: a level-0 step's world length at every level, density being per
    voxel of the sample's level (docs/method.md, "Cascade")."""
    return r.delta


@wp.struct
class Visit:
    """A sample the march must evaluate (index `s`, in `cell`, of `slot`); `s == num_samples`: none
    is left."""

    s: int
    slot: Slot
    cell: Cell


@wp.func
def next_visit(r: Ray, slot: Slot, s: int, inv_step: float, grid: GridView, params: MarchParams) -> Visit:
    """The first sample from index `s` on (`slot` at or before it) whose cell is occupied: empty blocks
    are jumped over and empty cells passed after a one-byte check. Forward and backward march through
    the same samples."""
    v = Visit()
    v.s = s
    v.slot = slot
    while v.s < r.num_samples:
        v.slot = slot_holding(r, v.slot, v.s, grid, params)
        v.cell = sample_cell(r, v.s, v.slot, grid.reso)
        c = v.cell
        if not block_occupied(grid.blocks, c, grid.shift):
            v.s = skip_block(r, c, v.s, v.slot, inv_step, grid.reso, grid.shift)
        elif grid.cells[c.level, c.base[0], c.base[1], c.base[2]] == wp.uint8(0):
            v.s = v.s + 1
        else:
            return v
    return v


@wp.func
def composite(t_before: float, log_t: float, tau: float, stop_thresh: float) -> wp.vec4:
    """One sample of optical depth `tau` behind transmittance `t_before` = exp(`log_t`): (its weight
    T (1 - e^-tau), log T after it, T after it, 1 where T after is below `stop_thresh`: the march ends
    there). Every kernel composites through this, forward and backward, grid and MSI (`march_reference.py`'s
    `composite_weights` is its oracle)."""
    weight = t_before * (1.0 - wp.exp(-tau))
    log_after = log_t - tau
    t_after = wp.exp(log_after)
    return wp.vec4(weight, log_after, t_after, wp.where(t_after < stop_thresh, 1.0, 0.0))


@wp.func
def finish_ray(
    tid: int, rgb: wp.vec3, t_end: float, params: MarchParams, bg: BackgroundLink, per_ray: bool
) -> wp.vec3:
    """The ray's radiance: the march's plus the background seen with transmittance `t_end` (`per_ray`:
    `feature_on` of `bg.per_ray`)."""
    if per_ray:
        bg.transmittance[tid] = t_end
        return rgb + t_end * bg.radiance[tid]
    return rgb + wp.vec3(t_end * params.background_brightness)


@wp.func
def relu_color(pre: wp.vec3) -> wp.vec3:
    """The sample's colour from its SH . basis per channel: ReLU(pre + 0.5)."""
    return wp.vec3(wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0))
