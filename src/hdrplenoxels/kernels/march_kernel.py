"""Kernel inputs and launches: the render API the training engine and `render/autograd.py` call.

Picks the kernel family for a device (`lanes_for`), builds the structs of `kernels/march_funcs.py` from a
`SparseGrid`, its `BlockOccupancy` and the `RenderOptions`, and launches: on CUDA once for the batch,
on the CPU once per part of the rays on every core, each backward part adding into its own gradient
buffers (`GridGradients`), which it marks as touched (`JOURNAL.md`).
"""

from __future__ import annotations

import functools
import weakref
from typing import NamedTuple

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, split
from hdrplenoxels.core.warp_runtime import (
    launch_kernel,
    launch_parts,
    launch_split,
    to_warp,
    warp_device,
    warp_struct,
)
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.grad_buffers import GridGradients, check_row_array
from hdrplenoxels.kernels.march_forward import forward_for
from hdrplenoxels.kernels.march_funcs import (
    BackgroundLink,
    DistortionLink,
    GridView,
    KernelVariant,
    MarchParams,
    Rays,
    sh_row,
)
from hdrplenoxels.kernels.march_lanes import LaneGradientTargets, lane_backward_for
from hdrplenoxels.kernels.march_read_rows import mark_read_rows_kernel
from hdrplenoxels.kernels.march_threads import (
    Record,
    gradient_targets_for,
    thread_backward_for,
)
from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
from hdrplenoxels.kernels.options import RenderOptions, near_distance
from hdrplenoxels.kernels.sample_record import SampleRecord

CUDA_LANES = 32  # a warp per ray
# The lanes' colour sum by warp shuffles (`KernelVariant.shuffle_sum`): off until a GPU's timing chooses
# (`make gpu-check`'s step section times it).
CUDA_SHUFFLE_SUM = False
# Rays sharing a lane kernel's block (`KernelVariant.rays_per_block`): one until a GPU's timing chooses.
CUDA_RAYS_PER_BLOCK = 1
# The lane backward's corner rows from the sample's `Corners` (`KernelVariant.rows_from_corners`): off
# until a GPU's timing chooses.
CUDA_ROWS_FROM_CORNERS = False
THREAD_RAYS_PER_SM = 512  # a CUDA forward of at least this many rays per multiprocessor: a thread per ray


def lanes_for(device: str, lanes: int | None, rays: int = 0) -> int:
    """Lanes per ray: `lanes` if given (0: the one-thread-per-ray kernels); else one thread per ray on the
    CPU, whose threads each take a range of rays, and a warp per ray on CUDA, unless `rays` (a forward's
    batch) fills the GPU with one thread per ray: each ray is then marched once rather than once per
    lane (benchmarks/RESULTS.md, the first GPU run)."""
    if lanes is not None:
        return lanes
    if device == "cpu":
        return 0
    fills = rays > 0 and rays >= THREAD_RAYS_PER_SM * wp.get_device(device).sm_count
    return 0 if fills else CUDA_LANES


def records_samples(device: str) -> bool:
    """Whether the default kernels on `device` keep a `SampleRecord` (the one-thread-per-ray kernels
    do; the lane kernels, CUDA's default, recompute instead)."""
    return lanes_for(device, None) == 0


def _block_lanes(device: str, lanes: int) -> int:
    """The lanes a block really gets: Warp runs CPU blocks one lane wide unless
    `wp.config.enable_cpu_blocks` (more lanes would each redo every coefficient)."""
    return 1 if device == "cpu" and not wp.config.enable_cpu_blocks else lanes


class _GridViews:
    """A grid's Warp views (the `GridView` struct and its SH), built once per grid and kept on it:
    rebuilding them costs dozens of wrappers a step. They stay right while the grid keeps its tensors
    and occupancy (kernels and the optimiser write in place); a new tensor or occupancy builds new ones."""

    def __init__(self, grid: SparseGrid, occ):
        self.sources = (weakref.ref(grid.links), weakref.ref(grid.density), weakref.ref(grid.sh), occ)
        scale, offset = grid.world_to_grid_affine("cpu")
        self.view = warp_struct(
            GridView,
            links=to_warp(grid.links, "the grid links"),
            density=to_warp(grid.density.detach(), "the grid density"),
            scale=wp.vec3(*scale.tolist()),
            offset=wp.vec3(*offset.tolist()),
            reso=wp.vec3i(*grid.reso),
            levels=grid.levels,
            cells=to_warp(occ.cells, "the occupancy cells"),
            blocks=to_warp(occ.blocks, "the occupancy blocks"),
            shift=occ.shift,
        )
        sh = grid.sh.detach()
        self.sh_rows = to_warp(sh, "the grid SH", dtype=sh_row(grid.basis_dim))
        self.sh_2d = to_warp(sh, "the grid SH")

    def serves(self, grid: SparseGrid, occ) -> bool:
        links, density, sh, cached_occ = self.sources
        return links() is grid.links and density() is grid.density and sh() is grid.sh and cached_occ is occ


