"""The `hdrplenoxels` command: process, train, render, eval, export, import-svox2, synth, experiment, demo.

Bad input ends with one line `error: <file>: <problem>` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click
import numpy as np
from click.core import ParameterSource

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.train.config import PRESETS, preset

EXIT_INPUT_ERROR = 2


def _existing_path(value: str, what: str) -> Path:
    p = Path(value)
    if not p.exists():
        raise InputError(p, f"{what} does not exist")
    return p


def _require_tonemap(cfg, *flags: str) -> None:
    """Tone-mapping options given without the tone mapper are refused (exit 2), not silently ignored."""
    if not cfg.tonemap.enabled:
        verb = "needs" if len(flags) == 1 else "need"
        raise click.UsageError(f"{' and '.join(flags)} {verb} the tone mapper (--tonemap)")


backend_option = click.option(
    "--backend",
    type=click.Choice(["warp", "torch"]),
    default="warp",
    show_default=True,
    help="Renderer: the Warp kernel, or the (slow) PyTorch reference.",
)
device_option = click.option(
    "--device", default="auto", show_default=True, help="'auto' picks CUDA when available, else CPU."
)
scene_mode_option = click.option(
    "--scene-mode",
    type=click.Choice(["auto", "bbox", "ndc"]),
    default="auto",
    show_default=True,
    help="Grid in a bounding box (360 scenes) or in NDC (forward-facing); auto detects.",
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """HDR radiance fields (Plenoxels sparse voxels + learned tone mapping) from photos."""


@cli.command()
@click.argument("data")
@click.option(
    "--preset",
    "preset_name",
    type=click.Choice(sorted(PRESETS)),
    default="fast",
    show_default=True,
    help="Named schedule: the paper's synthetic/real schedules, or a small fast one for CPU.",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Run folder: checkpoints, logs, config.json and the final model.npz.",
)
@click.option(
    "--iters", type=click.IntRange(min=1), default=None, help="Override the preset's number of iterations."
)
@click.option(
    "--batch-size", type=click.IntRange(min=1), default=None, help="Override the preset's rays per batch."
)
@backend_option
@device_option
@scene_mode_option
@click.option(
    "--holdout",
    type=click.Choice(["right-half", "full"]),
    default="right-half",
    show_default=True,
    help="right-half: test views' left halves train, right halves are scored (HDR-Plenoxels).",
)
@click.option(
    "--tonemap/--no-tonemap",
    default=None,
    help="Learn the per-image camera model (HDR-Plenoxels) or not (plain Plenoxels). "
    "Default: the preset's (on for the paper presets).",
)
@click.option(
    "--known-exposure",
    "exposure_file",
    default=None,
    help="JSON of each view's exposure in EV ({name: EV}, or a synth camera_truth.json). Training "
    "stays self-calibrated; afterwards the exponent of its ambiguity is fitted to these EVs, so the EXR "
    "is linear radiance and learned EVs and --ev are true stops.",
)
@click.option(
    "--exposure-init",
    type=click.Choice(["data", "metadata"]),
    default="data",
    show_default=True,
    help="Start each view's exposure from image statistics, or from the dataset's metadata (EXIF "
    "recorded by `process`, HDR-NeRF exposure times). Only a starting value: it is still learned.",
)
@click.option(
    "--response-prior",
    type=click.FloatRange(min=0.0),
    default=None,
    help="Weight of the response curve's log-log smoothness prior (default 0: off). Brackets of few "
    "exposures far apart leave the response between them open: see --sparse-bracket.",
)
@click.option(
    "--saturation-weighting",
    is_flag=True,
    default=None,
    help="Down-weight near-black and near-white pixels in the loss (default: off).",
)
@click.option(
    "--sparse-bracket",
    is_flag=True,
    help="The images are few exposures far apart (e.g. -3 and +3 EV only): turns on the response prior "
    "(at 1e-2 unless --response-prior says) and saturation weighting, as the median-exposure experiment "
    "does.",
)
@click.option("--resume", is_flag=True, help="Continue from the newest checkpoint in --out.")
@click.option(
    "--overwrite", is_flag=True, help="Start over in an --out that already holds a run (deletes it)."
)
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(
    data,
    preset_name,
    out_dir,
    iters,
    batch_size,
    backend,
    device,
    scene_mode,
    holdout,
    tonemap,
    exposure_file,
    exposure_init,
    response_prior,
    saturation_weighting,
    sparse_bracket,
    resume,
    overwrite,
    quiet,
):
    """Train a radiance field on DATA (a transforms.json file or a folder holding one)."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.train.model import MODEL_FILE
    from hdrplenoxels.train.trainer import Trainer

    cfg = _resumed_config(Path(out_dir)) if resume else preset(preset_name)
    # Flags set the new run's config; a resumed run keeps its own unless a flag is given explicitly
    # (and a changed setting is then refused by the Trainer).
    ctx = click.get_current_context()
    for key, param, value in [
        ("preset", "preset_name", preset_name),
        ("scene_mode", "scene_mode", scene_mode),
        ("holdout", "holdout", holdout),
    ]:
        if not resume or ctx.get_parameter_source(param) is ParameterSource.COMMANDLINE:
            setattr(cfg, key, value)
    if iters is not None:
        cfg.optim.n_iters = iters
    if batch_size is not None:
        cfg.optim.batch_size = batch_size
    if tonemap is not None:
        cfg.tonemap.enabled = tonemap
    cfg.backend, cfg.device = backend, device
    scene = load_scene(_existing_path(data, "data path"))
    if exposure_file is not None:
        from hdrplenoxels.data.exposures import load_exposures

        _require_tonemap(cfg, "--known-exposure")
        cfg.tonemap.known_exposure = True
        scene.exposures = load_exposures(_existing_path(exposure_file, "exposure file"), scene.names)
    if exposure_init == "metadata":
        _require_tonemap(cfg, "--exposure-init metadata")
        cfg.tonemap.exposure_init_from_metadata = True
    tone_flags: list[tuple[str, dict]] = []  # later entries override earlier ones
    if sparse_bracket:
        from hdrplenoxels.tonemap.config import SPARSE_BRACKET

        tone_flags.append(("--sparse-bracket", SPARSE_BRACKET))
    if response_prior is not None:
        tone_flags.append(("--response-prior", {"lambda_crf_loglog": response_prior}))
    if saturation_weighting is not None:
        tone_flags.append(("--saturation-weighting", {"saturation_weighting": saturation_weighting}))
    if tone_flags:
        _require_tonemap(cfg, *(flag for flag, _ in tone_flags))
    for _, settings in tone_flags:
        for key, value in settings.items():
            setattr(cfg.tonemap, key, value)
    t0 = time.perf_counter()
    model = Trainer(scene, cfg, Path(out_dir), resume=resume, overwrite=overwrite).run(progress=not quiet)
    click.echo(
        f"trained {model.step} steps in {time.perf_counter() - t0:.1f} s; model: {Path(out_dir) / MODEL_FILE}"
    )


