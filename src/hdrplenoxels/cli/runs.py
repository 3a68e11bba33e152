"""Commands on a trained run: `render`, `eval`, `export`, and `import-svox2` (which makes one)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import click

from hdrplenoxels.cli.common import (
    TONE_HELP,
    backend_option,
    choice_option,
    device_option,
    existing_path,
    load_model,
    load_tones,
    old_flag,
    parse_resolution,
    parse_tone,
    renamed_flag,
    scene_mode_option,
)
from hdrplenoxels.core.errors import InputError

# `--tone`'s words each command takes (common.TONE_WORDS); eval's are `evaluate.TONES`'s names (a test
# holds them equal), listed here so that starting the command line does not import the evaluation stack.
RENDER_TONES = ("own", "auto", "mean", "view N")  # cc needs the photo: only `eval` has one
EVAL_TONES = ("own", "auto", "mean", "cc")  # one tone for every view is render's


@click.command()
@click.argument("run")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Output folder (default: RUN/renders).",
)
@choice_option("--views", choices=["test", "train", "all"], default="test")
@click.option(
    "--pose",
    "pose_file",
    default=None,
    help="Render these 4x4 camera-to-world poses (.npy, .json or text; one or many) instead of views.",
)
@choice_option(
    "--pose-convention",
    choices=["opengl", "opencv"],
    default="opengl",  # data.poses.DEFAULT_POSE_CONVENTION, unimported so that --help stays quick
    help="Axes of --pose: OpenGL (nerfstudio/Blender transforms.json, the default, as the Python API's "
    "render_pose) or OpenCV (COLMAP).",
)
@click.option(
    "--ev",
    type=float,
    default=None,
    help="Exposure in stops relative to the mean of all views' white balance (needs --tonemap runs).",
)
@click.option("--wb", type=float, nargs=3, default=None, help="Per-channel gains relative to that mean.")
@click.option(
    "--tone",
    default=None,
    help=f"The tone the PNGs are seen through: own, auto, mean or view N. {TONE_HELP} A --pose has no "
    "own tone: it takes the reference image's. --ev and --wb are relative to auto or mean.",
)
@old_flag("--camera", "--tone")
@click.option(
    "--crf-from", type=int, default=None, help="Use this view's response curve (default: reference)."
)
@click.option(
    "--crf-run",
    default=None,
    help="Take --crf-from's curve from another trained run, or from a tone_params.json (a run's "
    "exported tones, edited or not).",
)
@click.option("--video", "video_file", default=None, help="Write an H.264 MP4 of a camera path instead.")
@click.option(
    "--camera-path",
    "camera_path_file",
    default=None,
    help="nerfstudio camera_path.json for --video (also as saved by `view`), with per-frame EV and WB.",
)
@choice_option(
    "--path",
    "path_kind",
    choices=["orbit", "spiral", "interp"],
    default="orbit",
    help="Generated path for --video without --camera-path (spiral: forward-facing; interp: through the "
    "training cameras).",
)
@click.option("--frames", type=click.IntRange(min=1), default=120, show_default=True)
@click.option("--fps", type=click.FloatRange(min=1, max=240), default=30.0, show_default=True)
@click.option("--resolution", default=None, help="WxH of a generated path (default: the first test view's).")
@click.option(
    "--ev-from", type=float, default=0.0, show_default=True, help="Exposure ramp of a generated path."
)
@click.option("--ev-to", type=float, default=None, help="End of the ramp (default: --ev-from).")
@click.option("--exr-frames", default=None, help="Also write each frame's linear radiance as EXR here.")
@click.option("--save-camera-path", default=None, help="Write the generated path as camera_path.json.")
@click.option(
    "--embedding-from",
    type=int,
    default=None,
    help="NeRF-A runs: render every view with this image's appearance embedding (default: each view's "
    "own; a --pose, that of the image whose tone maps it).",
)
@click.option(
    "--embedding-to", type=int, default=None, help="Blend --embedding-from's embedding towards this image's."
)
@click.option(
    "--embedding-weight",
    type=click.FloatRange(0.0, 1.0),
    default=0.5,
    show_default=True,
    help="Interpolation weight of --embedding-to (0: --embedding-from's, 1: --embedding-to's).",
)
@backend_option
@device_option
def render(
    run,
    out_dir,
    views,
    pose_file,
    pose_convention,
    ev,
    wb,
    tone,
    old_tone,
    crf_from,
    crf_run,
    video_file,
    camera_path_file,
    path_kind,
    frames,
    fps,
    resolution,
    ev_from,
    ev_to,
    exr_frames,
    save_camera_path,
    embedding_from,
    embedding_to,
    embedding_weight,
    backend,
    device,
):
    """Render RUN's views (or --pose) to float EXR (linear radiance) and PNG, or a camera path to MP4.

    The PNG shows each view through its own learned tone (a --pose through the reference image's);
    without tone mapping it is the radiance clipped to [0, 1]. A video shows every frame through the
    learned tones' mean white balance, at the frame's EV and gains.
    """
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.data.poses import read_poses
    from hdrplenoxels.eval.renders import ChosenTone, pose_jobs, view_jobs, write_renders

    model = load_model(run, str(pick_device(device)))
    chosen = _tone_choice(renamed_flag("--camera", "--tone", old_tone, tone), model, Path(run))
    if video_file is not None:
        ramp = (ev_from, ev_from if ev_to is None else ev_to)
        request = VideoRequest(
            Path(video_file), camera_path_file, path_kind, frames, fps, resolution, ramp, chosen
        )
        _render_video(model, request, exr_frames, save_camera_path, backend)
        return
    out = Path(out_dir) if out_dir else Path(run if Path(run).is_dir() else Path(run).parent) / "renders"
    if pose_file:
        jobs = pose_jobs(model, read_poses(existing_path(pose_file, "pose file"), pose_convention))
    else:
        jobs = view_jobs(model, views)
    if isinstance(chosen, int):
        if ev is not None or wb is not None or crf_from is not None or crf_run is not None:
            raise click.UsageError("--tone view N is that view's whole tone: drop --ev/--wb/--crf-*")
        for job in jobs:
            job.tone_view, job.name = chosen, f"{job.name}_view{chosen}"
    controlled = ev is not None or wb is not None or crf_from is not None or crf_run is not None
    if controlled and model.tonemapper is None:
        raise InputError(Path(run), "--ev/--wb/--crf-from need a run trained with --tonemap")
    controlled = controlled or chosen in ("auto", "mean")
    source = load_tones(crf_run) if crf_run else model.tonemapper
    n_views = len(source.log_wb) if source is not None else len(model.cameras)
    if crf_from is not None and not 0 <= crf_from < n_views:
        raise InputError(Path(crf_run or run), f"--crf-from {crf_from}: the run has views 0..{n_views - 1}")
    gains = tuple(wb or (1.0, 1.0, 1.0))
    user_tone = ChosenTone(ev or 0.0, gains, crf_from, source, chosen == "auto") if controlled else None
    write_renders(
        model,
        jobs,
        out,
        backend,
        user_tone,
        _appearance(model, Path(run), embedding_from, embedding_to, embedding_weight),
    )
    click.echo(f"wrote {len(jobs)} views (PNG + EXR) to {out}")


def _tone_choice(tone: str | None, model, run: Path) -> str | int | None:
    """render's --tone (`parse_tone`): "auto", "mean", a view's index, or None (each view's own), checked
    against the model."""
    chosen = parse_tone(tone, "render", RENDER_TONES)
    if chosen is None:
        return None
    _check_tone(model, run, "view" if isinstance(chosen, int) else chosen)
    if isinstance(chosen, int) and not 0 <= chosen < len(model.cameras):
        raise InputError(run, f"--tone view {chosen}: the run has views 0..{len(model.cameras) - 1}")
    return chosen


def _check_tone(model, run: Path, tone: str) -> None:
    """A tone other than each view's own needs learned tones (`--tonemap`), and `auto` the tone
    controller fitted at the end of training."""
    if model.tonemapper is None:
        raise InputError(run, f"--tone {tone} needs a run trained with --tonemap")
    if tone == "auto" and model.controller is None:
        raise InputError(
            run, "has no tone controller (a checkpoint, or a run from before them): use --tone mean"
        )


def _appearance(model, run: Path, first: int | None, second: int | None, weight: float):
    """The NeRF-A appearance the --embedding-* flags ask for (None: each view's own)."""
    from hdrplenoxels.render.nerf import Appearance

    if first is None and second is None:
        return None
    codes = getattr(model.field, "codes", None)
    if codes is None:
        raise InputError(
            run, "--embedding-from/--embedding-to need a run trained with --appearance-embedding"
        )
    if first is None:
        raise click.UsageError("--embedding-to needs --embedding-from")
    for flag, i in (("--embedding-from", first), ("--embedding-to", second)):
        if i is not None and not 0 <= i < len(model.cameras):
            raise InputError(run, f"{flag} {i}: the run has images 0..{len(model.cameras) - 1}")
    return Appearance(first, second, weight if second is not None else 0.0)


@click.command("eval")
@click.argument("run")
@click.option("--data", default=None, help="Dataset path (default: the one the model was trained on).")
@click.option(
    "--json", "json_path", default=None, help="Also write the metrics (means and per view) as JSON."
)
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS (the slowest metric on CPU).")
@click.option(
    "--tone",
    default=None,
    help=f"The tone each test view is seen through: own (the paper's protocol), auto (for views no photo "
    f"trained, --holdout full), mean or cc. {TONE_HELP}",
)
@old_flag("--camera", "--tone", EVAL_TONES)
@backend_option
@device_option
def eval_cmd(run, data, json_path, no_lpips, tone, old_tone, backend, device):
    """Score RUN on its test views: PSNR, SSIM, LPIPS-VGG and LPIPS-Alex, as a table."""
    from hdrplenoxels.core.atomic import atomic_write_text
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.eval.evaluate import evaluate, format_table, run_downscale

    model = load_model(run, str(pick_device(device)))
    scene = load_scene(existing_path(data or model.data_path, "dataset of the run"), run_downscale(model))
    tone = parse_tone(renamed_flag("--camera", "--tone", old_tone, tone), "eval", EVAL_TONES) or "own"
    if tone != "own":
        _check_tone(model, Path(run), tone)
    result = evaluate(model, scene, backend, lpips=not no_lpips, tone=tone)
    click.echo(format_table(result))
    if json_path:
        atomic_write_text(json_path, json.dumps(result, indent=2))


@click.command()
@click.argument("run")
@click.argument("output")
@choice_option(
    "--format",
    "fmt",
    choices=["svox2"],
    default="svox2",
    help="svox2: the Plenoxels ckpt.npz layout (links, density_data, sh_data, radius, center).",
)
def export(run, output, fmt):
    """Export RUN's grid to another format (a bounding-box grid in the dataset's own frame)."""
    from hdrplenoxels.grid.io import export_svox2
    from hdrplenoxels.grid.sparse_grid import SparseGrid, grid_in_data_frame

    model = load_model(run)
    if not isinstance(model.field, SparseGrid):
        raise InputError(Path(run), "is a NeRF run; only voxel grids export to the svox2 format")
    grid = model.grid if model.geometry.mode == "ndc" else grid_in_data_frame(model.grid, model.geometry)
    export_svox2(Path(output), grid)
    click.echo(f"wrote {fmt} checkpoint {output}")
    if grid.levels > 1:
        click.echo(
            f"note: only the finest of the grid's {grid.levels} nested boxes is exported: svox2 has one box "
            '(docs/design.md, "Cascade")',
            err=True,
        )
    if model.background is not None:
        click.echo(
            "note: the MSI background is not exported: svox2's background places and samples its layers "
            'differently, so no array of its layout renders the same (docs/design.md, "Background")',
            err=True,
        )


@click.command("import-svox2")
@click.argument("ckpt")
@click.argument("data")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@scene_mode_option
def import_svox2_cmd(ckpt, data, out_dir, scene_mode):
    """Make a run from an existing Plenoxels (svox2) CKPT and the DATA it was trained on."""
    from hdrplenoxels.train.model import MODEL_FILE
    from hdrplenoxels.train.svox2_import import model_from_svox2

    model = model_from_svox2(existing_path(ckpt, "checkpoint"), existing_path(data, "data path"), scene_mode)
    model.save(Path(out_dir) / MODEL_FILE)
    click.echo(f"wrote {Path(out_dir) / MODEL_FILE}")


@dataclass
class VideoRequest:
    out: Path
    camera_path: str | None
    kind: str
    frames: int
    fps: float
    resolution: str | None
    ev_ramp: tuple[float, float]
    tone: str | int | None = None  # `--tone`: auto, mean (also None) or a view's index


def _render_video(model, request: VideoRequest, exr_dir: str | None, save_path: str | None, backend) -> None:
    """`render --video`: a camera_path.json, or a generated path with an exposure ramp."""
    from hdrplenoxels.data.camera_path import read_camera_path, write_camera_path
    from hdrplenoxels.eval.video import camera_path_of, generated_frames, path_frames, ramp, render_video

    fps = request.fps
    if request.camera_path is not None:
        camera_path = read_camera_path(existing_path(request.camera_path, "camera path"))
        video_frames, size = path_frames(model, camera_path), (camera_path.width, camera_path.height)
        fps = camera_path.fps
    else:
        view = model.test_ids[0] if model.test_ids else 0
        w, h = model.cameras.size(view)
        size = parse_resolution(request.resolution) or (w - w % 2, h - h % 2)
        evs = ramp(*request.ev_ramp, request.frames)
        video_frames = generated_frames(model, request.kind, request.frames, size, evs)
        if save_path:
            write_camera_path(Path(save_path), camera_path_of(model, video_frames, size, fps))
    tone, crf_from = None, None
    if request.tone == "auto":
        from hdrplenoxels.tonemap.controller import ExposureTracker

        tone = ExposureTracker(model.controller, fps)
    elif isinstance(request.tone, int):
        crf_from = request.tone
        fixed = model.tonemapper.linear_log_wb()[crf_from]

        def tone(linear):  # view N's tone for every frame
            return fixed

    exr = Path(exr_dir) if exr_dir else None
    render_video(model, video_frames, size, request.out, fps, backend, exr, tone=tone, crf_from=crf_from)
    click.echo(f"wrote {len(video_frames)} frames at {size[0]}x{size[1]}, {fps:g} fps: {request.out}")
