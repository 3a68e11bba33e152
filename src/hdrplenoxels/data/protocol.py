"""The evaluation protocol's split, defined once (docs/method.md, "Evaluation protocol").

Every 8th view is a test view; the left half of a test view (columns [0, W//2)) trains its tone
parameters and its right half is scored. Training, evaluation and the experiments all read it here.
"""

from __future__ import annotations

HOLDOUT_EVERY = 8  # every 8th view (index % 8 == 0) is a test view, as in LLFF / HDR-Plenoxels


def every_nth_split(n: int, every: int = HOLDOUT_EVERY) -> tuple[list[int], list[int]]:
    """(train_ids, test_ids) with test views at indices 0, every, 2*every, ..."""
    test = [i for i in range(n) if i % every == 0]
    train = [i for i in range(n) if i % every != 0]
    return train, test


def left_width(width: int) -> int:
    """Columns [0, W//2) of a test view train its parameters; [W//2, W) are scored (one definition)."""
    return width // 2
