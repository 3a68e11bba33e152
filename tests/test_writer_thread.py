"""The writer thread: writes in order, its failures raised where the caller waits, never lost."""

from __future__ import annotations

import threading

import pytest

from hdrplenoxels.core.writer_thread import WriterThread


def test_writes_run_in_order_on_another_thread():
    done, threads = [], set()

    def write(name):
        threads.add(threading.get_ident())
        done.append(name)

    with WriterThread() as writer:
        first = writer.submit(write, "a")
        writer.submit(write, "b")
        first.result()
        assert done[0] == "a"
    assert done == ["a", "b"] and threading.get_ident() not in threads


def test_a_failed_write_is_raised_by_the_next_wait():
    def fail():
        raise OSError("disk full")

    writer = WriterThread()
    writer.submit(fail)
    with pytest.raises(OSError, match="disk full"):
        writer.wait()
    writer.wait()  # raised once
    writer.close()


def test_the_callers_error_wins_and_the_writes_error_is_noted_on_it():
    def fail():
        raise OSError("disk full")

    with pytest.raises(ValueError) as caught, WriterThread() as writer:
        writer.submit(fail).exception()
        raise ValueError("the controller's fit failed")
    assert any("disk full" in note for note in caught.value.__notes__)
