"""`batch` (many captures), and the executor options it shares with `experiment`."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import click

from hdrplenoxels.cli.common import (
    backend_option,
    checked_overrides,
    choice_option,
    device_option,
    iters_option,
    preset_option,
    set_option,
)


def executor_options(f):
    """--executor and --ray-address."""
    f = click.option(
        "--ray-address",
        default=None,
        help="With --executor ray: 'auto' or HOST:PORT joins a running Ray cluster (data and outputs on a "
        "path every node sees); default: start a local Ray instance on this machine's cores.",
    )(f)
    return choice_option(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="local: runs one after another in this process; ray: each run a Ray task (retried from its "
        "checkpoint if its worker dies). Ray is the optional extra: pip install hdrplenoxels[cluster].",
    )(f)


def executor_config(executor: str, ray_address: str | None):
    from hdrplenoxels.cluster.executors import ExecutorConfig, import_ray

    if ray_address is not None and executor != "ray":
        raise click.UsageError("--ray-address needs --executor ray")
    if executor == "ray":
        import_ray()  # a missing extra is one error line before any work
    return ExecutorConfig(executor, ray_address)


def report_failures(failed) -> None:
    """Each failed run with its reason and log, then exit 1 (the others finished)."""
    for outcome in failed:
        click.echo(f"failed: {outcome.key}: {outcome.error} (log: {outcome.log})", err=True)
    sys.exit(1)


@click.command()
@click.argument("captures")
@click.argument("out", type=click.Path(file_okay=False))
@preset_option("Training schedule of every capture.")
@iters_option
@click.option(
    "--tonemap/--no-tonemap",
    default=None,
    help="Learn each image's tone (HDR-Plenoxels) or not (plain Plenoxels). Default: decided per capture "
    "from its photos, as `train` does (on where the camera's settings vary).",
)
@set_option
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS (the slowest metric on CPU).")
@backend_option
@device_option
@executor_options
def batch(captures, out, preset_name, iters, tonemap, overrides, no_lpips, backend, device, executor,
          ray_address):  # fmt: skip
    """Train, render and score every capture in CAPTURES (one subfolder each: a dataset, or a folder of
    photos that is `process`ed first) into OUT/<capture>; writes OUT/summary.md and OUT/summary.json.
    Finished captures are skipped on a re-run."""
    from hdrplenoxels.cluster.batch import capture_jobs, run_batch
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.train.config import apply_overrides, flag_settings, parse_overrides
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import TrainingStopped

    typed = checked_overrides(parse_overrides, overrides)
    flags = flag_settings({"backend": backend, "device": device, "iters": iters, "tonemap": tonemap})
    config = apply_overrides(apply_overrides(preset(preset_name), flags), typed)
    if executor == "local":
        pick_device(device)  # a missing GPU is refused before any capture starts
    settings = executor_config(executor, ray_address)
    jobs = capture_jobs(Path(captures), Path(out), config, lpips=not no_lpips, backend=backend)
    skipped = sum(job.finished() for job in jobs)
    if skipped:
        click.echo(f"{skipped} of {len(jobs)} captures already finished with these settings: skipped")
    try:
        summary, outcomes = run_batch(jobs, Path(out), settings)
    except TrainingStopped as stopped:
        click.echo(
            f"stopped by {stopped.signal_name}; checkpoint written: {stopped.checkpoint}\n"
            "continue with the same command: finished captures are skipped, this one resumes",
            err=True,
        )
        sys.exit(128 + getattr(signal, stopped.signal_name))
    click.echo(f"summary: {Path(out) / 'summary.md'} ({len(summary['captures'])} of {len(jobs)} scored)")
    failed = [o for o in outcomes if o.error is not None]
    if failed:
        report_failures(failed)
