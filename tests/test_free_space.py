"""The free-space prior (docs/method.md, "Free space along lines of sight"): the sparse points file, the
prior's gradient against autograd, the level each sample is read from, and training that empties the
lines of sight."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from render_helpers import cascade_grid
from wall_points import with_wall_points

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.sight_lines import POINTS_FILE, SightLines, read_sight_lines, write_sight_lines
from hdrplenoxels.grid.sparse_grid import corner_weights
from hdrplenoxels.train.free_space import (
    SightSegments,
    free_space_grad_,
    line_stretches,
    near_segments,
    observed_lines,
    sample_levels,
    segment_points,
)


def _lines() -> SightLines:
    points = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0], [-1.0, 0.5, 2.0]])
    return SightLines(points, np.array([0, 1, 1, 2, 2]), np.array([0, 0, 1, 1, 2]))


def test_sparse_points_file_round_trips_by_image_stem(tmp_path):
    """Views are matched by file stem: a dataset re-encoded as PNG, subset and reordered keeps the
    observations of the views it still has, on those views' new indices."""
    path = write_sight_lines(tmp_path / POINTS_FILE, _lines(), ["a.JPG", "b.JPG", "c.JPG"])
    back = read_sight_lines(path, ["images/c.png", "images/a.png"])  # b left out, order changed
    np.testing.assert_array_equal(back.points, _lines().points)
    np.testing.assert_array_equal(back.view, [1, 0, 0])  # a's one observation, then c's two
    np.testing.assert_array_equal(np.sort(back.point), [0, 1, 2])
    assert len(back.of_views([0])) == 2 and len(back.of_views([1])) == 1


@pytest.mark.parametrize(
    "arrays, message",
    [
        ({"xyz": np.zeros((2, 3))}, "lacks array(s) images, obs_image, obs_point"),
        (
            {"xyz": np.zeros((2, 2)), "images": np.array(["a"]), "obs_image": [0], "obs_point": [0]},
            "'xyz' must be (P, 3)",
        ),
        (
            {"xyz": np.full((1, 3), np.nan), "images": np.array(["a"]), "obs_image": [0], "obs_point": [0]},
            "NaN",
        ),
        (
            {"xyz": np.zeros((1, 3)), "images": np.array(["a"]), "obs_image": [0], "obs_point": [5]},
            "'obs_point' indexes outside its 1 entries",
        ),
    ],
)
def test_a_bad_sparse_points_file_is_named_with_what_is_wrong(tmp_path, arrays, message):
    path = tmp_path / POINTS_FILE
    np.savez(path, **arrays)
    with pytest.raises(InputError) as e:
        read_sight_lines(path, ["a.png"])
    assert str(path) in str(e.value) and message in str(e.value)
    path.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable .npz archive"):
        read_sight_lines(path, ["a.png"])