@cli.command()
@click.argument("photos")
@click.argument("out", type=click.Path(file_okay=False))
@click.option(
    "--camera-model",
    type=click.Choice(["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"]),
    default="SIMPLE_RADIAL",
    show_default=True,
    help="Lens model COLMAP fits (images are undistorted to pinhole afterwards).",
)
@click.option(
    "--matcher",
    type=click.Choice(["auto", "exhaustive", "sequential"]),
    default="auto",
    show_default=True,
    help="auto: exhaustive up to 100 photos, sequential (file-name order) beyond.",
)
@click.option("--no-equalise", is_flag=True, help="Extract features from the photos as taken.")
@click.option("--threads", type=int, default=-1, show_default=True, help="CPU threads (-1: all cores).")
@click.option("--overwrite", is_flag=True, help="Replace OUT once the new result is complete.")
def process(photos, out, camera_model, matcher, no_equalise, threads, overwrite):
    """Calibrate a folder of PHOTOS with COLMAP (pycolmap, CPU) into a dataset in OUT for `train`."""
    from hdrplenoxels.process import process_photos
    from hdrplenoxels.process.sfm import SfmConfig

    cfg = SfmConfig(camera_model=camera_model, matcher=matcher, equalise=not no_equalise, num_threads=threads)
    t0 = time.perf_counter()
    result = process_photos(photos, out, cfg, overwrite=overwrite, log=click.echo)
    click.echo(
        f"registered {len(result.registered)} of {result.n_photos} photos, {result.n_points} points, "
        f"reprojection error {result.reprojection_error_px:.2f} px, {time.perf_counter() - t0:.1f} s"
    )