def _views(grid: SparseGrid) -> _GridViews:
    occ = occupancy_for(grid)
    views = grid.__dict__.get("_warp_views")
    if views is None or not views.serves(grid, occ):
        views = _GridViews(grid, occ)
        grid.__dict__["_warp_views"] = views
    return views


def _grid_view(grid: SparseGrid) -> GridView:
    return _views(grid).view


def _sh(grid: SparseGrid, lanes: int) -> wp.array:
    """The SH as the kernels take it: rows of vectors (one thread per ray) or a 2-D array (lanes)."""
    views = _views(grid)
    return views.sh_2d if lanes else views.sh_rows


def kernel_variant(
    device: str,
    grid: SparseGrid,
    opt: RenderOptions,
    specialise: bool,
    max_registers: int | None,
    *,
    distortion: bool,
    per_ray_background: bool,
    record: bool,
    shuffle_sum: bool | None = None,
    rays_per_block: int | None = None,
    rows_from_corners: bool | None = None,
) -> KernelVariant:
    """The kernels a launch compiles: the general ones, which read every feature switch at run time,
    or (`specialise`) ones fixed to this launch's grid levels and features; `max_registers` caps a CUDA
    thread's registers (ignored on the CPU, where it would only cost a compile) and `shuffle_sum` (None:
    `CUDA_SHUFFLE_SUM`) sums the lanes' colours by warp shuffles, as several rays in a lane block
    (`rays_per_block`, None: `CUDA_RAYS_PER_BLOCK`) need; `rows_from_corners` (None:
    `CUDA_ROWS_FROM_CORNERS`) keeps the lane backward from reading the links again. All are off by default
    until a GPU's timings choose them (JOURNAL.md, "Kernel variants"): a variant costs a
    compile, and the switches leave few registers behind."""
    shuffle = CUDA_SHUFFLE_SUM if shuffle_sum is None else shuffle_sum
    per_block = CUDA_RAYS_PER_BLOCK if rays_per_block is None else rays_per_block
    shuffle = shuffle or per_block > 1
    if device == "cpu":  # no cap; a CPU block's one lane needs no sum (its blocks of lanes: a tile sum)
        max_registers = None
        if wp.config.enable_cpu_blocks:
            shuffle, per_block = False, 1
    from_corners = CUDA_ROWS_FROM_CORNERS if rows_from_corners is None else rows_from_corners
    layout = {"shuffle_sum": shuffle, "rays_per_block": per_block, "rows_from_corners": from_corners}
    if not specialise:
        return KernelVariant(max_registers=max_registers, **layout)
    return KernelVariant(
        levels=grid.levels,
        distortion=distortion,
        near_grad=near_distance(opt, tuple(grid.reso)) > 0.0,
        per_ray_background=per_ray_background,
        record=record,
        max_registers=max_registers,
        **layout,
    )


def march_params(opt: RenderOptions, grid: SparseGrid | None = None) -> MarchParams:
    """The kernels' options; `grid` sizes `near_grad` (the MSI's kernels take none)."""
    return warp_struct(
        MarchParams,
        step=opt.step_size,
        sigma_thresh=opt.sigma_thresh,
        stop_thresh=opt.stop_thresh,
        t_far=opt.t_max,
        background_brightness=opt.background_brightness,
        near_grad=0.0 if grid is None else near_distance(opt, tuple(grid.reso)),
    )


def rays_input(origins: torch.Tensor, dirs: torch.Tensor) -> Rays:
    """The rays as the kernels read them (detached, contiguous float32 vectors)."""
    return warp_struct(Rays, origins=vec3s(origins), dirs=vec3s(dirs))


def vec3s(t: torch.Tensor) -> wp.array:
    return to_warp(t.detach().contiguous().float(), "a vec3 input", dtype=wp.vec3)


class Unused(NamedTuple):
    """The kernel arguments for features a launch does not use (arrays of the right types, never read)."""

    record: Record
    """No sample record."""
    background: BackgroundLink
    """The constant `RenderOptions.background_brightness` behind the grid."""
    distortion: DistortionLink
    """No distortion loss."""


@functools.cache
def _unused(device: str) -> Unused:
    def zeros(shape, dtype) -> wp.array:
        return wp.zeros(shape, dtype=dtype, device=device)

    record = warp_struct(
        Record,
        capacity=0,
        index=zeros((1, 1), wp.int32),
        values=zeros((1, 1), wp.vec4),
        count=zeros(1, wp.int32),
    )
    background = warp_struct(
        BackgroundLink, per_ray=0, radiance=zeros(1, wp.vec3), transmittance=zeros(1, wp.float32)
    )
    distortion = warp_struct(DistortionLink, enabled=0, stats=zeros(1, wp.vec3), weight=zeros(1, wp.float32))
    return Unused(record, background, distortion)


