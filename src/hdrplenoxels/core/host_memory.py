"""How much memory this process can still take: what sizes the CPU's per-thread gradient buffers.

The standard library has no portable call for it (and `psutil` is not a dependency for one number),
so this reads Linux's own accounting: `MemAvailable` (free memory plus the page cache the kernel can
drop), capped by the headroom of the process's cgroup, whose limit a container's `/proc/meminfo`
does not show. Elsewhere it answers None ("unknown") and callers assume plenty.
"""

from __future__ import annotations

from pathlib import Path

MEMINFO = Path("/proc/meminfo")
# (limit, usage) files of the process's memory cgroup: v2 (unified), then v1.
CGROUP = Path("/sys/fs/cgroup")
CGROUP_FILES = (
    (CGROUP / "memory.max", CGROUP / "memory.current"),
    (CGROUP / "memory" / "memory.limit_in_bytes", CGROUP / "memory" / "memory.usage_in_bytes"),
)
NO_LIMIT = 1 << 60  # v1 writes "no limit" as a number near 2^63, v2 as "max"


def _meminfo_available(meminfo: Path) -> int | None:
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024  # the value is in kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_headroom(files) -> int | None:
    for limit_file, usage_file in files:
        try:
            limit, usage = limit_file.read_text().strip(), int(usage_file.read_text())
        except (OSError, ValueError):
            continue
        if limit != "max" and int(limit) < NO_LIMIT:
            return max(0, int(limit) - usage)
        return None
    return None


def available_memory_bytes(meminfo: Path = MEMINFO, cgroup_files=CGROUP_FILES) -> int | None:
    """Bytes this process can still allocate without swapping, or None where that is unknown."""
    known = [b for b in (_meminfo_available(meminfo), _cgroup_headroom(cgroup_files)) if b is not None]
    return min(known) if known else None