def test_transforms_json_reads_the_file_its_key_names(tmp_path):
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene

    folder = write_procedural_scene(tmp_path / "s", TINY_WALLED).parent
    meta = json.loads((folder / "transforms.json").read_text())
    names = [f["file_path"] for f in meta["frames"]]
    write_sight_lines(folder / POINTS_FILE, _lines(), names[:3])
    meta["sparse_points"] = POINTS_FILE
    (folder / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(folder)
    assert scene.sight_lines is not None and len(scene.sight_lines) == 5
    meta["sparse_points"] = "missing.npz"
    (folder / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="missing.npz"):
        load_scene(folder)


def test_each_sample_is_read_from_the_finest_level_that_holds_it():
    grid = cascade_grid((8, 8, 8), 1, seed=3, levels=3)
    centre, radius = torch.tensor(grid.center), torch.tensor(grid.radius)
    x = centre + radius * torch.tensor([[0.5, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, -3.5], [9.0, 0, 0]])
    pos, level, inside = sample_levels(grid, x)
    assert level.tolist() == [0, 1, 2, 2] and inside.tolist() == [True, True, True, False]
    scale, offset = grid.world_to_grid_affine()
    for k in range(3):  # each position is the point in its level's own grid coordinates
        s, o = grid.world_to_grid_affine(level=int(level[k]))
        torch.testing.assert_close(pos[k], x[k] * s + o, atol=1e-4, rtol=0)


def _autograd_loss(grid, segments, weight, lines, samples, seed, spread):
    """The prior's loss written with autograd: weight x mean over segments of sum(relu(sigma) 2^-l L/S)."""
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(len(segments), (lines,), generator=g)
    u = torch.rand((lines, samples, 1), generator=g)
    s, e = segments.starts[pick], segments.ends[pick]
    x = segment_points(s, e, u, spread, g)
    pos, level, inside = sample_levels(grid, x)
    density = grid.density.detach().clone().requires_grad_(True)
    rows, cw = corner_weights(grid.links, pos, level)
    values = torch.where(rows >= 0, density[rows.clamp(min=0)], torch.zeros_like(cw))
    sigma = (cw * values).sum(-1) * inside
    tau = (torch.relu(sigma) * 0.5 ** level.float() * (e - s).norm(dim=-1)[:, None] / samples).sum(-1)
    loss = weight * tau.mean()
    loss.backward()
    return loss.detach(), density.grad


@pytest.mark.parametrize("spread", [0.0, 0.05])
def test_the_gradient_is_that_of_the_mean_optical_depth_of_the_segments(spread):
    grid = cascade_grid((8, 8, 8), 1, seed=11, levels=3)
    g = torch.Generator().manual_seed(0)
    starts = torch.randn(40, 3, generator=g) * 3.0  # from every level and from outside them all
    ends = torch.randn(40, 3, generator=g) * 0.8
    segments = SightSegments(starts, ends)
    grad = torch.zeros_like(grid.density)
    touched = torch.zeros(grid.num_voxels, dtype=torch.uint8)
    gen = torch.Generator().manual_seed(5)
    loss = free_space_grad_(grid, segments, 0.3, 64, 8, gen, grad, touched, spread, with_loss=True)
    ref_loss, ref_grad = _autograd_loss(grid, segments, 0.3, 64, 8, seed=5, spread=spread)
    torch.testing.assert_close(loss, ref_loss, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-5, atol=1e-7)
    assert ref_grad.abs().gt(0).sum() > 20  # the segments did reach voxels with density
    assert torch.equal(touched.bool(), grad != 0)  # every row with a gradient is marked for the optimiser


def test_a_spread_segment_fills_a_cone_from_its_camera():
    s, e = torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 10.0]])
    u = torch.rand((1, 4000, 1), generator=torch.Generator().manual_seed(0))
    x = segment_points(s, e, u, 0.1, torch.Generator().manual_seed(1))[0]
    off = x[:, :2].norm(dim=-1)
    torch.testing.assert_close(x[:, 2], 10.0 * u[0, :, 0])  # along the axis as without the spread
    assert (off <= 0.1 * x[:, 2] + 1e-5).all() and (off > 0.08 * x[:, 2]).any()  # inside the cone, filling it


