"""Which grid rows a batch's forward will read: the march alone, marking each visited sample's corners.

The view prior's pull may be owed by rows no step touched (`train/optim.Svox2RMSProp`); a step pays
what the rows it reads owe before it reads them, and this march says which those are. It visits the
samples the forward visits (`next_visit`) and composites the density as the forward does, but marks
every visited sample's 8 corners (also below the density threshold, and row 0 where a corner is empty,
which the forward reads at weight 0) and stops only once the transmittance is below half the
forward's stop: a superset of the forward's reads that no rounding can undercut.

Oracle: `hdrplenoxels.kernels.march_reference.read_rows_reference`; parity: tests/test_read_rows.py.
"""

import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, mark_touched
from hdrplenoxels.kernels.march_funcs import (
    GridView,
    MarchParams,
    Rays,
    composite,
    fetch_corners,
    first_slot,
    next_visit,
    sample_delta,
    setup_ray,
)

STOP_MARGIN = wp.constant(0.5)
"""The march stops at this share of the forward's stop threshold (`RenderOptions.stop_thresh`)."""


@KERNEL
def mark_read_rows_kernel(
    grid: GridView, params: MarchParams, rays: Rays, first_ray: int, rows: wp.array(dtype=wp.uint8)
):
    tid = wp.tid() + first_ray
    r = setup_ray(rays.origins[tid], rays.dirs[tid], grid, params, grid.levels)
    inv_step = 1.0 / params.step
    log_t = wp.float32(0.0)
    t_end = wp.float32(1.0)
    visit = next_visit(r, first_slot(r, grid, params), 0, inv_step, grid, params)
    while visit.s < r.num_samples:
        corners = fetch_corners(grid, visit.cell)
        for n in range(8):
            mark_touched(rows, corners.rows[n])
        sigma = corners.sigma
        if sigma > params.sigma_thresh:
            tau = sigma * sample_delta(r, visit.cell)
            step = composite(t_end, log_t, tau, params.stop_thresh * STOP_MARGIN)
            log_t = step[1]
            t_end = step[2]
            if step[3] != 0.0:
                break
        visit = next_visit(r, visit.slot, visit.s + 1, inv_step, grid, params)
