"""Running a list of jobs: one after another in this process (`local`), or as Ray tasks (`ray`) on a
local Ray instance over this machine's cores or on a running cluster (docs/design.md, "Executors").

A Ray task reserves the CPUs (and the GPU, where its config asks for CUDA) it uses, runs with the
driver's thread count so that CPU results equal a local run's bit for bit, and is retried when its worker
dies; a retry resumes the run from its newest checkpoint. Failures come back per job; the rest go on.
"""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from hdrplenoxels.cluster.jobs import LOG_FILE, Job, JobFailed, Outcome, error_line, execute_logged
from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.process_settings import apply_process_settings, available_cores
from hdrplenoxels.train.trainer import TrainingStopped

EXECUTORS = ("local", "ray")
INSTALL_HINT = "pip install hdrplenoxels[cluster]"
MAX_RETRIES = 3  # a task whose worker dies runs again (resuming its run) up to this many times
PROBE_TIMEOUT_S = 120.0
CONNECT_TIMEOUT_S = 5.0


@dataclass
class ExecutorConfig:
    """`kind`: local or ray; `address`: None starts a local Ray instance on this machine's cores, "auto"
    or HOST:PORT joins a running cluster."""

    kind: str = "local"
    address: str | None = None


def import_ray() -> Any:
    """Ray, or one InputError saying what to install (Ray is the optional extra `cluster`)."""
    try:
        import ray
    except ImportError:
        raise InputError(None, f"--executor ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def worker_env() -> dict[str, str]:
    """Environment of every Ray worker: the process settings (docs/design.md, "Process settings"), which
    must be in place before a worker imports torch, and this process's torch thread count."""
    return apply_process_settings() | {"OMP_NUM_THREADS": str(torch.get_num_threads())}


def check_reachable(address: str) -> None:
    """One error at once when nothing listens at HOST:PORT (Ray itself keeps retrying for minutes)."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or "://" in address:
        return  # "auto", or a scheme Ray resolves itself
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as e:
        raise InputError(None, f"--ray-address {address}: no Ray cluster answers there ({e})") from None


def start_ray(address: str | None) -> Any:
    """Start (or join) Ray quietly, with no dashboard; returns the module."""
    ray = import_ray()
    options: dict[str, Any] = {
        "include_dashboard": False,
        "logging_level": "ERROR",
        "log_to_driver": False,  # each job's output is in its own log file
        "runtime_env": {"env_vars": worker_env()},
    }
    if address is None:
        ray.init(num_cpus=available_cores(), **options)
    else:
        check_reachable(address)
        try:
            ray.init(address=address, **options)
        except ConnectionError as e:
            raise InputError(None, f"--ray-address {address}: no Ray cluster there ({e})") from None
    return ray


@contextmanager
def ray_session(address: str | None) -> Iterator[Any]:
    """Ray for the length of the block: an instance already started in this process is used as it is;
    one started here is shut down at the end."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    start_ray(address)
    try:
        yield ray
    finally:
        ray.shutdown()


def _probe(paths: list[str], probe_file: str, token: str) -> list[str]:
    """Run on a worker: the paths it cannot see, and whether the probe file holds the driver's token
    (the same folder, not a local folder of the same name)."""
    missing = [p for p in paths if not os.path.exists(p)]
    try:
        same = Path(probe_file).read_text() == token
    except OSError:
        same = False
    return missing + ([] if same else [str(Path(probe_file).parent)])


def check_paths_visible(ray: Any, out: Path, paths: list[Path]) -> None:
    """Fail early, with one error naming the node and the path, when any node's workers cannot see `out`
    (the very folder: a probe file written here is read there) or one of `paths`."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    out.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    probe_file = out / f".ray-probe-{token[:12]}"
    atomic_write_text(probe_file, token)
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0]
        probe = ray.remote(_probe)
        refs = {
            probe.options(
                num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)
            ).remote([str(p.resolve()) for p in paths], str(probe_file.resolve()), token): n
            for n in nodes
        }
        for ref, node in refs.items():
            unseen = ray.get(ref, timeout=PROBE_TIMEOUT_S)
            if unseen:
                raise InputError(
                    unseen[0],
                    f"not visible from the Ray workers on {node.get('NodeManagerHostname', node['NodeID'])}: "
                    "data and outputs must be on a path every node sees (a shared file system)",
                )
    finally:
        probe_file.unlink(missing_ok=True)


def _ray_task(job: Job, token: str, threads: int) -> dict[str, Any]:
    """A job on a Ray worker, with the driver's torch thread count (Ray sets OMP_NUM_THREADS to the task's
    CPUs otherwise), resuming its run when a previous attempt left a checkpoint."""
    torch.set_num_threads(threads)
    try:
        return execute_logged(job, token, resume=True)
    except Exception as e:
        raise JobFailed(error_line(e)) from None


def _started(job: Job, token: str) -> bool:
    try:
        return f"batch {token}" in (job.folder / LOG_FILE).read_text()
    except OSError:
        return False


class _Progress:
    """Runs done / running / failed on one tqdm line."""

    def __init__(self, total: int, what: str):
        self.bar = tqdm(total=total, unit=what, desc=f"{what}s", dynamic_ncols=True)
        self.failed = 0

    def update(self, finished: list[Outcome], running: int) -> None:
        self.failed += sum(o.error is not None for o in finished)
        done = self.bar.n + len(finished) - self.failed
        self.bar.set_postfix(done=done, running=running, failed=self.failed, refresh=not finished)
        self.bar.update(len(finished))

    def close(self) -> None:
        self.bar.close()


def run_jobs(
    jobs: list[Job], executor: ExecutorConfig, out: Path, paths: list[Path], what: str = "run"
) -> list[Outcome]:
    """Every job's outcome, in order. `out`: the output folder, `paths`: inputs the workers read."""
    token = uuid.uuid4().hex[:12]
    if executor.kind == "local":
        return _run_local(jobs, token, what)
    with ray_session(executor.address) as ray:
        check_paths_visible(ray, out, paths)
        return _run_ray(ray, jobs, token, what)


