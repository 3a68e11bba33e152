"""Splitting one Warp launch over the CPU's cores.

Warp runs a CPU kernel as one sequential loop (JOURNAL.md, "Other measured choices"), but it
releases the GIL while the kernel runs, so the same kernel launched on disjoint slices from several
Python threads uses several cores. CUDA launches are never split: the GPU is already parallel.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import torch

from hdrplenoxels.core.process_settings import available_cores

# Set, kernels are built in Warp's debug mode (`warp_runtime.ensure_warp`), which crashes when two threads
# run a kernel at once: one thread then runs them all.
WARP_DEBUG_VARIABLE = "HDRPLENOXELS_WARP_DEBUG"
MIN_ITEMS_PER_WORKER = 256  # below this the thread hand-off costs more than it saves

_pool: ThreadPoolExecutor | None = None


def cpu_workers() -> int:
    """How many threads CPU kernels use: torch's thread count (OMP_NUM_THREADS), capped by the cores;
    one under Warp's debug build (`WARP_DEBUG_VARIABLE`)."""
    if os.environ.get(WARP_DEBUG_VARIABLE):
        return 1
    return max(1, min(torch.get_num_threads(), available_cores()))


def split(n: int, parts: int) -> list[tuple[int, int]]:
    """At most `parts` contiguous, non-empty (start, stop) ranges covering [0, n); fewer when n is small."""
    parts = max(1, min(parts, n // MIN_ITEMS_PER_WORKER))
    bounds = [n * i // parts for i in range(parts + 1)]
    return [(bounds[i], bounds[i + 1]) for i in range(parts) if bounds[i + 1] > bounds[i]]


def run_parts(parts: list[tuple[int, int]], launch: Callable[[int, int, int], None], workers: int) -> None:
    """Call `launch(start, stop, part_index)` once for every part, on up to `workers` threads.

    The calling thread works too (waking a pool thread costs time: JOURNAL.md, "Constants
    justified by timings"), and each thread takes the next unclaimed part when it is done, which balances
    parts of uneven cost (image rows).
    """
    global _pool
    workers = min(workers, len(parts))
    if workers <= 1:
        for i, (a, b) in enumerate(parts):
            launch(a, b, i)
        return
    if _pool is None or _pool._max_workers < workers - 1:
        _pool = ThreadPoolExecutor(max_workers=workers - 1, thread_name_prefix="hdrplenoxels-warp")
    queue = iter(enumerate(parts))
    lock = threading.Lock()

    def drain() -> None:
        while True:
            with lock:
                item = next(queue, None)
            if item is None:
                return
            i, (a, b) = item
            launch(a, b, i)

    helpers = [_pool.submit(drain) for _ in range(workers - 1)]
    drain()
    for f in helpers:
        f.result()
