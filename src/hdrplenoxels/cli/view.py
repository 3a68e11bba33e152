"""`view`: the interactive HDR viewer in the browser."""

from __future__ import annotations

import ipaddress
import time
from pathlib import Path

import click

from hdrplenoxels.cli.common import backend_option, device_option, load_model


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


@click.command()
@click.argument("run")
@click.option("--port", type=click.IntRange(min=0, max=65535), default=8765, show_default=True)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to listen on. Anything but loopback lets other machines on the network see the run.",
)
@backend_option
@device_option
def view(run, port, host, backend, device):
    """Fly through RUN in the browser: exposure, white balance, response curve, display modes (tone-mapped,
    linear HDR, false colour with a histogram), training cameras, saved views and camera paths."""
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.viewer.server import Viewer, ViewerConfig

    model = load_model(run, str(pick_device(device)))
    if not _is_loopback(host):
        click.echo(f"warning: listening on {host}: anyone who can reach it can see this run", err=True)
    folder = Path(run) if Path(run).is_dir() else Path(run).parent
    viewer = Viewer(model, folder, ViewerConfig(host=host, port=port, backend=backend))
    bound = viewer.start()
    click.echo(f"viewer: http://{'localhost' if _is_loopback(host) else host}:{bound}  (Ctrl-C stops it)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
