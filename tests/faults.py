"""File-system fault injection for tests: a write that fails part-way with ENOSPC, a folder that refuses new
files (EACCES, EROFS), an fsync or a rename that fails.

`inject(monkeypatch, fault, target)` makes the file system fail, in the way `fault` names, for `target`
and every temporary file or folder named after it beside it (`.model.npz.x1y2.npz`, `.0.partial-x1y2`), at
the lowest level Python reaches: `open` (files opened for writing get a proxy whose `write` stops part-way),
`os.open` / `os.mkdir` (creation), `os.fsync` and `os.replace`. Writers in C++ (OpenEXR, COLMAP) open their
files themselves: only creation, fsync and rename faults reach them here; a real full disk does the rest
(see `tmpfs`).
"""

from __future__ import annotations

import builtins
import contextlib
import errno
import io
import os
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

# name -> (where it strikes, errno)
FAULTS = {
    "enospc-mid-write": ("write", errno.ENOSPC),
    "eacces-create": ("create", errno.EACCES),
    "erofs-create": ("create", errno.EROFS),
    "enospc-fsync": ("fsync", errno.ENOSPC),
    "erofs-rename": ("replace", errno.EROFS),
}
WRITE_BUDGET = 40  # bytes a failing file takes before the disk is "full"
_WRITE_MODES = set("wax+")


@dataclass
class Injector:
    where: str
    code: int
    target: Path
    hits: list[str] = field(default_factory=list)

    def matches(self, path: str | os.PathLike | int) -> bool:
        if isinstance(path, int):
            try:
                path = os.readlink(f"/proc/self/fd/{path}")
            except OSError:
                return False
        p = Path(os.fsdecode(path)).absolute()
        folder = self.target.parent.absolute()
        if p == self.target.absolute():
            return True
        try:
            first = p.relative_to(folder).parts[0]
        except (ValueError, IndexError):
            return False
        return first == self.target.name or first.startswith(f".{self.target.name}.")  # or a temp file

    def fail(self, path) -> OSError:
        self.hits.append(str(path))
        return OSError(
            self.code, os.strerror(self.code), os.fsdecode(path) if not isinstance(path, int) else None
        )


class _FailingFile:
    """A file object that accepts `budget` bytes (or characters), writes part of the call that crosses it,
    then raises the injector's error on that and every later write."""

    def __init__(self, f, injector: Injector, path, budget: int):
        self._f, self._inj, self._path, self._left = f, injector, path, budget

    def write(self, data):
        if self._left >= len(data):
            self._left -= len(data)
            return self._f.write(data)
        self._f.write(data[: self._left])
        self._left = 0
        raise self._inj.fail(self._path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        with contextlib.suppress(OSError):  # a full disk's close can fail again; the write already said so
            self._f.close()

    def __getattr__(self, name):
        return getattr(self._f, name)


@contextlib.contextmanager
def inject(monkeypatch, fault: str, target: Path) -> Iterator[Injector]:
    where, code = FAULTS[fault]
    inj = Injector(where, code, Path(target))
    real_open, real_os_open, real_mkdir = builtins.open, os.open, os.mkdir
    real_fsync, real_replace = os.fsync, os.replace

    def fake_open(file, mode="r", *args, **kwargs):
        writing = bool(_WRITE_MODES & set(mode)) and not isinstance(file, int)
        if writing and inj.matches(file):
            if where == "create":
                raise inj.fail(file)
            if where == "write":
                return _FailingFile(real_open(file, mode, *args, **kwargs), inj, file, WRITE_BUDGET)
        return real_open(file, mode, *args, **kwargs)

    def fake_os_open(path, flags, *args, **kwargs):
        if where == "create" and flags & (os.O_CREAT | os.O_WRONLY | os.O_RDWR) and inj.matches(path):
            raise inj.fail(path)
        return real_os_open(path, flags, *args, **kwargs)

    def fake_mkdir(path, *args, **kwargs):
        if where == "create" and inj.matches(path):
            raise inj.fail(path)
        return real_mkdir(path, *args, **kwargs)

    def fake_fsync(fd):
        if where == "fsync" and inj.matches(fd):
            raise inj.fail(os.readlink(f"/proc/self/fd/{fd}"))
        return real_fsync(fd)

    def fake_replace(src, dst, *args, **kwargs):
        if where == "replace" and inj.matches(dst):
            raise inj.fail(dst)
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(io, "open", fake_open)
    monkeypatch.setattr(os, "open", fake_os_open)
    monkeypatch.setattr(os, "mkdir", fake_mkdir)
    monkeypatch.setattr(os, "fsync", fake_fsync)
    monkeypatch.setattr(os, "replace", fake_replace)
    try:
        yield inj
    finally:  # the file system works again after the block (a writer can then be retried)
        monkeypatch.setattr(builtins, "open", real_open)
        monkeypatch.setattr(io, "open", real_open)
        monkeypatch.setattr(os, "open", real_os_open)
        monkeypatch.setattr(os, "mkdir", real_mkdir)
        monkeypatch.setattr(os, "fsync", real_fsync)
        monkeypatch.setattr(os, "replace", real_replace)


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (hidden ones included) by relative path."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def tmpfs(folder: Path, size_kib: int) -> Iterator[Path]:
    """A real, small file system at `folder` (needs the right to mount: root in most containers); the
    caller skips when it raises PermissionError."""
    folder.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None:
        raise PermissionError("no mount command")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(folder)], capture_output=True
    )
    if done.returncode != 0:
        raise PermissionError(done.stderr.decode(errors="replace").strip())
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)
