"""Views per voxel (`train/view_coverage.py`): which voxels enough pooled views see, and a grid kept to them
from the start and through every resample."""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.resample_kernel import resample
from hdrplenoxels.train.view_coverage import (
    PooledFrustums,
    pooled_frustums,
    prune_unseen,
    seen_enough,
    views_seeing,
)


def _two_cameras() -> PooledFrustums:
    """Two cameras 10 units from the origin, looking along +z and along +x, 20 x 10 pixels, focal 10; the
    second lends only its left half (a test view)."""
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[0, :3, 3] = torch.tensor([0.0, 0.0, -10.0])
    c2w[1, :3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # z -> +x
    c2w[1, :3, 3] = torch.tensor([-10.0, 0.0, 0.0])
    intrinsics = torch.tensor([[10.0, 10.0, 10.0, 5.0]]).repeat(2, 1)
    return pooled_frustums(
        c2w, intrinsics, torch.tensor([0, 1]), torch.tensor([20, 10]), torch.tensor([10, 10])
    )


def _brute_force(f: PooledFrustums, p: np.ndarray) -> np.ndarray:
    """The count, one view and one point at a time."""
    counts = np.zeros(len(p), dtype=int)
    for v in range(f.w2c.shape[0]):
        w2c, (fx, fy, cx, cy) = f.w2c[v].double().numpy(), f.intrinsics[v].tolist()
        for k, x in enumerate(p):
            c = w2c[:3, :3] @ x + w2c[:3, 3]
            if c[2] <= 0:
                continue
            u, w = fx * c[0] / c[2] + cx, fy * c[1] / c[2] + cy
            counts[k] += 0 <= u < float(f.widths[v]) and 0 <= w < float(f.heights[v])
    return counts


def _centres(grid: SparseGrid) -> torch.Tensor:
    """World positions of every allocated voxel of `grid`."""
    voxels = (grid.links >= 0).nonzero()
    return grid.grid_to_world(voxels[:, 1:].float(), voxels[:, 0])


def test_views_seeing_counts_each_views_pooled_pixels():
    f = _two_cameras()
    p = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # the first; the second at u = 10, its right half's first column
            [0.0, 0.0, -20.0],  # behind the first camera; the second at u = 30: none
            [0.0, 0.0, 5.0],  # the first, and the second at u = 10 - 5: its left half
            [0.0, 0.0, -5.0],  # the first; the second at u = 10 + 5: its right half
            [20.0, 0.0, 0.0],  # the first at u = 30; the second at u = 10: none
        ]
    )
    np.testing.assert_array_equal(views_seeing(f, p).numpy(), [1, 0, 2, 1, 0])
    random = torch.rand((500, 3), generator=torch.Generator().manual_seed(0)) * 40.0 - 20.0
    counts = views_seeing(f, random, chunk=64).numpy()
    np.testing.assert_array_equal(counts, _brute_force(f, random.double().numpy()))
    assert set(counts.tolist()) == {0, 1, 2}


def test_a_grid_keeps_only_what_enough_views_see_at_the_start_and_at_every_resample():
    f = _two_cameras()
    grid = SparseGrid.create((8, 8, 8), radius=(4.0, 4.0, 4.0), basis_dim=1, init_sigma=1.0, levels=2)
    kept = prune_unseen(grid, f, 2)
    assert 0 < kept.num_voxels < grid.num_voxels
    assert (views_seeing(f, _centres(kept)) >= 2).all()
    seen = views_seeing(f, _centres(grid)) >= 2
    assert kept.num_voxels == int(seen.sum())  # and nothing else went

    finer = resample(
        kept, (16, 16, 16), thresh=0.5, dilate=2, allowed=lambda v: seen_enough(f, 2, (16,) * 3, kept, v)
    )
    assert finer.num_voxels > 0 and (views_seeing(f, _centres(finer)) >= 2).all()
    free = resample(kept, (16, 16, 16), thresh=0.5, dilate=2)  # without it, dilation reaches past the views
    assert free.num_voxels > finer.num_voxels


def test_training_keeps_the_grid_to_voxels_two_views_see(tmp_path):
    """On the walled scene with `grid.min_views` 2: the trainer says what it dropped, and the trained
    grid, resampled once, holds no voxel fewer than two pooled views see."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene
    from hdrplenoxels.train.config import apply_overrides
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import Trainer

    scene = load_scene(write_procedural_scene(tmp_path / "walled", TINY_WALLED))
    cfg = {
        "device": "cpu",
        "grid.reso_schedule": [(8, 8, 8), (16, 16, 16)],
        "grid.upsample_every": 10,
        "grid.min_views": 2,
        "optim.n_iters": 20,
        "optim.batch_size": 256,
        "checkpoint_every": 0,
    }
    trainer = Trainer(scene, apply_overrides(preset("fast"), cfg), tmp_path / "run")
    assert trainer.coverage_note.startswith("views per voxel: at least 2; ")
    p = trainer.pool
    frustums = pooled_frustums(p.c2w, p.intrinsics, p.image_ids, p.used_width, p.heights)
    model = trainer.run(progress=False)
    assert model.grid.reso == (16, 16, 16)
    assert (views_seeing(frustums, _centres(model.grid)) >= 2).all()
