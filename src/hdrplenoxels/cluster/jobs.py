"""A job is one unit an executor runs: a training (`TrainJob`) or a whole capture of a batch. Each runs
through `execute_logged`, which writes its output to a log file in its own folder, so the log is the same
whether the job ran in this process or on a Ray worker (docs/design.md, "Executors")."""

from __future__ import annotations

import os
import socket
import time
import traceback
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch

from hdrplenoxels.core.parallel import cpu_workers
from hdrplenoxels.core.process_settings import HUGE_PAGES, OPENMP_SPIN
from hdrplenoxels.train.runs import RunSpec, train_spec

LOG_FILE = "task.log"


class Job(Protocol):
    key: str  # names the job in progress lines and failure reports

    @property
    def folder(self) -> Path: ...  # where its log goes (on a path every node sees)

    @property
    def device(self) -> str: ...  # the config's device: a GPU is reserved where it asks for CUDA

    def finished(self) -> bool: ...

    def execute(self, resume: bool) -> dict[str, Any]: ...


@dataclass
class TrainJob:
    """One run of an experiment's plan."""

    key: str
    spec: RunSpec

    @property
    def folder(self) -> Path:
        return self.spec.run

    @property
    def device(self) -> str:
        return self.spec.config.device

    def finished(self) -> bool:
        return self.spec.finished()

    def execute(self, resume: bool) -> dict[str, Any]:
        model, _ = train_spec(self.spec, resume=resume)
        return {"step": model.step}


@dataclass
class Outcome:
    """What came back of one job: its result, or the one-line reason it failed."""

    key: str
    log: Path
    result: dict[str, Any] | None = None
    error: str | None = None


def worker_threads() -> dict[str, int]:
    """The thread counts CPU results depend on (torch's, and the Warp kernels' split: core/parallel.py)."""
    return {"torch_threads": torch.get_num_threads(), "kernel_threads": cpu_workers()}


def attempt_line(job: Job, token: str) -> str:
    """The first line of each attempt in the job's log; `token` names the batch (a progress display
    counts a job as running once its log holds this batch's line)."""
    threads = worker_threads()
    settings = " ".join(f"{name}={os.environ.get(name)}" for name, _ in (OPENMP_SPIN, HUGE_PAGES))
    return (
        f"== {job.key}: attempt on {socket.gethostname()}, pid {os.getpid()}, "
        f"{threads['torch_threads']} torch threads, {threads['kernel_threads']} kernel threads, {settings}, "
        f"batch {token} =="
    )


def execute_logged(job: Job, token: str, resume: bool) -> dict[str, Any]:
    """Run `job` with its output appended to FOLDER/task.log; an exception is logged, then raised."""
    job.folder.mkdir(parents=True, exist_ok=True)
    with (job.folder / LOG_FILE).open("a") as log, redirect_stdout(log), redirect_stderr(log):
        print(attempt_line(job, token), flush=True)
        t0 = time.perf_counter()
        try:
            result = job.execute(resume)
        except BaseException:
            traceback.print_exc()
            log.flush()
            raise
        print(f"== {job.key}: done in {time.perf_counter() - t0:.1f} s ==", flush=True)
    return result | worker_threads()


class JobFailed(Exception):
    """A job's error as one line: what a Ray task raises instead of the job's own exception, which may not
    survive the trip back to the driver (an exception whose constructor takes other arguments than its
    message is not rebuilt there)."""


def error_line(e: BaseException) -> str:
    """One line for a failed job: the message of an InputError, WriteError or JobFailed, else the
    exception's type and first line."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    name = type(e).__name__
    return text if name in ("InputError", "WriteError", "JobFailed") else f"{name}: {text}" if text else name
