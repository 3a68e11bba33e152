"""Synthetic data and the experiments: `synth`, `experiment`, `demo`."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from hdrplenoxels.cli.batch import executor_config, executor_options, report_failures
from hdrplenoxels.cli.common import (
    backend_option,
    checked_overrides,
    choice_option,
    device_option,
    iters_option,
    parse_resolution,
    preset_option,
    set_option,
)
from hdrplenoxels.train.presets import PRESETS


@click.command()
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
    "--test-spp",
    type=click.IntRange(min=1),
    default=None,
    help="Samples per pixel of the test views, whose right halves are scored (default: --spp).",
)
@choice_option(
    "--ev-range",
    choices=["3", "4", "5", "6"],
    default="3",
    help="3: EV drawn from {-3, 0, +3} as in the paper; 4-6: five levels over +-N EV.",
)
@choice_option(
    "--crf",
    choices=["gamma3", "filmic", "srgb", "mixed"],
    default="gamma3",
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
@choice_option(
    "--camera",
    choices=["bracket", "auto"],
    default="bracket",
    help="auto: also OUT/auto, captured as a phone's auto exposure and white balance would (metered from "
    "each view, with the meter's noise and a white-balance bias); the bracketed varying/ stays.",
)
@click.option(
    "--photos",
    is_flag=True,
    help="Also write each capture's images as a phone's JPEGs with EXIF (each view's exposure time, the "
    "lens's 35 mm-equivalent focal) in OUT/<capture>/photos/: input for `process` with a known answer.",
)
@click.option("--overwrite", is_flag=True, help="Replace a scene already synthesised in OUT.")
def synth(scene, out, list_scenes, resolution, paper, views, spp, test_spp, ev_range, crf, noise, vignetting,
          seed, camera, photos, overwrite):  # fmt: skip
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
    size = (800, 800) if paper else parse_resolution(resolution)
    opts = SynthOptions(views, *(size or (None, None)), spp, test_spp)
    pipeline = PipelineConfig(
        ev_set=exposure_set(int(ev_range)),
        crfs=tuple(CRFS) if crf == "mixed" else (crf,),
        vignetting=tuple(vignetting),
        noise=noise,
        seed=seed,
    )
    with click.progressbar(length=views, label=f"rendering {scene}") as bar:
        summary = synthesize(
            scene, Path(out), opts, pipeline, lambda i, n: bar.update(1), overwrite, camera == "auto"
        )
    if photos:
        from hdrplenoxels.synth.generate import AUTO_VARIANT, VARIANTS
        from hdrplenoxels.synth.photos import write_photos

        for variant in (*VARIANTS, AUTO_VARIANT) if camera == "auto" else VARIANTS:
            summary.setdefault("photos", []).append(str(write_photos(Path(out) / variant)))
    click.echo(json.dumps(summary, indent=1))


def _experiment_settings(
    preset_name, nerf_preset, iters, scenes, views, resolution, spp, no_lpips, data, backend, device
):
    from hdrplenoxels.core.devices import pick_device
    from hdrplenoxels.experiments import ExperimentSettings
    from hdrplenoxels.synth.scenes import SCENES
    from hdrplenoxels.train.presets import preset

    for name, option, kind in ((preset_name, "--preset", "grid"), (nerf_preset, "--nerf-preset", "nerf")):
        if preset(name).model != kind:
            raise click.BadParameter(f"{name!r} is not a {kind} preset", param_hint=option)

    pick_device(device)  # a missing GPU is refused before any scene is rendered
    names = tuple(n for n in (scenes or "").split(",") if n)
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise click.BadParameter(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    return ExperimentSettings(
        preset=preset_name,
        nerf_preset=nerf_preset,
        iters=iters,
        scenes=names,
        n_views=views,
        resolution=parse_resolution(resolution),
        spp=spp,
        lpips=not no_lpips,
        backend=backend,
        device=device,
        data_root=Path(data) if data else None,
    )


def experiment_options(f):
    """Options every experiment (and the demo) shares."""
    options = [
        preset_option("Training schedule of every grid run."),
        choice_option(
            "--nerf-preset",
            choices=sorted(PRESETS),
            default="nerf-cpu",
            help="Training schedule of every NeRF run (NeRF baselines).",
        ),
        iters_option,
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


@click.command()
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
@set_option
@experiment_options
@executor_options
def experiment(name, out, list_names, variants, overrides, preset_name, nerf_preset, iters, scenes, views,
               resolution, spp, no_lpips, data, backend, device, executor, ray_address):  # fmt: skip
    """Run experiment NAME into OUT: report.md, report.json and images/, stating the protocol.

    With --executor ray the truth and captures are rendered here, every run is trained as a Ray task,
    then the experiment scores the finished runs."""
    from hdrplenoxels.cluster.experiment import RunsFailed, run_experiment
    from hdrplenoxels.experiments import EXPERIMENTS
    from hdrplenoxels.experiments.common import check_overrides
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
    checked_overrides(check_overrides, overrides)
    executor_settings = executor_config(executor, ray_address)
    settings = _experiment_settings(preset_name, nerf_preset, iters, scenes, views, resolution, spp, no_lpips,
                                    data, backend, device)  # fmt: skip
    settings.variants, settings.overrides = tuple(variants), tuple(overrides)
    t0 = time.perf_counter()
    try:
        report = run_experiment(name, Path(out), settings, executor_settings)
    except RunsFailed as e:
        report_failures(e.failed)
    click.echo(f"report: {report} ({time.perf_counter() - t0:.0f} s)")


@click.command()
@click.option("--out", "out_dir", default="demo_out", show_default=True, type=click.Path(file_okay=False))
@experiment_options
def demo(out_dir, preset_name, nerf_preset, iters, scenes, views, resolution, spp, no_lpips, data, backend,
         device):  # fmt: skip
    """HDR-Plenoxels on the built-in varying-camera scene, with baselines; writes a report and prints it."""
    from hdrplenoxels.experiments import EXPERIMENTS

    settings = _experiment_settings(preset_name, nerf_preset, iters, scenes, views, resolution, spp, no_lpips,
                                    data, backend, device)  # fmt: skip
    t0 = time.perf_counter()
    report = EXPERIMENTS["demo"][1](Path(out_dir), settings)
    result = json.loads(report.with_name("report.json").read_text())["scenes"]["demo"]
    for key, values in result.items():
        click.echo(f"{key:<18} PSNR {values['psnr']:6.2f} dB  SSIM {values['ssim']:.4f}")
    click.echo(f"report: {report} ({time.perf_counter() - t0:.0f} s)")
