"""`train` (dataset -> run)."""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

import click
from click.core import ParameterSource

from hdrplenoxels.cli.common import (
    backend_option,
    checked_overrides,
    choice_option,
    device_option,
    existing_path,
    iters_option,
    preset_option,
    scene_mode_option,
    set_option,
    setting_option,
)
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.train.config import (
    FLAG_KEYS,
    ConfigError,
    apply_overrides,
    flag_settings,
    parse_overrides,
    read_config,
)
from hdrplenoxels.train.presets import AUTO, auto_preset, preset


def _resumed_config(run: Path, preset_name: str):
    """The configuration a run was started with (a resumed run must keep it; see Trainer._resume). A run
    killed before it wrote one has no checkpoint either: it starts anew from the preset."""
    from hdrplenoxels.train.run_folder import checkpoints

    path = run / "config.json"
    if not path.exists():
        if not checkpoints(run):
            return preset(preset_name)
        raise InputError(path, "--resume needs the run's config.json, which is missing")
    return read_config(path)


def _warn_pool_memory(scene, cfg) -> None:
    from hdrplenoxels.train.ray_pool import pool_memory_warning

    d = cfg.data
    sizes = scene.cameras.sizes
    warning = pool_memory_warning(
        sizes, scene.train_ids, scene.test_ids, cfg.holdout, d.pool_budget_gb, d.downscale
    )
    if warning:
        click.echo(f"warning: {warning}", err=True)


# Flags with a default that a resumed run takes only when they are on its command line.
RUN_FLAG_KEYS = {"preset_name": "preset", "scene_mode": "scene_mode", "holdout": "holdout"}


def _flag_settings(params: dict, resume: bool) -> dict:
    """The config keys the command line's flags set (of the tone-mapping flags, later ones win; without
    the tone mapper `TrainConfig.check` refuses them)."""
    from hdrplenoxels.tonemap.config import SPARSE_BRACKET

    ctx = click.get_current_context()
    keys = {
        key: params[name]
        for name, key in RUN_FLAG_KEYS.items()
        if not resume or ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE
    }
    keys |= flag_settings({name: params[name] for name in FLAG_KEYS if name in params})
    if params["exposure_file"] is not None:
        keys["tonemap.known_exposure"] = True
    if params["exposure_init"] == "metadata":
        keys["tonemap.exposure_init_from_metadata"] = True
    if params["sparse_bracket"]:
        keys |= {f"tonemap.{key}": value for key, value in SPARSE_BRACKET.items()}
    if params["response_prior"] is not None:
        keys["tonemap.lambda_crf_loglog"] = params["response_prior"]
    if params["saturation_weighting"] is not None:
        keys["tonemap.saturation_weighting"] = params["saturation_weighting"]
    return keys


PROCESSED = "data"  # where `train` on a folder of photos or a video puts the dataset `process` makes


def _dataset(data: str, out_dir: Path) -> Path:
    """DATA itself; or, where it is a folder of photos or a video, the dataset `process` makes of it in
    the run folder (made first, and said; reused when a previous call made it)."""
    from hdrplenoxels.data import scene_layout
    from hdrplenoxels.data.video import is_video
    from hdrplenoxels.process.photos import PHOTO_EXTENSIONS

    path = existing_path(data, "data path")
    photos = path.is_dir() and scene_layout(path) is None
    photos = photos and any(p.suffix.lower() in PHOTO_EXTENSIONS for p in path.iterdir() if p.is_file())
    if not photos and not (path.is_file() and is_video(path)):
        return path
    target = out_dir / PROCESSED
    if (target / "transforms.json").is_file():
        click.echo(f"using the dataset `process` made of {path} in {target} (delete it to process again)")
        return target
    from hdrplenoxels.process import process_photos

    kind = "a video" if path.is_file() else "a folder of photos"
    click.echo(f"{path} is {kind}: registering it with `process` into {target} first")
    process_photos(path, target, log=click.echo)
    return target


def _read_inputs(scene, cfg, params: dict) -> None:
    """The placement line and the pool's memory warning; the scene's exposures read here when given."""
    from hdrplenoxels.data.placement import placement_summary

    click.echo(placement_summary(scene, cfg.scene_mode))
    _warn_pool_memory(scene, cfg)
    if params["exposure_file"] is not None:
        from hdrplenoxels.data.exposures import load_exposures

        scene.exposures = load_exposures(existing_path(params["exposure_file"], "exposure file"), scene.names)


