"""Atomic file writes: write to a temporary file beside the target, then rename over it.

A crash, a full disk or a bad input half-way never leaves a truncated file where a good one was, and
never leaves the temporary file behind. A failure of the file system (no space, read-only, no permission)
becomes one `WriteError` naming the target and the cause (docs/design.md, "Writing files"). The file that
lands has the mode any new file gets under the process's umask (0644 under 022), not the owner-only mode
of the temporary file it was: outputs are read on shared folders and by a cluster's other machines.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from hdrplenoxels.core.errors import WriteError, no_space

# Free space kept beyond a file's known size: file-system metadata and whatever else is writing there.
SPACE_MARGIN = 1 << 20


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success rename it onto `path`.

    `suffix` defaults to the target's own suffix, since some writers (numpy, OpenEXR, Pillow) pick the
    format from it.
    """
    path = Path(path)
    with _as_write_error(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
        os.close(fd)
    tmp_path = Path(tmp)
    try:
        with _as_write_error(path):
            yield tmp_path
            os.chmod(tmp_path, new_file_mode())
            # The data reaches the disk before the name does: a power loss keeps one or the other.
            _sync(tmp_path)
            os.replace(tmp_path, path)
            _sync(path.parent)
    finally:
        tmp_path.unlink(missing_ok=True)


def umask() -> int:
    """The process's umask, read without changing it where Linux shows it (setting it to read it back is
    not safe while other threads create files)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def new_file_mode() -> int:
    """The permission bits `open` gives a new file under the umask."""
    return 0o666 & ~umask()


def new_folder_mode() -> int:
    """The permission bits `mkdir` gives a new folder under the umask."""
    return 0o777 & ~umask()


@contextlib.contextmanager
def _as_write_error(path: Path) -> Iterator[None]:
    """An OSError about `path`, its folder or a temporary file or folder named after it becomes a
    WriteError naming `path`; one about another file (a writer reading its input) passes unchanged."""
    try:
        yield
    except WriteError:
        raise
    except OSError as e:
        if e.filename is not None and not _about(Path(os.fsdecode(e.filename)), path):
            raise
        raise WriteError.from_os_error(path, e) from e


def _about(name: Path, path: Path) -> bool:
    if name == path.parent:
        return True
    try:
        first = name.relative_to(path.parent).parts[0]
    except (ValueError, IndexError):
        return False
    return first == path.name or first.startswith(f".{path.name}.")


def _sync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def ensure_space(path: str | Path, nbytes: int) -> None:
    """Refuse, before anything is written, a file of at least `nbytes` that would not fit beside the
    old one (the temporary file and the old file exist together until the rename)."""
    path = Path(path)
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return  # unknown: the write itself will tell
    if nbytes + SPACE_MARGIN > free:
        raise no_space(path, nbytes + SPACE_MARGIN, free)


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call `write(tmp_path)` and move the result onto `path` only if it returned normally."""
    with atomic_path(path) as tmp:
        write(tmp)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text))


def atomic_write_files(folder: str | Path, write: Callable[[Path], None]) -> Path:
    """Call `write(tmp_folder)`, which may write several files (a COLMAP model), then move each onto
    `folder`: no file there is ever half-written, and nothing is touched if `write` fails."""
    folder = Path(folder)
    with _as_write_error(folder):
        folder.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        with _as_write_error(folder):
            write(tmp)
            for f in sorted(tmp.iterdir()):
                os.replace(f, folder / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