def test_segments_run_from_each_training_camera_short_of_its_points():
    lines = _lines()
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, :3, 3] = [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    world_from_data = np.diag([2.0, 2.0, 2.0, 1.0])  # the grid's world is twice the data's scale
    seg = line_stretches(observed_lines(lines, c2w, world_from_data, views=[0, 1]), 0.0, 1.0 - 0.25, "cpu")
    assert len(seg) == 3  # view 2's observations are not a training view's
    np.testing.assert_allclose(seg.starts[0], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(seg.ends[0], [0.0, 0.0, -1.0 + 0.75 * 3.0])  # point (0, 0, 2) in the world


def test_near_segments_fill_each_training_view_short_of_its_nearest_point():
    """Through a grid of each view's pixels, `fraction` of the way to its nearest point (1st
    percentile); a view that saw no point gets none."""
    lines = SightLines(_lines().points, np.array([0, 1, 1]), np.array([0, 0, 1]))
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, :3, 3] = [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    intrinsics = np.tile([10.0, 10.0, 4.0, 3.0], (3, 1))
    sizes = np.tile([8, 6], (3, 1))
    world_from_data = np.diag([2.0, 2.0, 2.0, 1.0])
    seen = observed_lines(lines, c2w, world_from_data, [0, 1, 2])
    seg = near_segments(seen, c2w, intrinsics, sizes, 0.5, "cpu")
    grid = 16 * 16
    assert len(seg) == 2 * grid  # view 2 saw nothing
    np.testing.assert_allclose(seg.starts[:grid], np.tile([0.0, 0.0, -1.0], (grid, 1)))
    np.testing.assert_allclose(seg.starts[grid:], np.tile([1.0, 0.0, 0.0], (grid, 1)))
    length = (seg.ends - seg.starts).norm(dim=-1)
    torch.testing.assert_close(length[:grid], torch.full((grid,), 0.5 * 3.0))  # its one point, 3 away
    far = np.percentile([np.sqrt(5.0), np.sqrt(53.0)], 1.0)  # (0, 0, 2) and (2, 4, 6) from (1, 0, 0)
    torch.testing.assert_close(length[grid:], torch.full((grid,), 0.5 * far, dtype=torch.float32))
    d = (seg.ends - seg.starts).numpy()  # identity rotations: the camera's axes are the world's
    u, v = 10.0 * d[:, 0] / d[:, 2] + 4.0, 10.0 * d[:, 1] / d[:, 2] + 3.0
    assert (d[:, 2] > 0).all() and (u > 0).all() and (u < 8).all() and (v > 0).all() and (v < 6).all()
    assert u.min() < 0.5 and u.max() > 7.5  # the grid spans the image


def test_a_test_views_left_half_is_guarded_to_the_nearest_training_point_inside_it():
    """Through a grid of the left half only, `fraction` of the way to the nearest training-view point that
    projects into it: a nearer point in the scored right half is not read; a left half holding no point
    gets none."""
    points = np.array([[-1.0, 0.0, 4.0], [-1.5, 0.0, 6.0], [1.0, 0.0, 2.0]])  # left, left, right of view 1
    lines = SightLines(points, np.array([0, 0, 0]), np.array([0, 1, 2]))  # all seen by training view 0
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[0, :3, 3] = [0.0, 0.0, -5.0]
    c2w[2, :3, 3] = [0.0, 0.0, 10.0]  # view 2 looks away from every point
    intrinsics = np.tile([4.0, 4.0, 4.0, 3.0], (3, 1))
    sizes = np.tile([8, 6], (3, 1))
    seen = observed_lines(lines, c2w, np.eye(4), [0])
    both = near_segments(seen, c2w, intrinsics, sizes, 0.5, "cpu", left_widths={1: 4, 2: 4})
    grid = 16 * 16
    assert len(both) == 2 * grid  # training view 0's, then view 1's left half; view 2's holds no point
    seg = SightSegments(both.starts[grid:], both.ends[grid:])
    np.testing.assert_allclose(seg.starts, np.zeros((grid, 3)))
    nearest = np.percentile(np.linalg.norm(points[:2], axis=1), 1.0)  # not the right half's point, 2.2 away
    torch.testing.assert_close((seg.ends - seg.starts).norm(dim=-1), torch.full((grid,), 0.5 * nearest))
    d = (seg.ends - seg.starts).numpy()
    u = 4.0 * d[:, 0] / d[:, 2] + 4.0
    assert (u > 0).all() and (u < 4).all() and u.max() > 3.8  # the left half, whole


def test_training_with_the_prior_empties_the_lines_of_sight(tmp_path):
    """Lines of sight from the training cameras of the walled scene to its walls (truth standing in for
    SfM points): with the prior, the density the field leaves on them is a fraction of what it is
    without."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene
    from hdrplenoxels.train.config import apply_overrides
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import Trainer

    scene = with_wall_points(load_scene(write_procedural_scene(tmp_path / "walled", TINY_WALLED)), 30, 0.98)
    depth = {}
    for weight in (0.0, 1.0):
        cfg = {
            "device": "cpu",
            "grid.reso_schedule": [(16, 16, 16)],
            "optim.n_iters": 60,
            "optim.batch_size": 512,
            "optim.lambda_free_space": weight,
            "optim.lambda_surface": 0.0,  # the free-space prior alone
            "optim.free_space_lines": 256,
            "optim.free_space_near": 0.0,
            "checkpoint_every": 0,
        }
        trainer = Trainer(scene, apply_overrides(preset("fast"), cfg), tmp_path / f"w{weight}")
        assert (trainer.sight_priors_note is None) == (weight == 0)
        model = trainer.run(progress=False)
        frame = (model.cameras.c2w, model.geometry.world_from_data)
        segments = line_stretches(observed_lines(scene.sight_lines, *frame, scene.train_ids), 0.0, 0.9, "cpu")
        grad = torch.zeros_like(model.grid.density)
        generator = torch.Generator().manual_seed(1)
        loss = free_space_grad_(model.grid, segments, 1.0, 2048, 32, generator, grad, with_loss=True)
        depth[weight] = float(loss)
    note = trainer.sight_priors_note
    assert "lines of sight" in note and "near the cameras" not in note
    assert depth[1.0] < 0.3 * depth[0.0], depth
    cfg.pop("optim.free_space_near")  # the default: the cameras' near segments join the lines
    near = Trainer(scene, apply_overrides(preset("fast"), cfg), tmp_path / "n")
    views, halves = len(scene.train_ids), len(scene.test_ids)  # the test views' left halves are pooled
    assert f"and {16 * 16 * (views + halves):,} near the cameras" in near.sight_priors_note
    assert f"; {halves} test views' left halves among them" in near.sight_priors_note
    bare = Trainer(
        dataclasses.replace(scene, sight_lines=None), apply_overrides(preset("fast"), cfg), tmp_path / "b"
    )
    assert bare.sight_priors_note == "free space and surfaces: off (the dataset has no sparse points)"
