"""Checking a .npy header against the bytes really there before numpy allocates anything.

numpy's `np.load` allocates the array its header declares and only then reads the data: a damaged or
hostile file declaring a shape of 10^12 elements asks for terabytes, and on a machine that overcommits
memory it may get them and be killed later. A header is accepted only when its dtype holds no Python
objects and its shape times its item size equals the data bytes that follow it (the file's size, or a
zip entry's stated size) and fits in the memory this process has left (docs/design.md, "Data loading").
`read_npz` reads every array of an archive that way (models, checkpoints, sparse points).
"""

from __future__ import annotations

import math
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.host_memory import available_memory_bytes

_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}


class NpyHeaderError(ValueError):
    """The .npy header can't be honoured; the message says why (the caller adds the file's name)."""


def check_npy_header(f: BinaryIO, total_bytes: int) -> tuple[tuple[int, ...], np.dtype]:
    """Read and check the header of the .npy stream `f` of `total_bytes` (header included); returns the
    shape and dtype. The stream is left after the header."""
    try:
        version = np.lib.format.read_magic(f)
        reader = _READERS.get(version)
        if reader is None:
            raise NpyHeaderError(f".npy format version {version[0]}.{version[1]} is not supported")
        shape, _, dtype = reader(f)
    except NpyHeaderError:
        raise
    except (ValueError, TypeError, SyntaxError, OverflowError, EOFError, tokenize.TokenError) as e:
        raise NpyHeaderError(f"broken .npy header ({_first_line(e)})") from None
    if dtype.hasobject:
        raise NpyHeaderError(f"holds Python objects (dtype {dtype}), which are never loaded")
    declared = math.prod(shape) * dtype.itemsize
    held = total_bytes - f.tell()
    if declared != held:
        raise NpyHeaderError(
            f"header declares shape {shape} of {dtype} ({_size(declared)}) but {_size(max(held, 0))} "
            "of data follow: the file is damaged"
        )
    shortfall = memory_shortfall(declared)
    if shortfall:
        raise NpyHeaderError(f"shape {shape} of {dtype} {shortfall}")
    return shape, dtype


def memory_shortfall(nbytes: int) -> str | None:
    """What an array of `nbytes` a file asks for lacks ("needs ... of memory, ... free"), or None when it
    fits (or the free memory is unknown): a reader refuses it before allocating."""
    free = available_memory_bytes()
    if free is not None and nbytes > free:
        return f"needs {_size(nbytes)} of memory, {_size(free)} free"
    return None


def _first_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return lines[0] if lines else type(e).__name__


def _size(n: float) -> str:
    if n < 1024:
        return f"{int(n)} bytes"
    for unit in ("KiB", "MiB", "GiB"):
        n /= 1024
        if n < 1024:
            return f"{n:.1f} {unit}"
    return f"{n / 1024:.1f} TiB"


def check_npy_file(path) -> None:
    """`check_npy_header` on a .npy file (raises OSError when it can't be read)."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        total = f.tell()
        f.seek(0)
        check_npy_header(f, total)


_READ_ERRORS = (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError, KeyError, RuntimeError)


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of an `.npz` (no pickle), or an `InputError` saying why the file can't be read."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found")
    if p.is_dir():
        raise InputError(p, "is a folder, expected an .npz file")
    try:
        with open(p, "rb") as f:
            head = f.read(6)
    except OSError as e:
        raise InputError(p, f"can't be read ({_reason(e)})") from e
    if not head:
        raise InputError(p, "not a readable .npz archive (the file is empty)")
    if not head.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):
        # Checked up front: numpy would otherwise try pickle and advise `allow_pickle`, which we never use.
        raise InputError(p, "not a readable .npz archive (unrecognised content)")
    if head.startswith(b"PK"):
        _check_npz_headers(p)
    try:
        loaded = np.load(p, allow_pickle=False)
    except _READ_ERRORS as e:
        raise InputError(p, f"not a readable .npz archive ({_reason(e)})") from e
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise InputError(p, "is a single .npy array, not an .npz archive")
    out: dict[str, np.ndarray] = {}
    with loaded:
        for key in loaded.files:
            try:
                out[key] = loaded[key]
            except _READ_ERRORS as e:
                raise InputError(p, f"entry {key!r} can't be read; the file is damaged ({_reason(e)})") from e
    return out


def _check_npz_headers(p: Path) -> None:
    """Every entry's .npy header against its stored size (`check_npy_header`), before numpy allocates."""
    try:
        with zipfile.ZipFile(p) as zf:
            for info in zf.infolist():
                if info.filename.endswith(".npy"):
                    with zf.open(info) as f:
                        check_npy_header(f, info.file_size)
    except NpyHeaderError as e:
        raise InputError(p, f"entry {info.filename.removesuffix('.npy')!r}: {e}") from None
    except _READ_ERRORS as e:
        raise InputError(p, f"not a readable .npz archive ({_reason(e)})") from e


def _reason(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__
