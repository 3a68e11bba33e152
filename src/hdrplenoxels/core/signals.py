"""SIGINT and SIGTERM as a request to stop at the next safe point, instead of dying mid-write."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass
class StopRequest:
    signal: str | None = None  # the name of the first stop signal received, once one arrived


@contextmanager
def stop_signals() -> Iterator[StopRequest]:
    """While inside, SIGINT/SIGTERM only record themselves in the yielded request; the previous handlers
    come back on exit. Outside the main thread (where Python delivers no signal) nothing is installed."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def record(signum: int, _frame) -> None:
        if request.signal is None:
            request.signal = signal.Signals(signum).name

    previous = {s: signal.signal(s, record) for s in STOP_SIGNALS}
    try:
        yield request
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
