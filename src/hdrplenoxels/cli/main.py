"""The `hdrplenoxels` command: process, train, render, view, eval, export, import-svox2, synth, experiment,
demo, batch.

Bad input ends with one line `error: <file>: <problem>` on stderr and exit code 2, never a traceback; a
file the system refuses to write (disk full, read-only folder, no permission) with one such line and exit
code 74.
"""

from __future__ import annotations

import sys

import click

from hdrplenoxels.cli.batch import batch
from hdrplenoxels.cli.common import EXIT_INPUT_ERROR, EXIT_WRITE_ERROR
from hdrplenoxels.cli.experiments import demo, experiment, synth
from hdrplenoxels.cli.process import process
from hdrplenoxels.cli.runs import eval_cmd, export, import_svox2_cmd, render
from hdrplenoxels.cli.train import train
from hdrplenoxels.cli.view import view
from hdrplenoxels.core.errors import InputError, WriteError

__all__ = ["EXIT_INPUT_ERROR", "EXIT_WRITE_ERROR", "cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="hdrplenoxels", prog_name="hdrplenoxels")
def cli() -> None:
    """HDR radiance fields (Plenoxels sparse voxels + learned tone mapping) from photos."""


for command in (
    process,
    train,
    render,
    view,
    eval_cmd,
    export,
    import_svox2_cmd,
    synth,
    experiment,
    demo,
    batch,
):
    cli.add_command(command)


def main(argv: list[str] | None = None) -> None:
    try:
        cli.main(args=argv, prog_name="hdrplenoxels", standalone_mode=False)
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(EXIT_INPUT_ERROR)
    except OSError as e:  # WriteError, or a file system failure outside an atomic write (a log append)
        click.echo(f"error: {_os_error_line(e)}", err=True)
        sys.exit(EXIT_WRITE_ERROR)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)


def _os_error_line(e: OSError) -> str:
    if isinstance(e, WriteError):
        return str(e)
    reason = e.strerror or str(e) or type(e).__name__
    return f"{e.filename}: {reason}" if e.filename is not None else reason