def _distortion_input(
    stats: torch.Tensor | None, weight: torch.Tensor | None, n: int, device: str
) -> DistortionLink:
    if stats is None:
        return _unused(device).distortion
    if stats.shape != (n, 3) or stats.dtype != torch.float32 or (weight is not None and weight.shape != (n,)):
        raise ValueError(f"distortion needs float32 stats ({n}, 3) and, in the backward, weights ({n},)")
    return warp_struct(
        DistortionLink,
        enabled=1,
        stats=to_warp(stats, "the distortion sums", dtype=wp.vec3),
        weight=(
            _unused(device).distortion.weight
            if weight is None
            else to_warp(weight.detach().contiguous().float(), "the distortion weights")
        ),
    )


def _background_input(
    behind: torch.Tensor | None, transmittance: torch.Tensor | None, n: int, device: str
) -> BackgroundLink:
    if behind is None:
        return _unused(device).background
    if behind.shape != (n, 3) or transmittance is None or transmittance.shape != (n,):
        raise ValueError(f"a per-ray background needs radiance ({n}, 3) and a transmittance buffer ({n},)")
    transmittance = to_warp(transmittance, "the transmittance")
    return warp_struct(BackgroundLink, per_ray=1, radiance=vec3s(behind), transmittance=transmittance)


def _record_input(record: SampleRecord | None, n: int, device: str) -> Record:
    if record is None:
        return _unused(device).record
    if record.rays != n:
        raise ValueError(f"the sample record holds {record.rays} rays, the batch {n}")
    return warp_struct(
        Record,
        capacity=record.capacity,
        index=to_warp(record.index, "the sample record index"),
        values=to_warp(record.values, "the sample record values", dtype=wp.vec4),
        count=to_warp(record.count, "the sample record count"),
    )


