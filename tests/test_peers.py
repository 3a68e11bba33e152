"""`benchmarks/peers.py` (gsplat on our captures): what it hands gsplat matches what we train on. gsplat
itself is CUDA only and never needed here; these are the parts that decide whether the comparison is
fair: the same pool of pixels, the same camera convention, points coloured from training views only."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from wall_points import with_wall_points

from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.geometry.cameras import pixel_rays

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "peers.py"


@pytest.fixture(scope="module")
def peers():
    spec = importlib.util.spec_from_file_location("peers", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["peers"] = module  # its dataclass looks its module up
    spec.loader.exec_module(module)
    return module


def test_the_pool_is_ours_and_a_pixel_projects_where_our_ray_leaves_it(peers, walled):
    views = peers.peer_views(walled)
    assert [v.index for v in views] == sorted(walled.train_ids + walled.test_ids)
    for v in views:
        w, _ = v.size
        assert v.pooled_width == (w // 2 if v.index in walled.test_ids else w)  # a test view's left half
        assert torch.equal(v.image, torch.tensor(walled.images[v.index], dtype=torch.float32) / 255.0)
    view = views[1]
    rows, cols = torch.tensor([0, 3, 7, 19]), torch.tensor([0, 5, 11, 23])
    c2w = torch.as_tensor(walled.cameras.c2w[view.index], dtype=torch.float32).expand(4, 4, 4)
    k = torch.as_tensor(walled.cameras.intrinsics[view.index], dtype=torch.float32).expand(4, 4)
    o, d = pixel_rays(c2w, k, cols, rows)
    points = torch.cat([o + 2.5 * d, torch.ones(4, 1)], 1)
    cam = (view.viewmat @ points.T)[:3]
    pixel = (view.K @ cam)[:2] / (view.K @ cam)[2]
    torch.testing.assert_close(pixel.T, torch.stack([cols, rows], 1).float() + 0.5, atol=1e-3, rtol=0)


def test_points_are_coloured_by_a_training_view_that_saw_them(peers, walled):
    train, test = walled.train_ids[0], walled.test_ids[0]
    picks = [(train, 4, 6), (train, 15, 9), (test, 2, 2)]  # (view, column, row)
    points, views = [], []
    for view, col, row in picks:
        c2w = torch.as_tensor(walled.cameras.c2w[view], dtype=torch.float32)[None]
        k = torch.as_tensor(walled.cameras.intrinsics[view], dtype=torch.float32)[None]
        o, d = pixel_rays(c2w, k, torch.tensor([col]), torch.tensor([row]))
        points.append((o + 1.5 * d)[0].double().numpy())
        views.append(view)
    seen = dataclasses.replace(
        walled, sight_lines=SightLines(np.array(points), np.array(views), np.arange(3))
    )
    kept, colours = peers.initial_points(seen)
    assert kept.shape == (2, 3)  # the point only a test view saw is left out
    np.testing.assert_allclose(kept, np.array(points[:2]))
    for (view, col, row), colour in zip(picks[:2], colours):
        np.testing.assert_allclose(colour, walled.images[view][row, col] / 255.0)


def test_gaussians_start_at_the_points_with_their_colours_and_the_table_reads_the_report(peers):
    rng = np.random.default_rng(0)
    points, colours = rng.normal(size=(50, 3)), rng.uniform(size=(50, 3))
    splats = peers.new_gaussians(points, colours, "cpu")
    torch.testing.assert_close(splats["means"].double(), torch.as_tensor(points), atol=1e-6, rtol=0)
    rgb = 0.5 + 0.28209479177387814 * splats["sh0"][:, 0]  # the DC term's colour
    torch.testing.assert_close(rgb.double(), torch.as_tensor(colours), atol=1e-6, rtol=0)
    assert splats["shN"].shape == (50, 15, 3) and torch.all(splats["shN"] == 0)
    result = {
        "psnr": 21.5,
        "ssim": 0.7,
        "seconds": 90.0,
        "steps": 3000,
        "gaussians": 123456,
        "peak_gpu_mb": 800.0,
    }
    report = {"method": "gsplat", "gpu": "GPU", "protocol": "right halves", "results": {"kermit": result}}
    assert "| kermit | 21.50 | 0.700 | – | 90 | 3000 | 123,456 | 800 |" in peers.markdown(report)


def test_a_sheet_row_is_photo_render_and_depth_side_by_side(peers):
    photo = np.full((6, 5, 3), 40, np.uint8)
    rgb = torch.full((6, 5, 3), 0.5)
    depth = torch.linspace(1.0, 2.0, 30).reshape(6, 5)
    opacity = torch.ones(6, 5)
    opacity[0, 0] = 0.0  # nothing hit: black
    row = peers.sheet_row(photo, rgb, depth, opacity)
    assert row.shape == (6, 15, 3) and row.dtype == np.uint8
    assert np.array_equal(row[:, :5], photo) and np.all(row[:, 5:10] == 128)
    assert np.all(row[0, 10] == 0) and row[5, 14].any()


def test_a_shorter_run_is_gsplats_schedule_compressed_not_cut_off(peers):
    full, half = peers.Schedule(), peers.Schedule(0.5)
    assert (full.steps, full.sh_every, full.exposure_delay) == (30_000, 1_000, 5_000)
    assert full.strategy() == {
        "refine_start_iter": 500,
        "refine_stop_iter": 15_000,
        "reset_every": 3_000,
        "refine_every": 100,
    }
    assert (half.steps, half.sh_every, half.exposure_delay) == (15_000, 500, 2_500)
    assert half.strategy() == {
        "refine_start_iter": 250,
        "refine_stop_iter": 7_500,
        "reset_every": 1_500,
        "refine_every": 50,
    }
    tiny = peers.Schedule(1e-4)
    assert tiny.sh_every == 1 and tiny.strategy()["refine_every"] == tiny.strategy()["reset_every"] == 1


def test_the_exposure_rate_is_held_back_then_decays_as_3dgs_runs_it(peers):
    schedule = peers.Schedule()
    assert schedule.exposure_rate(0) == pytest.approx(1e-3 * 1e-3)  # held near 0 at the start
    assert schedule.exposure_rate(2_500) < schedule.exposure_rate(5_000)
    at_delay = 1e-3 * (1e-4 / 1e-3) ** (5_000 / 30_000)  # the ramp done: log-linear from there
    assert schedule.exposure_rate(5_000) == pytest.approx(at_delay)
    assert schedule.exposure_rate(30_000) == pytest.approx(1e-4)
    assert peers.Schedule(0.5).exposure_rate(2_500) == pytest.approx(at_delay)  # compressed with the rest


def test_the_exposure_matrix_starts_as_no_correction_and_is_affine_per_image(peers):
    look = peers.Appearance(3)
    rgb = torch.rand(4, 5, 3) * 1.5  # not clamped: a render may exceed 1
    assert torch.equal(look(rgb, 1), rgb)
    with torch.no_grad():
        look.matrix[2] = torch.tensor([[0.5, 0.1, 0.0, 0.02], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 2.0, -0.1]])
    expected = torch.stack(
        [0.5 * rgb[..., 0] + 0.1 * rgb[..., 1] + 0.02, rgb[..., 1], 2.0 * rgb[..., 2] - 0.1], -1
    )
    torch.testing.assert_close(look(rgb, 2), expected)
    assert torch.equal(look(rgb, 0), rgb)  # other images untouched


def test_views_come_once_a_pass_in_a_new_order(peers):
    order = peers.view_order(7, 30)
    assert len(order) == 30
    passes = [order[i : i + 7] for i in range(0, 28, 7)]
    assert all(sorted(p) == list(range(7)) for p in passes)
    assert len({tuple(p) for p in passes}) > 1 and order == peers.view_order(7, 30)


def test_a_gaussian_starts_as_wide_as_its_three_nearest_points_root_mean_square(peers):
    points = np.stack([np.arange(8.0), np.zeros(8), np.zeros(8)], 1)  # a row, one apart
    splats = peers.new_gaussians(points, np.full((8, 3), 0.5), "cpu")
    widths = splats["scales"].detach().exp()
    assert torch.allclose(widths[:, 0], widths[:, 2])  # isotropic
    torch.testing.assert_close(float(widths[3, 0]), float(np.sqrt((1 + 1 + 4) / 3)))  # 1, 1, 2 away
    torch.testing.assert_close(float(widths[0, 0]), float(np.sqrt((1 + 4 + 9) / 3)))  # the end: 1, 2, 3


def test_the_strategy_refines_after_the_steps_update_as_gsplats_trainer(peers, walled, monkeypatch):
    """A refinement replaces the parameters (their gradients gone): before the update it would lose that
    step's update of every Gaussian. gsplat is stood in for by a renderer that depends on every parameter
    and a strategy that records what it sees."""
    seen = []

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **_):
        total = means.sum() + quats.sum() + scales.sum() + opacities.sum() + colors.sum()
        return (0.5 + 1e-3 * total).expand(1, height, width, 3), torch.ones(1, height, width, 1), {}

    class Strategy:
        def __init__(self, **steps):
            self.steps = steps

        def check_sanity(self, params, optimisers):
            pass

        def initialize_state(self, scene_scale):
            return {}

        def step_pre_backward(self, params, optimisers, state, step, info):
            pass

        def step_post_backward(self, params, optimisers, state, step, info, packed):
            adam = optimisers["means"].state[params["means"]]
            seen.append((step, int(adam["step"]), params["means"].grad is None))

    gsplat = type(sys)("gsplat")
    gsplat.rasterization, gsplat.DefaultStrategy = rasterization, Strategy
    monkeypatch.setitem(sys.modules, "gsplat", gsplat)
    monkeypatch.setattr(torch.cuda, "synchronize", lambda *a, **k: None)
    scene = with_wall_points(walled, per_view=10, reach=1.0)
    trained = peers.train(peers.peer_views(scene), scene, peers.Schedule(1e-4), None, appearance=True)
    assert trained["steps"] == 3
    assert seen == [
        (0, 1, True),
        (1, 2, True),
        (2, 3, True),
    ]  # each step's update made, its gradients cleared
