"""Files written on one worker thread while the caller goes on (JOURNAL.md, "Checkpoint writes").

A write is mostly waiting: for the disk, for `fsync`, for CRCs of large buffers, none of which holds
Python's lock, so training steps, renders and fits go on beside it. Writes run one at a time, in the order
they were handed over; a failed one is raised by the next `wait` (or `close`), never lost.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor


class WriterThread:
    """One worker thread for writes; `wait()` is the point where the caller needs them done."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hdrplenoxels-writer")
        self._pending: list[Future] = []

    def submit(self, write: Callable[..., object], *args: object) -> Future:
        """Queue `write(*args)`; its future's `result()` waits for that one alone."""
        future = self._pool.submit(write, *args)
        self._pending.append(future)
        return future

    def wait(self) -> None:
        """Block until every write handed over so far has finished; raise the first one that failed."""
        pending, self._pending = self._pending, []
        errors = [e for e in (f.exception() for f in pending) if e is not None]
        if errors:
            for later in errors[1:]:
                errors[0].add_note(f"another background write also failed: {later}")
            raise errors[0]

    def close(self) -> None:
        """`wait`, then stop the thread (it stops even when a write failed)."""
        try:
            self.wait()
        finally:
            self._pool.shutdown(wait=True)

    def __enter__(self) -> WriterThread:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        try:  # already failing: finish the writes; the caller's error is raised, a write's noted on it
            self.close()
        except Exception as e:  # noqa: BLE001
            if exc is not None and e is not exc:  # (the caller may be raising a write's own error)
                exc.add_note(f"a background write also failed: {e}")
