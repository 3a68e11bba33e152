"""`hdrplenoxels batch CAPTURES OUT`: every subfolder of CAPTURES is one capture, processed with COLMAP
when it is a folder of photos, then trained, its test views rendered and scored (the `eval` protocol).
OUT/<capture>/ holds data/ (processed photos), run/, renders/, eval.json, result.json and task.log;
OUT/summary.md and OUT/summary.json cover every capture. A capture whose result.json was written with
the same source and settings is skipped on a re-run."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdrplenoxels.cluster.executors import ExecutorConfig, run_jobs
from hdrplenoxels.cluster.jobs import LOG_FILE, Outcome
from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data import scene_layout
from hdrplenoxels.eval.evaluate import METRIC_KEYS, evaluate
from hdrplenoxels.eval.renders import view_jobs, write_renders
from hdrplenoxels.experiments.report import METRIC_COLUMNS, table
from hdrplenoxels.process import process_photos
from hdrplenoxels.process.photos import find_photos
from hdrplenoxels.process.sfm import SfmConfig
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.runs import RunSpec, train_spec

RESULT_FILE = "result.json"
SUMMARY = "summary"
COLUMNS = (*METRIC_COLUMNS, ("num_test_views", "test views", 0), ("seconds", "seconds", 0))


@dataclass
class CaptureJob:
    """One capture of a batch, from its photos or dataset to its scores."""

    key: str
    source: Path  # the capture folder (absolute: workers have another working directory)
    out: Path  # OUT/<capture>
    config: TrainConfig
    photos: bool  # a folder of photos, processed into OUT/<capture>/data first
    lpips: bool = True
    backend: str = "warp"

    @property
    def folder(self) -> Path:
        return self.out

    @property
    def device(self) -> str:
        return self.config.device

    @property
    def spec(self) -> RunSpec:
        return RunSpec(self.out / "data" if self.photos else self.source, self.out / "run", self.config)

    def settings(self) -> dict[str, Any]:
        """What the result depends on: a re-run with other settings does the capture again."""
        return {
            "source": str(self.source),
            "config": self.config.to_dict(),
            "lpips": self.lpips,
            "backend": self.backend,
        }

    def finished(self) -> bool:
        try:
            saved = json.loads((self.out / RESULT_FILE).read_text())
        except (OSError, ValueError):
            return False
        return saved.get("settings") == json.loads(json.dumps(self.settings()))

    def execute(self, resume: bool) -> dict[str, Any]:
        t0 = time.perf_counter()
        spec = self.spec
        if self.photos and scene_layout(spec.data) is None:
            process_photos(self.source, spec.data, SfmConfig(), overwrite=spec.data.exists(), log=print)
        model, scene = train_spec(spec, resume=resume)
        write_renders(model, view_jobs(model, "test"), self.out / "renders", self.backend)
        scored = evaluate(model, scene, self.backend, lpips=self.lpips)
        atomic_write_text(self.out / "eval.json", json.dumps(scored, indent=2))
        result = {
            "capture": self.key,
            "settings": self.settings(),
            "processed": self.photos,
            "data": str(spec.data),
            "run": str(spec.run),
            "protocol": scored["protocol"],
            "num_test_views": scored["num_test_views"],
            **{k: scored[k] for k in METRIC_KEYS if k in scored},
            "seconds": time.perf_counter() - t0,
        }
        atomic_write_text(self.out / RESULT_FILE, json.dumps(result, indent=1))
        return result


def find_captures(captures: Path, out: Path) -> list[tuple[str, Path, bool]]:
    """(name, folder, is a folder of photos) for every capture; one InputError for a CAPTURES folder that
    is not a folder of captures, or a subfolder that is neither a dataset nor a folder of photos."""
    if not captures.is_dir():
        raise InputError(captures, "no such folder" if not captures.exists() else "is not a folder")
    if scene_layout(captures) is not None:
        raise InputError(
            captures, "is itself a dataset; CAPTURES is a folder holding one subfolder per capture"
        )
    if out.resolve().is_relative_to(captures.resolve()):
        raise InputError(out, "is inside CAPTURES: a re-run would take it for a capture")
    found = []
    for folder in sorted(p for p in captures.iterdir() if p.is_dir() and not p.name.startswith(".")):
        photos = scene_layout(folder) is None
        if photos:
            find_photos(folder)  # an InputError naming the folder when it holds no photos either
        found.append((folder.name, folder.resolve(), photos))
    if not found:
        raise InputError(
            captures, "holds no capture folders (each subfolder is one capture: a dataset or photos)"
        )
    return found


def capture_jobs(
    captures: Path, out: Path, config: TrainConfig, lpips: bool = True, backend: str = "warp"
) -> list[CaptureJob]:
    out = out.resolve()
    return [
        CaptureJob(name, folder, out / name, config, photos, lpips, backend)
        for name, folder, photos in find_captures(captures, out)
    ]


def run_batch(jobs: list[CaptureJob], out: Path, executor: ExecutorConfig) -> tuple[dict, list[Outcome]]:
    """Run the unfinished captures, then write the summary over all of them. Returns the summary and the
    outcomes of the captures run now."""
    out = out.resolve()
    todo = [job for job in jobs if not job.finished()]
    outcomes = run_jobs(todo, executor, out, [job.source for job in todo], what="capture") if todo else []
    errors = {o.key: o for o in outcomes if o.error is not None}
    summary: dict[str, Any] = {"captures": {}, "failed": {}}
    for job in jobs:
        if job.key in errors:
            summary["failed"][job.key] = {"error": errors[job.key].error, "log": str(job.out / LOG_FILE)}
        else:
            summary["captures"][job.key] = json.loads((job.out / RESULT_FILE).read_text())
    protocols = {r["protocol"] for r in summary["captures"].values()}
    summary["protocol"] = " / ".join(sorted(protocols))
    write_summary(out, summary)
    return summary, outcomes


def write_summary(out: Path, summary: dict) -> None:
    rows = [(name, r) for name, r in summary["captures"].items()]
    md = ["# Batch summary", "", f"Protocol: {summary['protocol']}." if summary["protocol"] else "", ""]
    md += [table(rows, COLUMNS, first="capture"), ""] if rows else []
    if summary["failed"]:
        md += ["## Failed", ""]
        md += [f"- {name}: {f['error']} (log: {f['log']})" for name, f in summary["failed"].items()]
    atomic_write_text(out / f"{SUMMARY}.json", json.dumps(summary, indent=1))
    atomic_write_text(out / f"{SUMMARY}.md", "\n".join(md).rstrip() + "\n")