def _resumed_config(run: Path):
    """The configuration a run was started with (a resumed run must keep it; see Trainer._resume)."""
    from hdrplenoxels.train.config import TrainConfig

    path = run / "config.json"
    if not path.exists():
        raise InputError(path, "--resume needs the run's config.json, which is missing")
    try:
        return TrainConfig.from_dict(json.loads(path.read_text()))
    except (ValueError, TypeError) as e:
        raise InputError(path, f"cannot read the run's configuration: {e}") from None


def _load_model(run: str, device: str = "cpu"):
    from hdrplenoxels.train.model import MODEL_FILE, Model

    path = _existing_path(run, "run folder or model file")
    if path.is_dir():
        path = path / MODEL_FILE
        if not path.exists():
            raise InputError(path, "no trained model here (train first, or pass the model .npz)")
    return Model.load(path, device=device)


def _load_cameras(source: str):
    """The learned cameras (a ToneMapper) of a run folder, a model file, or a camera_params.json."""
    from hdrplenoxels.tonemap.module import ToneMapper

    path = _existing_path(source, "run folder, model file or camera_params.json")
    if path.suffix == ".json":
        try:
            return ToneMapper.from_parameters_dict(json.loads(path.read_text()))
        except (ValueError, AttributeError) as e:  # JSONDecodeError is a ValueError
            raise InputError(path, str(e)) from None
    tonemapper = _load_model(source).tonemapper
    if tonemapper is None:
        raise InputError(path, "--crf-run needs a run trained with --tonemap")
    return tonemapper


