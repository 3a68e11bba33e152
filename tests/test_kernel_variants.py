"""Kernels compiled for one launch's features (`march.KernelVariant`, `launch.kernel_variant`) render and
differentiate exactly as the general kernels, which read the same switches at run time, and as the
PyTorch oracle: fixing a switch at compile time may only drop code, never change arithmetic."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from render_helpers import cascade_grid, cascade_rays

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import RenderOptions, launch, render_rays
from hdrplenoxels.render.grad_buffers import GridGradients
from hdrplenoxels.render.march import GENERAL, KernelVariant
from hdrplenoxels.render.sample_record import SampleRecord

N = 240


def _run(grid, o, d, opt, lanes, specialise, features):
    """rgb, distortion sums, transmittance and the gradients of one forward + backward."""
    gen = torch.Generator().manual_seed(5)
    upstream, dist_weight = torch.randn(N, 3, generator=gen), torch.rand(N, generator=gen)
    behind = torch.rand(N, 3, generator=gen) if features else None
    transmittance = torch.empty(N) if features else None
    stats = torch.empty(N, 3) if features else None
    record = SampleRecord.empty(N, "cpu", 3) if features and not lanes else None
    rgb = launch.render_forward(
        grid, o, d, opt, lanes, record, behind, transmittance, stats, specialise=specialise
    )
    grads = GridGradients(grid, parts=1 if lanes else 2)
    launch.accumulate_backward(
        grid,
        o,
        d,
        rgb,
        upstream,
        opt,
        grads,
        lanes,
        record,
        (stats, dist_weight) if features else None,
        specialise=specialise,
    )
    return [t for t in (rgb, stats, transmittance, *grads.total()) if t is not None]


@pytest.mark.parametrize(
    ("lanes", "levels", "features"),
    [(0, 1, False), (0, 3, True), (8, 3, True)],
    ids=["thread-one-box-plain", "thread-cascade-every-feature", "lanes-cascade-every-feature"],
)
def test_a_specialised_kernel_equals_the_general_one_and_the_oracle(monkeypatch, lanes, levels, features):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", lanes > 0)
    grid = cascade_grid((9, 8, 7), 9, seed=levels, levels=levels, empty_fraction=0.2)
    o, d = cascade_rays(N, seed=levels + 1, levels=levels)
    opt = RenderOptions(stop_thresh=0.01, near_grad=1.5 if features else 0.0, background_brightness=0.3)
    general = _run(grid, o, d, opt, lanes, False, features)
    fixed = _run(grid, o, d, opt, lanes, True, features)
    assert len(general) == len(fixed) == (5 if features else 3)
    for a, b in zip(general, fixed):
        assert torch.equal(a, b)
    assert general[-1].abs().max() > 1e-3  # gradients really flow
    if not features:  # the general kernels meet the oracle with each feature on in their own tests
        density, sh = grid.density.clone().requires_grad_(True), grid.sh.clone().requires_grad_(True)
        ref = render_rays(SparseGrid(grid.links, density, sh, grid.center, grid.radius), o, d, opt, "torch")
        (ref * torch.randn(N, 3, generator=torch.Generator().manual_seed(5))).sum().backward()
        for a, b in zip((ref.detach(), density.grad, sh.grad), fixed):
            assert (a - b).abs().max() <= 1e-5


def test_the_variant_fixes_what_the_launch_uses_only_when_asked():
    grid = cascade_grid((9, 8, 7), 4, seed=1, levels=2)
    features = dict(distortion=True, per_ray_background=False, record=True)
    opt = RenderOptions()
    assert launch.kernel_variant("cuda:0", grid, opt, False, None, **features) == GENERAL
    assert launch.kernel_variant("cuda:0", grid, opt, False, 96, **features) == KernelVariant(
        max_registers=96
    )
    assert launch.kernel_variant("cpu", grid, opt, False, 96, **features) == GENERAL  # no registers to cap
    fixed = launch.kernel_variant("cpu", grid, RenderOptions(near_grad=1.0), True, None, **features)
    assert fixed == KernelVariant(2, True, True, False, True)
    assert fixed.switches() == (2, 1, 1, 0, 1) and GENERAL.switches() == (0, -1, -1, -1, -1)
