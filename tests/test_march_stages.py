"""benchmarks/march_stages.py's stage kernels are copies of the lane forward cut after a stage; its
`eager` kernel (the SH read beside the density) is a candidate change, so it must render what the
package's kernel renders, and the cut copies must really do less (else the differences place nothing)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from render_helpers import inward_rays, random_sparse_grid

from hdrplenoxels.kernels.march_kernel import render_forward
from hdrplenoxels.render import RenderOptions

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import march_stages  # noqa: E402


def test_the_eager_and_sh_kernels_render_what_the_lane_forward_renders_and_march_counts_visits():
    grid = random_sparse_grid((9, 8, 7), 9, seed=5)
    o, d = inward_rays(128, seed=4)
    opt = RenderOptions(background_brightness=0.25)
    stages = ("march", "sh", "full", "eager")
    calls = march_stages.stage_calls(grid, o, d, opt, lanes=32, stages=stages)
    for stage in stages:
        calls[stage]()
    expected = render_forward(grid, o, d, opt, lanes=32)
    assert torch.equal(calls["full"].out, expected)
    assert torch.equal(calls["eager"].out, expected)
    # a CPU block is one lane, whose share of the SH is all of it: the cut before the sum loses nothing
    assert torch.equal(calls["sh"].out, expected)
    assert (expected - 0.25).abs().max() > 1e-2  # the rays see the grid, not only the background
    visits = calls["march"].out[:, 0] - 0.25  # one per visited sample, then the background
    assert visits.max() >= 3 and torch.equal(visits, visits.round())


def test_on_blocks_as_wide_as_a_gpu_warp_eager_renders_what_the_lane_forward_renders(monkeypatch):
    """The same on CPU blocks of 32 lanes (the block-wide sum real, as on CUDA), and with 5 lanes, which
    do not divide the 27 coefficients; `sh` (each lane's share, unsummed) then differs."""
    import warp as wp

    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    grid = random_sparse_grid((9, 8, 7), 9, seed=5)
    o, d = inward_rays(96, seed=4)
    opt = RenderOptions(background_brightness=0.25)
    for lanes in (32, 5):
        calls = march_stages.stage_calls(grid, o, d, opt, lanes=lanes, stages=("sh", "eager"))
        for stage in ("sh", "eager"):
            calls[stage]()
        expected = render_forward(grid, o, d, opt, lanes=lanes)
        assert torch.equal(calls["eager"].out, expected), lanes
        assert not torch.equal(calls["sh"].out, expected), lanes


def test_the_backward_stages_do_less_than_the_package_backward_and_keep_what_they_compute():
    """`bwd-plain` flushes the slots as the package's kernel does, with plain stores: on a CPU (one lane
    a block) its per-ray sums add up to what the package's atomics add into the grid; `bwd-march`
    keeps every sample's gradients alive without scattering any."""
    grid = random_sparse_grid((9, 8, 7), 9, seed=5)
    o, d = inward_rays(128, seed=4)
    opt = RenderOptions(background_brightness=0.25)
    calls = march_stages.stage_calls(grid, o, d, opt, lanes=32, stages=march_stages.BACKWARD_STAGES)
    for stage in march_stages.BACKWARD_STAGES:
        calls[stage]()
    grads = calls["backward"].out  # the package's gradient buffers
    scattered = grads.density.sum() + grads.sh.sum()
    assert scattered.abs() > 1e-3
    torch.testing.assert_close(calls["bwd-plain"].out.sum(), scattered, rtol=1e-4, atol=1e-6)
    assert calls["bwd-march"].out.abs().sum() > 0
