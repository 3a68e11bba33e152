"""`benchmarks/profile_training.py` (where a training step goes, level by level): each level of the
schedule is timed and profiled at its end, before its resample, and the report names what ran."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hdrplenoxels.train.config import apply_overrides
from hdrplenoxels.train.presets import preset

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import profile_training  # noqa: E402

LEVELS = [(16, 16, 16), (24, 24, 24)]


def _config(n_iters: int):
    overrides = {
        "device": "cpu",
        "grid.reso_schedule": LEVELS,
        "grid.upsample_every": n_iters // 2,
        "optim.n_iters": n_iters,
        "optim.batch_size": 256,
        "checkpoint_every": 0,
        "tonemap.enabled": True,
    }
    return apply_overrides(preset("fast"), overrides)


def test_each_level_is_timed_and_profiled_on_its_own_grid(tiny_scene, tmp_path):
    report = profile_training.profile_levels(tiny_scene, _config(16), tmp_path / "run", steps=2, rows=5)
    assert report["device"] == "cpu" and not report["graph"]  # no graph on a CPU
    levels = report["levels"]
    assert [lv["reso"] for lv in levels] == [list(r) for r in LEVELS]
    assert levels[0]["voxels"] == 16**3 and levels[1]["voxels"] < 24**3  # the second level, pruned
    for lv in levels:
        assert lv["wall_ms"] > 0 and 0 < len(lv["top"]) <= 5
        assert all(r["ms"] >= 0 and r["calls"] > 0 for r in lv["top"])
        assert [r["ms"] for r in lv["top"]] == sorted((r["ms"] for r in lv["top"]), reverse=True)
    lines = profile_training.format_report(report)
    assert lines[1].startswith("level 0 (16x16x16, 4096 voxels") and "torch operators" in lines[2]
    assert "the view prior's pull auto" in lines[0]
    prior = [lv["view_prior"] for lv in levels]  # where the prior acts at each level's end
    assert ("view prior on" in lines[1]) == prior[0]


def test_a_level_too_short_for_its_windows_is_refused_before_training(tiny_scene, tmp_path):
    with pytest.raises(ValueError, match="lower --steps or --scale"):
        profile_training.profile_levels(tiny_scene, _config(16), tmp_path / "run", steps=4, rows=5)
    assert not (tmp_path / "run").exists()