def _read_poses(path: Path, convention: str) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses from .npy, .json or whitespace text; validated as rigid."""
    from hdrplenoxels.geometry.cameras import opengl_to_opencv

    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
            if arr.dtype.kind not in "iuf":
                raise InputError(path, f"poses must be real numbers, got an array of dtype {arr.dtype}")
        elif path.suffix == ".json":
            arr = json.loads(path.read_text())
            if not isinstance(arr, list):
                raise InputError(
                    path, f"expected a 4x4 matrix or a list of them (JSON arrays), got {type(arr).__name__}"
                )
        else:
            arr = np.loadtxt(path, dtype=np.float64)
        arr = np.asarray(arr, dtype=np.float64)
    except (ValueError, TypeError, OSError) as e:
        raise InputError(path, f"cannot read poses: {e}") from None
    if arr.size % 16 or arr.size == 0:
        raise InputError(path, f"expected one or more 4x4 matrices, got shape {arr.shape}")
    arr = arr.reshape(-1, 4, 4)
    if not np.isfinite(arr).all():
        raise InputError(path, "pose contains NaN or inf")
    rot = arr[:, :3, :3]
    if (
        np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() > 1e-3
        or np.abs(arr[:, 3] - [0, 0, 0, 1]).max() > 1e-6
    ):
        raise InputError(path, "pose is not a rigid camera-to-world transform (rotation not orthonormal)")
    if (np.linalg.det(rot) <= 0).any():
        raise InputError(path, "pose is not a rigid camera-to-world transform (rotation is a reflection)")
    return opengl_to_opencv(arr) if convention == "opengl" else arr


@cli.command()
@click.argument("run")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Output folder (default: RUN/renders).",
)
@click.option("--views", type=click.Choice(["test", "train", "all"]), default="test", show_default=True)
@click.option(
    "--pose",
    "pose_file",
    default=None,
    help="Render these 4x4 camera-to-world poses (.npy, .json or text; one or many) instead of views.",
)
@click.option(
    "--pose-convention",
    type=click.Choice(["opengl", "opencv"]),
    default="opengl",
    show_default=True,
    help="Axes of --pose: OpenGL (nerfstudio/Blender transforms.json) or OpenCV (COLMAP).",
)
@click.option(
    "--ev",
    type=float,
    default=None,
    help="Exposure in stops relative to the mean of all views' white balance (needs --tonemap runs).",
)
@click.option("--wb", type=float, nargs=3, default=None, help="Per-channel gains relative to that mean.")
@click.option(
    "--crf-from", type=int, default=None, help="Use this view's response curve (default: reference)."
)
@click.option(
    "--crf-run",
    default=None,
    help="Take --crf-from's curve from another trained run, or from a camera_params.json (a run's "
    "exported cameras, edited or not).",
)
@backend_option
@device_option
def render(run, out_dir, views, pose_file, pose_convention, ev, wb, crf_from, crf_run, backend, device):
    """Render RUN's views (or --pose) to float EXR (linear radiance) and PNG.

    The PNG shows each view through its own learned camera (a --pose through the reference image's);
    without tone mapping it is the radiance clipped to [0, 1].
    """
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.data.image_io import write_exr, write_png

    model = _load_model(run, str(pick_device(device)))
    out = Path(out_dir) if out_dir else Path(run if Path(run).is_dir() else Path(run).parent) / "renders"
    # (name, pose, intrinsics, size, view whose camera model tone-maps the PNG)
    jobs: list[tuple[str, np.ndarray, np.ndarray, tuple[int, int], int]] = []
    if pose_file:
        poses = model.geometry.poses_to_world(
            _read_poses(_existing_path(pose_file, "pose file"), pose_convention)
        )
        ref = model.test_ids[0] if model.test_ids else 0
        look = int(model.tonemapper.reference) if model.tonemapper is not None else ref
        for k, pose in enumerate(poses):
            jobs.append((f"pose_{k:03d}", pose, model.cameras.intrinsics[ref], model.cameras.size(ref), look))
    else:
        ids = {"test": model.test_ids, "train": model.train_ids, "all": range(len(model.cameras))}[views]
        for i in ids:
            name = Path(model.names[i]).stem
            jobs.append((name, model.cameras.c2w[i], model.cameras.intrinsics[i], model.cameras.size(i), i))
    controlled = ev is not None or wb is not None or crf_from is not None or crf_run is not None
    if controlled and model.tonemapper is None:
        raise InputError(Path(run), "--ev/--wb/--crf-from need a run trained with --tonemap")
    source = _load_cameras(crf_run) if crf_run else model.tonemapper
    n_views = len(source.log_wb) if source is not None else len(model.cameras)
    if crf_from is not None and not 0 <= crf_from < n_views:
        raise InputError(Path(crf_run or run), f"--crf-from {crf_from}: the run has views 0..{n_views - 1}")
    suffix = f"_ev{ev or 0:+g}" if controlled else ""
    for name, pose, intr, size, look in jobs:
        radiance = model.render_view(pose, intr, size, backend)
        write_exr(out / f"{name}.exr", model.hdr(radiance).cpu().numpy())
        if controlled:
            ldr = model.to_ldr_controlled(radiance, ev or 0.0, tuple(wb or (1.0, 1.0, 1.0)), crf_from, source)
        else:
            ldr = model.to_ldr(radiance, look)
        write_png(out / f"{name}{suffix}.png", ldr.cpu().numpy())
    click.echo(f"wrote {len(jobs)} views (PNG + EXR) to {out}")


@cli.command("eval")
@click.argument("run")
@click.option("--data", default=None, help="Dataset path (default: the one the model was trained on).")
@click.option(
    "--json", "json_path", default=None, help="Also write the metrics (means and per view) as JSON."
)
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS (the slowest metric on CPU).")
@backend_option
@device_option
def eval_cmd(run, data, json_path, no_lpips, backend, device):
    """Score RUN on its test views: PSNR, SSIM, LPIPS-VGG and LPIPS-Alex, as a table."""
    from hdrplenoxels.core.atomic import atomic_write_text
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.eval.evaluate import evaluate, format_table

    model = _load_model(run, str(pick_device(device)))
    scene = load_scene(_existing_path(data or model.data_path, "dataset of the run"))
    result = evaluate(model, scene, backend, lpips=not no_lpips)
    click.echo(format_table(result))
    if json_path:
        atomic_write_text(json_path, json.dumps(result, indent=2))


@cli.command()
@click.argument("run")
@click.argument("output")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["svox2"]),
    default="svox2",
    show_default=True,
    help="svox2: the Plenoxels ckpt.npz layout (links, density_data, sh_data, radius, center).",
)
def export(run, output, fmt):
    """Export RUN's grid to another format (a bounding-box grid in the dataset's own frame)."""
    from hdrplenoxels.grid.io import export_svox2
    from hdrplenoxels.grid.sparse_grid import grid_in_data_frame

    model = _load_model(run)
    grid = model.grid if model.geometry.mode == "ndc" else grid_in_data_frame(model.grid, model.geometry)
    export_svox2(Path(output), grid)
    click.echo(f"wrote {fmt} checkpoint {output}")


@cli.command("import-svox2")
@click.argument("ckpt")
@click.argument("data")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@scene_mode_option
def import_svox2_cmd(ckpt, data, out_dir, scene_mode):
    """Make a run from an existing Plenoxels (svox2) CKPT and the DATA it was trained on."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.data.placement import setup_scene
    from hdrplenoxels.grid.io import import_svox2
    from hdrplenoxels.render import RenderOptions
    from hdrplenoxels.train.model import MODEL_FILE, Model

    grid = import_svox2(_existing_path(ckpt, "checkpoint"))
    scene = load_scene(_existing_path(data, "data path"))
    cams, geometry = setup_scene(scene, scene_mode, normalise=False)  # the grid is in svox2's frame
    geometry.center, geometry.radius = grid.center, grid.radius
    opt = RenderOptions(background=scene.background)
    model = Model(
        grid,
        geometry,
        opt,
        cams,
        scene.names,
        scene.train_ids,
        scene.test_ids,
        str(scene.source),
        {"holdout": "full"},
    )
    model.save(Path(out_dir) / MODEL_FILE)
    click.echo(f"wrote {Path(out_dir) / MODEL_FILE}")


