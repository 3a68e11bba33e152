"""An experiment through an executor. `local` is the experiment's own `run` (it trains as it goes). `ray`
first renders the truth and captures on this machine while listing the runs (the experiment's `plan`,
built from the same method tables as `run`), trains every unfinished run as a Ray task, then calls
`run`, which finds every run finished and only scores and writes the report."""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from hdrplenoxels.cluster.executors import ExecutorConfig, run_jobs
from hdrplenoxels.cluster.jobs import Outcome, TrainJob
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.experiments import EXPERIMENTS, ExperimentSettings
from hdrplenoxels.train.runs import RunSpec


class RunsFailed(Exception):
    """Some jobs failed (each with its one-line reason and its log); the others finished."""

    def __init__(self, failed: list[Outcome]):
        self.failed = failed
        super().__init__(f"{len(failed)} run(s) failed")


def plan_of(name: str) -> Callable[[Path, ExperimentSettings], list[RunSpec]] | None:
    """The `plan` beside experiment `name`'s `run` (its module's), or None."""
    return getattr(sys.modules[EXPERIMENTS[name][1].__module__], "plan", None)


def train_jobs(out: Path, specs: list[RunSpec]) -> list[TrainJob]:
    """A job per unfinished run (a run planned twice, e.g. shared by two scenes' tables, once)."""
    unique = {spec.run.resolve(): spec for spec in specs}
    return [
        TrainJob(str(spec.run.relative_to(out) if spec.run.is_relative_to(out) else spec.run), spec)
        for spec in unique.values()
        if not spec.finished()
    ]


def run_experiment(name: str, out: Path, s: ExperimentSettings, executor: ExecutorConfig) -> Path:
    """The report of experiment `name`; RunsFailed (after every other run finished) when a run failed."""
    run = EXPERIMENTS[name][1]
    if executor.kind != "local":
        # Workers have another working directory: every path they are given is absolute.
        out = out.resolve()
        s = replace(s, data_root=s.data_root.resolve() if s.data_root else None)
        plan = plan_of(name)
        if plan is None:
            raise InputError(None, f"experiment {name} lists no runs (plan) yet: use --executor local")
        jobs = train_jobs(out, plan(out, s))
        if jobs:
            paths = [out] + ([s.data_root] if s.data_root else [])
            failed = [o for o in run_jobs(jobs, executor, out, paths) if o.error is not None]
            if failed:
                raise RunsFailed(failed)
    return run(out, s)
