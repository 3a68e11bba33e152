"""The ray march every render kernel shares, as Warp functions, and the structs kernels take.

The thread kernels (`render/thread_kernels.py`) and the lane kernels (`render/lane_kernels.py`) must
visit exactly the same samples with exactly the same arithmetic, or their outputs and gradients would
differ from each other and from `render/reference.py` (`docs/method.md`, "Rendering"). So ray setup,
sample placement, corner fetching and empty-space skipping (`render/occupancy.py`) live here once.
Loop-carried scalars are declared as wp.float32(...) so Warp treats them as dynamic variables.
"""

import functools

import warp as wp

from hdrplenoxels.geometry.sh import SH_C0, SH_C1, SH_C2
from hdrplenoxels.render.reference import FAR_FACE_SLACK, TINY_DIR

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


@functools.cache
def sh_row(bdim: int):
    """One voxel's SH row (3 channels of `bdim` coefficients) as a vector type, loaded at once."""
    return wp.types.vector(length=3 * bdim, dtype=wp.float32)


@wp.struct
class GridView:
    """What the march reads of a grid besides its SH (whose array type differs between the thread and
    the lane kernels): links, density, the world-to-grid transform and the occupancy marks."""

    links: wp.array3d(dtype=wp.int32)
    density: wp.array(dtype=wp.float32)
    scale: wp.vec3  # world -> grid units: p * scale + offset
    offset: wp.vec3
    reso: wp.vec3i
    cells: wp.array3d(dtype=wp.uint8)  # occupied cells (`render/occupancy.py`)
    blocks: wp.array3d(dtype=wp.uint8)  # occupied blocks of 2^shift cells a side
    shift: int


@wp.struct
class MarchParams:
    """The `RenderOptions` a kernel uses (`background` only by the forward)."""

    step: float
    sigma_thresh: float
    stop_thresh: float
    t_far: float
    background: float


@wp.struct
class BackgroundLink:
    """What a forward kernel composites behind the march: `per_ray` 0, the constant
    `MarchParams.background`; 1, `radiance[ray]`, and then it writes the transmittance left in front of
    it to `transmittance[ray]` (docs/method.md, "Background")."""

    per_ray: int
    radiance: wp.array(dtype=wp.vec3)
    transmittance: wp.array(dtype=wp.float32)


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
    origin: wp.vec3  # grid units
    direction: wp.vec3  # unit, grid space
    inv_direction: wp.vec3  # 1 / direction (zero components replaced by TINY_DIR), for block exits
    delta: float  # segment length of one step in world/NDC units
    t_min: float
    num_samples: int


@wp.func
def setup_ray(o_world: wp.vec3, d_world: wp.vec3, grid: GridView, params: MarchParams) -> Ray:
    o = wp.cw_mul(o_world, grid.scale) + grid.offset
    d = wp.cw_mul(d_world, grid.scale)
    nrm = wp.length(d)
    d = wp.vec3(d[0] / nrm, d[1] / nrm, d[2] / nrm)
    t_min = wp.float32(0.0)
    t_max = params.t_far
    lo = wp.float32(-1.0e30)
    hi = wp.float32(1.0e30)
    for a in range(3):
        da = safe_dir(d[a])
        t1 = (-0.5 - o[a]) / da
        t2 = (float(grid.reso[a]) - 0.5 - o[a]) / da
        lo = wp.max(lo, wp.min(t1, t2))
        hi = wp.min(hi, wp.max(t1, t2))
    t_min = wp.max(lo, t_min)
    t_max = wp.min(hi, t_max)
    r = Ray()
    r.origin = o
    r.direction = d
    r.inv_direction = wp.vec3(1.0 / safe_dir(d[0]), 1.0 / safe_dir(d[1]), 1.0 / safe_dir(d[2]))
    r.delta = params.step / nrm
    r.t_min = t_min
    r.num_samples = 0
    if t_min <= t_max:
        r.num_samples = int(wp.floor((t_max - t_min) / params.step + FAR_FACE_SLACK)) + 1
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
def fetch_corners(grid: GridView, c: Cell) -> Corners:
    out = corner_rows(grid.links, c)
    sigma = wp.float32(0.0)
    for n in range(8):
        sigma += out.weights[n] * grid.density[out.rows[n]]
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
def block_occupied(blocks: wp.array3d(dtype=wp.uint8), cell: Cell, shift: int) -> bool:
    b = cell.base  # shifts, not divisions: this runs for every sample
    return blocks[b[0] >> shift, b[1] >> shift, b[2] >> shift] != wp.uint8(0)


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
class Visit:
    """A sample the march must evaluate (index `s`, in `cell`); `s == num_samples`: none is left."""

    s: int
    cell: Cell


@wp.func
def next_visit(r: Ray, s: int, inv_step: float, grid: GridView, params: MarchParams) -> Visit:
    """The first sample from index `s` on whose cell is occupied: empty blocks are jumped over and
    empty cells passed after a one-byte check. Forward and backward march through the same samples."""
    v = Visit()
    v.s = s
    while v.s < r.num_samples:
        v.cell = sample_cell(r, v.s, params.step, grid.reso)
        if not block_occupied(grid.blocks, v.cell, grid.shift):
            v.s = skip_block(r, v.cell, v.s, inv_step, grid.shift)
        elif grid.cells[v.cell.base[0], v.cell.base[1], v.cell.base[2]] == wp.uint8(0):
            v.s = v.s + 1
        else:
            return v
    return v


@wp.func
def finish_ray(tid: int, rgb: wp.vec3, t_end: float, params: MarchParams, bg: BackgroundLink) -> wp.vec3:
    """The ray's radiance: the march's plus the background seen with transmittance `t_end`."""
    if bg.per_ray != 0:
        bg.transmittance[tid] = t_end
        return rgb + t_end * bg.radiance[tid]
    return rgb + wp.vec3(t_end * params.background)


@wp.func
def relu_color(pre: wp.vec3) -> wp.vec3:
    """The sample's colour from its SH . basis per channel: ReLU(pre + 0.5)."""
    return wp.vec3(wp.max(pre[0] + 0.5, 0.0), wp.max(pre[1] + 0.5, 0.0), wp.max(pre[2] + 0.5, 0.0))
