"""Every CPU kernel family once on tiny inputs, for `test_large_arrays.py` to run under Warp's debug
build (`HDRPLENOXELS_WARP_DEBUG=1`: every array access bounds-checked, a bad one aborts)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch
from render_helpers import cascade_grid, cascade_rays

from hdrplenoxels.data import load_scene
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.background_kernel import MSIGradients, msi_accumulate_backward, msi_forward
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
from hdrplenoxels.kernels.resample_kernel import resample
from hdrplenoxels.kernels.rmsprop import RMSPropStep
from hdrplenoxels.kernels.rmsprop_kernel import fused_grid_rmsprop_touched_, fused_rmsprop_
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.kernels.tv import TVTerm, sample_tv_cells
from hdrplenoxels.kernels.tv_kernel import tv_grad_
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.synth.procedural import ProceduralSceneSpec, write_procedural_scene
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer


def main() -> None:
    grid = cascade_grid((9, 8, 7), 9, seed=0)
    o, d = cascade_rays(200, seed=1)
    weights = torch.randn(200, 3, generator=torch.Generator().manual_seed(2))
    opt = RenderOptions()
    record = SampleRecord.empty(len(o), "cpu", 4)  # small: some rays overflow it and re-march
    stats = torch.zeros(len(o), 3)
    rgb = march_kernel.render_forward(grid, o, d, opt, lanes=0, record=record, distortion=stats)
    grads = GridGradients(grid, parts=2)
    march_kernel.accumulate_backward(grid, o, d, rgb, weights, opt, grads, lanes=0, record=record,
                               distortion=(stats, torch.ones(len(o))))  # fmt: skip
    lane_rgb = march_kernel.render_forward(grid, o, d, opt, lanes=4)
    march_kernel.accumulate_backward(
        grid, o, d, lane_rgb, weights, opt, GridGradients(grid, parts=1), lanes=4
    )
    cells = sample_tv_cells(tuple(grid.links.shape), 1.0)
    tv_grad_(TVTerm(grid.links, grid.sh, 0.1, cells, "self"), grads.sh, touched=grads.touched)
    occupancy = occupancy_for(grid)
    states = (torch.zeros_like(grid.density), torch.zeros_like(grid.sh))
    last_step = torch.zeros(grid.num_voxels, dtype=torch.int32)
    fused_grid_rmsprop_touched_((grid.density, grid.sh), states, (grads.density, grads.sh), (1.0, 0.1),
                                grads.touched, last_step, 3, 0.95, 1e-8, -1e9, occupancy)  # fmt: skip
    fused_rmsprop_(RMSPropStep(grid.density, states[0], grads.density, 1.0, 0.95, 1e-8, -1e9), occupancy)
    pulled = RMSPropStep(grid.sh, states[1], grads.sh, 0.1, 0.95, 1e-8, -1e9, torch.ones(27))
    fused_rmsprop_(pulled, per_element=True)
    fused_rmsprop_(RMSPropStep(grid.sh, states[1], grads.sh, 0.1, 0.95, 1e-8, -1e9), per_element=False)
    bg = MSIBackground.create(grid, layers=4, height=8, width=16, density=0.5)
    bg_rgb = msi_forward(bg, o, d, opt)
    msi_accumulate_backward(bg, o, d, bg_rgb, weights, opt, MSIGradients(bg, parts=2))
    resample(grid, (12, 11, 10), thresh=-10.0)

    with tempfile.TemporaryDirectory() as tmp:
        spec = ProceduralSceneSpec(grid_reso=16, num_views=8, width=16, height=12)
        scene = load_scene(write_procedural_scene(Path(tmp) / "scene", spec))
        cfg = preset("fast")
        cfg.device = "cpu"
        cfg.grid.reso_schedule = [(8, 8, 8), (12, 12, 12)]
        cfg.grid.upsample_every = 6
        cfg.optim.n_iters = 12
        cfg.optim.batch_size = 256
        cfg.optim.lambda_distortion = 0.01
        cfg.tonemap.enabled = True
        cfg.background.enabled = True
        cfg.checkpoint_every = 0
        Trainer(scene, cfg, Path(tmp) / "run").run(progress=False)
    print("in bounds: forward, backward, lanes, record, occupancy, TV, MSI, optimiser, resample, training")


if __name__ == "__main__":
    main()
