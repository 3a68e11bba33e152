"""Process-wide settings that make the CPU kernels fast, applied explicitly (never on import).

The command line applies them before torch loads (`hdrplenoxels.cli`); a library user calls
`apply_process_settings()` first thing, before `import torch`. Measurements: JOURNAL.md.
"""

from __future__ import annotations

import os

# Our CPU kernels run on Python threads between torch ops. torch's OpenMP threads spin for a while after
# each op (GNU OpenMP: 300k spins) and take the cores those kernels need; sleeping at once makes every
# small torch op pay a wake-up instead. A short spin keeps both fast. Read by OpenMP when torch loads.
OPENMP_SPIN = ("GOMP_SPINCOUNT", "10000")
# The ray march reads and adds into grid rows scattered over hundreds of MB; with 4 KiB pages nearly every
# row costs a TLB miss. torch's CPU allocator backs large tensors with 2 MiB pages when asked (where the
# kernel's transparent huge pages are "madvise"). torch reads this at its first large CPU allocation.
HUGE_PAGES = ("THP_MEM_ALLOC_ENABLE", "1")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity on Linux, else all), without importing torch:
    a thread count chosen from it must be set before torch loads."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def apply_process_settings() -> dict[str, str]:
    """Set the OpenMP spin and huge-page allocation for this process; a user's own setting wins.

    Returns the values in force. Effective only before torch is imported (the spin) or before its first
    large CPU allocation (huge pages)."""
    for name, value in (OPENMP_SPIN, HUGE_PAGES):
        os.environ.setdefault(name, value)
    return {name: os.environ[name] for name, _ in (OPENMP_SPIN, HUGE_PAGES)}