def _resolution(value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT, e.g. 800x800, got {value!r}") from None
    if w < 8 or h < 8:
        raise click.BadParameter("width and height must be at least 8")
    return w, h


@cli.command()
@click.argument("scene", required=False)
@click.argument("out", required=False, type=click.Path(file_okay=False))
@click.option("--list", "list_scenes", is_flag=True, help="Print the scene names, one per line, and exit.")
@click.option("--resolution", default=None, help="WIDTHxHEIGHT (default: a small CPU size per scene).")
@click.option("--paper", is_flag=True, help="The paper's 800x800 resolution.")
@click.option(
    "--views", type=click.IntRange(min=8), default=50, show_default=True, help="Every 8th is a test view."
)
@click.option(
    "--spp", type=click.IntRange(min=1), default=None, help="Samples per pixel (default per scene)."
)
@click.option(
    "--ev-range",
    type=click.Choice(["3", "4", "5", "6"]),
    default="3",
    show_default=True,
    help="3: EV drawn from {-3, 0, +3} as in the paper; 4-6: five levels over +-N EV.",
)
@click.option(
    "--crf",
    type=click.Choice(["gamma3", "filmic", "srgb", "mixed"]),
    default="gamma3",
    show_default=True,
    help="Camera response of the varying views (mixed: drawn per view).",
)
@click.option("--noise", is_flag=True, help="Add Poisson-Gaussian shot noise (full well 4000 e-, read 3 e-).")
@click.option(
    "--vignetting",
    type=float,
    nargs=2,
    default=(0.0, 0.0),
    show_default=True,
    help="Radial falloff k1 k2 (1 + k1 r^2 + k2 r^4), e.g. -0.3 0.",
)
@click.option(
    "--seed",
    type=click.IntRange(0, 2**31 - 1),
    default=0,
    show_default=True,
    help="Seeds the per-view camera settings, noise and Monte Carlo sampling (not the scene).",
)
@click.option("--overwrite", is_flag=True, help="Replace a scene already synthesised in OUT.")
def synth(
    scene, out, list_scenes, resolution, paper, views, spp, ev_range, crf, noise, vignetting, seed, overwrite
):
    """Render SCENE with Mitsuba into OUT: HDR truth plus varying- and static-camera LDR datasets."""
    from hdrplenoxels.synth.pipeline import CRFS, PipelineConfig, exposure_set
    from hdrplenoxels.synth.scenes import SCENES

    if list_scenes:
        click.echo("\n".join(SCENES))
        return
    if scene is None or out is None:
        raise click.UsageError("give SCENE and OUT (or --list)")
    if scene not in SCENES:
        raise click.BadParameter(
            f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}", param_hint="SCENE"
        )
    from hdrplenoxels.synth.generate import SynthOptions, synthesize

    if paper and resolution:
        raise click.UsageError("give --paper or --resolution, not both")
    size = (800, 800) if paper else _resolution(resolution)
    opts = SynthOptions(views, *(size or (None, None)), spp)
    pipeline = PipelineConfig(
        ev_set=exposure_set(int(ev_range)),
        crfs=tuple(CRFS) if crf == "mixed" else (crf,),
        vignetting=tuple(vignetting),
        noise=noise,
        seed=seed,
    )
    with click.progressbar(length=views, label=f"rendering {scene}") as bar:
        summary = synthesize(scene, Path(out), opts, pipeline, lambda i, n: bar.update(1), overwrite)
    click.echo(json.dumps(summary, indent=1))


