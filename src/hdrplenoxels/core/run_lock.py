"""One writer per run folder: an advisory lock held while a run trains (docs/design.md, "Crash safety").

The lock is `fcntl.flock` on `RUN/.lock`, so the kernel drops it when the holder dies however it dies
(SIGKILL included): a stale lock file is simply locked again by the next run, with no race over deleting
it. The file holds the holder's pid and host, only to name it in the error. flock is advisory and local:
on network file systems that do not pass it on, two machines are not kept apart.
"""

from __future__ import annotations

import fcntl
import os
import socket
from pathlib import Path

from hdrplenoxels.core.errors import InputError

LOCK_FILE = ".lock"


class RunLock:
    """Exclusive use of a run folder by this process until `release()` (or the process ends)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        self.folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise InputError(
                self.folder, f"is in use by {holder}; wait for it to finish or stop it first"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"process {os.getpid()} on {socket.gethostname()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays for the next holder
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __del__(self) -> None:
        self.release()