def _launch_lanes(
    kernel, n: int, lanes: int, head: list, tail: list, device: str, per_block: int = 1
) -> None:
    """Launch a lane kernel (arguments: `head`, the first ray, `tail`) over the rays [0, n), `per_block`
    rays a block (`KernelVariant.rays_per_block`)."""
    threads = _block_lanes(device, lanes) * per_block

    def launch(start: int, stop: int, _part: int) -> None:
        blocks = -(-(stop - start) // per_block)
        inputs = [*head, start, *tail]
        launch_kernel(kernel, dim=(blocks, threads), inputs=inputs, block_dim=threads, device=device)

    launch_parts(device, n, launch, [(0, n)])


def prepared_rays(
    origins: torch.Tensor, dirs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch's rays as the kernels read them (detached, contiguous float32) and an empty (N, 3) output."""
    origins = origins.detach().contiguous().float()
    return origins, dirs.detach().contiguous().float(), torch.empty_like(origins)


def render_forward(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions,
    lanes: int | None = None,
    record: SampleRecord | None = None,
    behind: torch.Tensor | None = None,
    transmittance: torch.Tensor | None = None,
    distortion: torch.Tensor | None = None,
    specialise: bool = False,
    max_registers: int | None = None,
    shuffle_sum: bool | None = None,
    rays_per_block: int | None = None,
) -> torch.Tensor:
    """Linear radiance (N, 3) of rays with unit directions (no autograd); `lanes`: see `lanes_for`;
    `record`: filled for `accumulate_backward` (one thread per ray only, see `records_samples`);
    `behind`: per-ray radiance (N, 3) behind the grid instead of `opt.background_brightness`, and then
    `transmittance` (N,) float32 receives what the march leaves for it (docs/method.md, "Background");
    `distortion` (N, 3) float32 receives each ray's distortion sums (`DistortionLink`), its loss last;
    `specialise`, `max_registers`, `shuffle_sum`, `rays_per_block`: see `kernel_variant`."""
    device = warp_device(grid.density)
    origins, dirs, out = prepared_rays(origins, dirs)
    n = origins.shape[0]
    if n == 0:
        return out
    lanes = lanes_for(device, lanes, n)
    if lanes and record is not None:
        raise ValueError("the lane kernels keep no sample record")
    head = [_grid_view(grid), _sh(grid, lanes), march_params(opt, grid), rays_input(origins, dirs)]
    out_rgb = to_warp(out, "the radiance output", dtype=wp.vec3)
    link = _background_input(behind, transmittance, n, device)
    dist = _distortion_input(distortion, None, n, device)
    uses = dict(
        distortion=distortion is not None, per_ray_background=behind is not None, record=record is not None
    )
    layout = {"shuffle_sum": shuffle_sum, "rays_per_block": rays_per_block}
    variant = kernel_variant(device, grid, opt, specialise, max_registers, **uses, **layout)
    tail = [out_rgb, link, _record_input(record, n, device), dist]
    if lanes:
        forward_lanes = forward_for(grid.basis_dim, _block_lanes(device, lanes), variant)
        _launch_lanes(forward_lanes, n, lanes, head, tail, device, variant.rays_per_block)
        return out
    # More parts than threads: a thread done early takes the next part (image rows vary in cost).
    workers = cpu_workers()
    parts = split(n, workers if n < 16384 else 4 * workers)
    launch_split(forward_for(grid.basis_dim, 0, variant), n, head, tail, device, parts)
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
    distortion: tuple[torch.Tensor, torch.Tensor] | None = None,
    specialise: bool = False,
    max_registers: int | None = None,
    shuffle_sum: bool | None = None,
    rays_per_block: int | None = None,
    rows_from_corners: bool | None = None,
) -> None:
    """Add d(loss)/d(density, SH) for rays whose forward output was `rgb` and upstream gradient
    `grad_rgb` into `grads` (the re-march of `kernels/march_threads.py`); `lanes`: see `lanes_for`;
    `record`: what the forward over the same rays and the same grid recorded; `distortion`: the
    forward's distortion sums (N, 3) and d(loss)/d(each ray's distortion loss) (N,); `specialise`,
    `max_registers`, `shuffle_sum`, `rays_per_block`, `rows_from_corners`: see `kernel_variant` (the
    backward composites no background)."""
    device = warp_device(grid.density)
    n = origins.shape[0]
    if n == 0:
        return
    lanes = lanes_for(device, lanes)
    if lanes:
        if record is not None:
            raise ValueError("the lane kernels keep no sample record")
        if grads.density.shape[0] != 1:
            raise ValueError("lane kernels add into one gradient buffer (their atomics must be real)")
    head = [_grid_view(grid), _sh(grid, lanes), march_params(opt, grid), rays_input(origins, dirs)]
    tail = [vec3s(rgb), vec3s(grad_rgb)]
    dist = _distortion_input(*(distortion or (None, None)), n, device)
    touched = to_warp(grads.touched, "the touched rows")  # shared: every writer stores 1
    uses = dict(distortion=distortion is not None, per_ray_background=False, record=record is not None)
    layout = {
        "shuffle_sum": shuffle_sum,
        "rays_per_block": rays_per_block,
        "rows_from_corners": rows_from_corners,
    }
    variant = kernel_variant(device, grid, opt, specialise, max_registers, **uses, **layout)
    if lanes:
        targets = warp_struct(
            LaneGradientTargets,
            density=to_warp(grads.density[0], "the density gradient"),
            sh=to_warp(grads.sh[0], "the SH gradient"),
            touched=touched,
        )
        backward_kernel = lane_backward_for(grid.basis_dim, _block_lanes(device, lanes), variant)
        _launch_lanes(backward_kernel, n, lanes, head, [*tail, dist, targets], device, variant.rays_per_block)
        return
    backward_kernel = thread_backward_for(grid.basis_dim, variant)
    GradientTargets = gradient_targets_for(grid.basis_dim)
    tail += [_record_input(record, n, device), dist]
    per_part = []  # one pair of buffers per part: CPU threads never add into the same buffer
    for d, s in zip(grads.density, grads.sh):
        row_t = sh_row(grid.basis_dim)
        targets = warp_struct(
            GradientTargets,
            density=to_warp(d, "a density gradient part"),
            sh=to_warp(s, "an SH gradient part", dtype=row_t),
            touched=touched,
        )
        per_part.append([*tail, targets])
    parts = split(n, len(per_part))
    launch_split(backward_kernel, n, head, lambda part: per_part[part], device, parts)


def mark_read_rows(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions, rows: torch.Tensor
) -> None:
    """Mark in `rows` (uint8 over the grid's rows) every row `render_forward` of these rays will read,
    and some more (`kernels/march_read_rows.py`); nothing is cleared."""
    device = warp_device(grid.density)
    check_row_array("rows", rows, grid.num_voxels, torch.uint8)
    origins, dirs, _ = prepared_rays(origins, dirs)
    n = origins.shape[0]
    if n == 0 or grid.num_voxels == 0:
        return
    head = [_grid_view(grid), march_params(opt, grid), rays_input(origins, dirs)]
    tail = [to_warp(rows, "the rows read")]
    launch_split(mark_read_rows_kernel, n, head, tail, device)
    torch.autograd.graph.increment_version([rows])