@click.command()
@click.argument("data")
@preset_option(
    "Named schedule: fast, a first look in minutes on a laptop's CPU (64^3 grid); balanced, the CPU "
    "result, several times longer whatever the number of views (256^3 grid, SH degree 2, a finer "
    "background); paper-synthetic / paper-real, the paper's 128 000 steps (a GPU); nerf-fast / nerf-cpu, "
    "the NeRF engine at CPU sizes; auto, fast on a CPU and on a GPU the paper's schedule for the capture "
    "(paper-synthetic for an object in a box, else paper-real), said in one line. Costs and measured "
    'gains: docs/usage.md, "Presets".',
    auto=True,
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Run folder: checkpoints, logs, config.json and the final model.npz.",
)
@iters_option
@setting_option("--batch-size", "Override the preset's rays per batch.")
@setting_option(
    "--downscale",
    "Train on images this many times smaller on each side (area filter; the dataset's own images_N "
    "copies when present). Default 1, or a resumed run's own. render and eval use the run's.",
)
@click.option(
    "--model",
    "model_kind",
    type=click.Choice(["grid", "nerf"]),
    default=None,
    help="The radiance field: a Plenoxels sparse voxel grid, or a NeRF MLP (sizes in the preset's `nerf` "
    "section; --set nerf.width=... changes them). Default: the preset's (grid).",
)
@click.option(
    "--appearance-embedding",
    is_flag=True,
    default=None,
    help="NeRF-A (with --model nerf): a learned embedding per image into the colour branch (NeRF-W "
    "without transients; --set nerf.appearance_dim=..., 48 by default).",
)
@backend_option
@device_option
@scene_mode_option
@choice_option(
    "--holdout",
    choices=["right-half", "full"],
    default="right-half",
    help="right-half: test views' left halves train, right halves are scored (HDR-Plenoxels).",
)
@click.option(
    "--tonemap/--no-tonemap",
    default=None,
    help="Learn a tone per photo (HDR-Plenoxels) or not (plain Plenoxels, the baseline). Default: on where "
    "the photos' camera settings vary (their EXIF exposures, or overlapping views' exposure and white "
    "balance) and off for one fixed camera; the run says which and why.",
)
@click.option(
    "--known-exposure",
    "exposure_file",
    default=None,
    help="JSON of each view's exposure in EV ({name: EV}, or a synth camera_truth.json). Training "
    "stays self-calibrated; afterwards the exponent of its ambiguity is fitted to these EVs, so the EXR "
    "is linear radiance and learned EVs and --ev are true stops.",
)
@choice_option(
    "--exposure-init",
    choices=["data", "metadata"],
    default="data",
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
    "--saturation-weighting/--no-saturation-weighting",
    default=None,
    help="Down-weight near-black and near-white pixels in the tone mapper's loss (default: the preset's; "
    "on in fast and balanced).",
)
@click.option(
    "--sparse-bracket",
    is_flag=True,
    help="The images are few exposures far apart (e.g. -3 and +3 EV only): turns on the response prior "
    "(at 1e-2 unless --response-prior says) and saturation weighting, as the table-s2 experiment "
    "does.",
)
@set_option
@click.option("--resume", is_flag=True, help="Continue from the newest checkpoint in --out.")
@click.option(
    "--overwrite", is_flag=True, help="Start over in an --out that already holds a run (deletes it)."
)
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(data, out_dir, overrides, resume, overwrite, quiet, **params):
    """Train a radiance field on DATA: a dataset (a transforms.json file or a folder holding one, LLFF,
    COLMAP), or a folder of photos or a video, which `process` registers into OUT/data first."""
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.data.placement import choose_mode
    from hdrplenoxels.train.model import MODEL_FILE
    from hdrplenoxels.train.trainer import Trainer, TrainingStopped

    overrides = checked_overrides(parse_overrides, overrides)
    # Flags set the new run's config; a resumed run keeps its own unless a flag is given explicitly (and a
    # changed setting is then refused by the Trainer).
    keys = _flag_settings(params, resume)
    if keys.get("preset") == AUTO:
        keys.pop("preset")  # a resumed run keeps its preset; a new one gets what `auto` chooses below

    def configured(name: str):
        cfg = _resumed_config(Path(out_dir), name) if resume else preset(name)
        return apply_overrides(apply_overrides(cfg, keys), overrides)

    name = params["preset_name"]
    # No preset sets the data's or the device's keys, so the scene loads the same under any of them.
    cfg = configured("fast" if name == AUTO else name)
    scene = load_scene(_dataset(data, Path(out_dir)), cfg.data.downscale)
    if name == AUTO and not (resume and (Path(out_dir) / "config.json").exists()):
        chosen, why = auto_preset(pick_device(cfg.device).type, choose_mode(scene, cfg.scene_mode))
        click.echo(f"preset: {chosen} ({why}; --preset names another)")
        cfg = configured(chosen)
    _read_inputs(scene, cfg, params)
    t0 = time.perf_counter()
    try:
        try:  # the settings against each other and the capture: a usage error before anything is written
            trainer = Trainer(scene, cfg, Path(out_dir), resume=resume, overwrite=overwrite)
        except ConfigError as e:
            raise click.UsageError(str(e)) from None
        for note in trainer.config_notes:
            click.echo(note)
        for note in (trainer.sight_priors_note, trainer.coverage_note):
            if note:
                click.echo(note)
        model = trainer.run(progress=not quiet)
        for note in trainer.end_notes:
            click.echo(note)
    except TrainingStopped as stopped:
        click.echo(
            f"stopped by {stopped.signal_name} at step {stopped.step}; "
            f"checkpoint written: {stopped.checkpoint}\n"
            f"continue with: hdrplenoxels train {data} --out {out_dir} --resume",
            err=True,
        )
        sys.exit(128 + getattr(signal, stopped.signal_name))
    click.echo(
        f"trained {model.step} steps in {time.perf_counter() - t0:.1f} s; model: {Path(out_dir) / MODEL_FILE}"
    )