def _experiment_settings(preset_name, iters, scenes, views, resolution, spp, no_lpips, data, backend, device):
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.experiments import ExperimentSettings
    from hdrplenoxels.synth.scenes import SCENES

    pick_device(device)  # a missing GPU is refused before any scene is rendered
    names = tuple(n for n in (scenes or "").split(",") if n)
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise click.BadParameter(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    return ExperimentSettings(
        preset=preset_name,
        iters=iters,
        scenes=names,
        n_views=views,
        resolution=_resolution(resolution),
        spp=spp,
        lpips=not no_lpips,
        backend=backend,
        device=device,
        data_root=Path(data) if data else None,
    )


def experiment_options(f):
    """Options every experiment (and the demo) shares."""
    options = [
        click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="fast",
                     show_default=True, help="Training schedule of every run."),
        click.option("--iters", type=click.IntRange(min=1), default=None, help="Override the iterations."),
        click.option("--scenes", default=None, help="Comma-separated scenes (default per experiment)."),
        click.option("--views", type=click.IntRange(min=8), default=50, show_default=True),
        click.option("--resolution", default=None, help="WIDTHxHEIGHT (default: each scene's CPU size)."),
        click.option("--spp", type=click.IntRange(min=1), default=None, help="Mitsuba samples per pixel."),
        click.option("--no-lpips", is_flag=True, help="Skip LPIPS (the slowest metric on CPU)."),
        click.option("--data", default=None, type=click.Path(file_okay=False),
                     help="Keep rendered HDR truth here, shared between experiments (default OUT/data)."),
        backend_option,
        device_option,
    ]  # fmt: skip
    for option in reversed(options):
        f = option(f)
    return f


@cli.command()
@click.argument("name", required=False)
@click.argument("out", required=False, type=click.Path(file_okay=False))
@click.option("--list", "list_names", is_flag=True, help="Print the experiments and exit.")
@click.option(
    "--variant",
    "variants",
    multiple=True,
    help="`validation` only, repeatable: tone-mapping settings to compare, e.g. lambda_crf_loglog=1e-2 "
    "(comma-separate several settings; 'defaults' is the defaults, the only variant when none is given).",
)
@experiment_options
def experiment(name, out, list_names, variants, preset_name, iters, scenes, views, resolution, spp, no_lpips,
               data, backend, device):  # fmt: skip
    """Run experiment NAME into OUT: report.md, report.json and images/, stating the protocol."""
    from hdrplenoxels.experiments import EXPERIMENTS
    from hdrplenoxels.experiments.validation import parse_variant

    if list_names:
        for key, (description, _) in EXPERIMENTS.items():
            click.echo(f"{key:<17} {description}")
        return
    if name is None or out is None:
        raise click.UsageError("give NAME and OUT (or --list)")
    if name not in EXPERIMENTS:
        raise click.BadParameter(f"unknown experiment {name!r}; see --list", param_hint="NAME")
    if variants and name != "validation":
        raise click.UsageError("--variant is for the validation experiment")
    for variant in variants:
        try:
            parse_variant(variant)
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--variant") from None
    settings = _experiment_settings(preset_name, iters, scenes, views, resolution, spp, no_lpips, data,
                                    backend, device)  # fmt: skip
    settings.variants = tuple(variants)
    t0 = time.perf_counter()
    report = EXPERIMENTS[name][1](Path(out), settings)
    click.echo(f"report: {report} ({time.perf_counter() - t0:.0f} s)")


@cli.command()
@click.option("--out", "out_dir", default="demo_out", show_default=True, type=click.Path(file_okay=False))
@experiment_options
def demo(out_dir, preset_name, iters, scenes, views, resolution, spp, no_lpips, data, backend, device):
    """HDR-Plenoxels on the built-in varying-camera scene, with baselines; writes a report and prints it."""
    from hdrplenoxels.experiments import EXPERIMENTS

    settings = _experiment_settings(preset_name, iters, scenes, views, resolution, spp, no_lpips, data,
                                    backend, device)  # fmt: skip
    t0 = time.perf_counter()
    report = EXPERIMENTS["demo"][1](Path(out_dir), settings)
    result = json.loads(report.with_name("report.json").read_text())["scenes"]["demo"]
    for key, values in result.items():
        click.echo(f"{key:<18} PSNR {values['psnr']:6.2f} dB  SSIM {values['ssim']:.4f}")
    click.echo(f"report: {report} ({time.perf_counter() - t0:.0f} s)")


def main(argv: list[str] | None = None) -> None:
    try:
        cli.main(args=argv, prog_name="hdrplenoxels", standalone_mode=False)
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(EXIT_INPUT_ERROR)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
