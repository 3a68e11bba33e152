"""`benchmarks/prior_update.py` (device session 3 runs it at 23 M rows) runs on the CPU at a test's size,
and its two timed updates, the dense pass and the owed pull, leave the same grid."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import prior_update  # noqa: E402


def test_the_prior_update_benchmark_times_the_same_training_both_ways():
    cpu = torch.device("cpu")
    update = prior_update.update_times(500, 0.05, 1, cpu)
    assert update["every_row_ms"] > 0 and update["touched_rows_ms"] > 0
    step = prior_update.step_times(500, 0.05, 0.08, 1, cpu)
    assert step["dense_step_ms"] > 0 and step["owed_step_ms"] > 0
    assert step["max_difference"] == 0.0  # to the bit on a CPU
