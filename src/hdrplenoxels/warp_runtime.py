"""Warp, initialised once and quietly, for every module that launches kernels.

Every kernel here has a hand-written backward (or none), so Warp's automatic adjoints are never
generated: `KERNEL` is the decorator all our kernels use.
"""

from __future__ import annotations

import functools
import logging

import warp as wp

wp.config.log_level = logging.WARNING  # no start-up banner or per-module load lines
wp.init()

KERNEL = functools.partial(wp.kernel, module="unique", enable_backward=False)


def warp_device(t) -> str:
    """Warp's name for the device of torch tensor `t`."""
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"