def _run_local(jobs: list[Job], token: str, what: str) -> list[Outcome]:
    progress, outcomes = _Progress(len(jobs), what), []
    for job in jobs:
        progress.update([], running=1)
        outcome = Outcome(job.key, job.folder / LOG_FILE)
        try:
            outcome.result = execute_logged(job, token, resume=True)
        except TrainingStopped:
            progress.close()
            raise  # Ctrl-C or SIGTERM stops the batch, not only this job
        except Exception as e:
            outcome.error = error_line(e)
        outcomes.append(outcome)
        progress.update([outcome], running=0)
    progress.close()
    return outcomes


def _resources(ray: Any, job: Job, threads: int) -> dict[str, float]:
    nodes = [n["Resources"] for n in ray.nodes() if n.get("Alive")]
    largest = max((r.get("CPU", 0) for r in nodes), default=1)
    has_gpu = any(r.get("GPU", 0) > 0 for r in nodes)
    wants_gpu = job.device.startswith("cuda") or (job.device == "auto" and has_gpu)
    return {"num_cpus": max(1, min(threads, int(largest))), "num_gpus": 1 if wants_gpu else 0}


def _run_ray(ray: Any, jobs: list[Job], token: str, what: str) -> list[Outcome]:
    threads = torch.get_num_threads()
    task = ray.remote(_ray_task)
    refs = {
        task.options(name=job.key, max_retries=MAX_RETRIES, **_resources(ray, job, threads)).remote(
            job, token, threads
        ): job
        for job in jobs
    }
    outcomes: dict[str, Outcome] = {}
    progress, pending = _Progress(len(jobs), what), list(refs)
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=1.0)
            finished = []
            for ref in ready:
                job = refs[ref]
                outcome = outcomes[job.key] = Outcome(job.key, job.folder / LOG_FILE)
                try:
                    outcome.result = ray.get(ref)
                except ray.exceptions.RayTaskError as e:  # the job raised: its own error
                    outcome.error = error_line(e.cause if e.cause is not None else e)
                except ray.exceptions.RayError as e:  # its worker died more often than it is retried
                    outcome.error = error_line(e)
                finished.append(outcome)
            progress.update(finished, running=sum(_started(refs[r], token) for r in pending))
    except KeyboardInterrupt:
        for ref in pending:  # a training task stops at its next step with a checkpoint
            ray.cancel(ref)
        raise
    finally:
        progress.close()
    return [outcomes[job.key] for job in jobs]
