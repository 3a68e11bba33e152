"""User-facing errors: one clear line naming the file and the problem, never a traceback."""

from __future__ import annotations

import errno as errno_codes
import os
from pathlib import Path


class InputError(Exception):
    """Bad input from the user (a file, a path, a value). The CLI prints it as one line and exits 2."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class WriteError(OSError):
    """A file could not be written (disk full, read-only folder, no permission). Writes are atomic
    (core/atomic.py), so whatever was at `path` before is still there; the CLI prints one line."""

    def __init__(self, path: str | Path, reason: str, code: int | None = None):
        super().__init__(code, reason, str(path))
        self.path = Path(path)
        self.reason = reason

    def __str__(self) -> str:
        return f"{self.path}: can't write ({self.reason})"

    @classmethod
    def from_os_error(cls, path: str | Path, e: OSError) -> WriteError:
        code = e.errno
        reason = e.strerror or (os.strerror(code) if code else str(e)) or type(e).__name__
        return cls(path, reason, code)


def no_space(path: str | Path, needed: int, free: int) -> WriteError:
    """The error for a file known in advance not to fit on its disk."""
    mib = 1 << 20
    size = f"needs at least {needed / mib:.1f} MiB, {free / mib:.1f} MiB free"
    reason = f"{os.strerror(errno_codes.ENOSPC)}: {size}"
    return WriteError(path, reason, errno_codes.ENOSPC)
