"""benchmarks/run.py's estimate of the whole paper-synthetic schedule from a shortened run: each level's
steps priced by whether the view prior acts (a dense update, so a dearer step) and each level's one-off
cost added once, so a run whose prior ends inside a level is not priced at that level's median alone."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from run import estimate_full_run, scaled_preset  # noqa: E402

from hdrplenoxels.train.presets import preset  # noqa: E402


def step_cost(level: int, step: int, prior_end: float) -> float:
    """The trainer's rule: step `step` (from 0) takes the prior while step < prior_end."""
    return (level + 1) * (2.0 if step < prior_end else 1.0)


def test_the_estimate_prices_each_levels_steps_by_regime_and_adds_its_one_off_cost_once():
    full, cfg = preset("paper-synthetic"), scaled_preset("paper-synthetic", 400, 1)
    every, n, end = cfg.grid.upsample_every, cfg.optim.n_iters, cfg.view_prior_end()
    assert 2 * every < end < 4 * every and end % cfg.log_every != 0  # the prior ends inside level 3
    log, seconds = [], 0.0
    starts = {k * every + cfg.log_every for k in range(4)}
    for step in range(cfg.log_every, n + 1, cfg.log_every):
        level = min((step - 1) // every, 3)
        seconds += sum(step_cost(level, s, end) for s in range(step - cfg.log_every, step))
        seconds += 5.0 if step in starts else 0.0  # a resample at each level's start
        log.append({"step": step, "seconds": seconds, "voxels": 1000 * (level + 1)})
    levels, estimate = estimate_full_run(log, cfg, full)
    assert [lv["step_seconds_prior"] for lv in levels] == [2.0, 4.0, 6.0, 8.0]
    # levels 0-2 have no step without the prior: their rate stands for both
    assert [lv["step_seconds_free"] for lv in levels] == [2.0, 4.0, 6.0, 4.0]
    assert [lv["once_seconds"] for lv in levels] == pytest.approx([5.0] * 4)
    full_end = math.ceil(full.view_prior_end())  # the steps s < view_prior_end take the prior
    bounds = [0, 25600, 51200, 76800, full.optim.n_iters]
    expected = 4 * 5.0
    for level in range(4):
        prior = max(0.0, min(bounds[level + 1], full_end) - bounds[level])
        expected += (level + 1) * (2.0 * prior + (bounds[level + 1] - bounds[level] - prior))
    assert estimate == pytest.approx(expected)
    # each level at its median alone (the last level's intervals mostly after the prior) misses the
    # prior's dearer steps in the last level: 8 533 of them, 4 s dearer each here
    by_median = sum(
        lv["step_seconds"] * (hi - lo) + lv["once_seconds"] for lv, lo, hi in zip(levels, bounds, bounds[1:])
    )
    assert levels[3]["step_seconds"] == 4.0
    assert estimate - by_median == pytest.approx((full_end - bounds[3]) * 4.0)
