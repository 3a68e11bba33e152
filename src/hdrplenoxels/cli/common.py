"""What the commands share: options, reading user paths and values, and their one-line errors."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import click

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.settings import fields_of
from hdrplenoxels.train.config import FLAG_KEYS, OverrideError, TrainConfig
from hdrplenoxels.train.presets import AUTO, PRESETS

EXIT_INPUT_ERROR = 2
EXIT_WRITE_ERROR = 74  # sysexits' EX_IOERR: the system refused a read or write (disk full, read-only)


def choice_option(*names: str, choices: Iterable[str], default: str | None, help: str | None = None):
    """A click option taking one of `choices`, its default shown in --help (every such option of the
    command line is declared through this)."""
    return click.option(
        *names, type=click.Choice(list(choices)), default=default, show_default=True, help=help
    )


# `--tone`, what a picture is seen through: one vocabulary for `render` and `eval` (what each word does:
# eval/evaluate.TONES; "view N" is view N's learned tone, for every picture).
TONE_WORDS = ("own", "auto", "mean", "cc", "view N")
TONE_HELP = (
    "own: each view's own learned tone (the default); auto: the tone the tone controller predicts from "
    "the render, as a camera's auto exposure and white balance would set it; mean: the mean learned "
    "tone; cc: the mean tone colour-corrected to the photo (an affine colour fit per image, as Zip-NeRF "
    "/ BilaRF / PPISP tables report); view N: view N's learned tone."
)


def parse_tone(text: str | None, command: str, takes: tuple[str, ...]) -> str | int | None:
    """`--tone` as one of TONE_WORDS: None for "own" (or no --tone), a view's index for "view N", else the
    word; a word of the vocabulary this `command` has no use for (`takes` the ones it has) is refused
    naming those, as is anything else."""
    if text is None:
        return None
    words = text.strip().lower().split()
    view = len(words) in (1, 2) and (len(words) == 1 or words[0] == "view") and words[-1].isdigit()
    word = "view N" if view else " ".join(words)
    valid = ", ".join(takes[:-1]) + f" or {takes[-1]}"
    if word not in TONE_WORDS:
        raise click.BadParameter(f"{text!r}: use {valid}", param_hint="--tone")
    if word not in takes:
        raise click.BadParameter(f"{command} has no use for {word!r}: use {valid}", param_hint="--tone")
    if word == "own":
        return None
    return int(words[-1]) if view else word


def old_flag(old: str, new: str, choices: Iterable[str] | None = None):
    """A hidden option under a flag's old name, so that scripts written before the rename still run; the
    command passes both values to `renamed_flag`."""
    kind = click.Choice(list(choices)) if choices is not None else None
    dest = "old_" + new.lstrip("-").replace("-", "_")
    return click.option(old, dest, type=kind, default=None, hidden=True, help=f"The old name of {new}.")


def renamed_flag(old: str, new: str, old_value, new_value):
    """The value of a renamed flag given under either name (None: neither); both at once is an error."""
    if old_value is not None and new_value is not None:
        raise click.UsageError(f"{old} is the old name of {new}: give one of them")
    return new_value if new_value is not None else old_value


backend_option = choice_option(
    "--backend",
    choices=["warp", "torch"],
    default="warp",
    help="Renderer: the Warp kernel, or the (slow) PyTorch reference.",
)
device_option = click.option(
    "--device", default="auto", show_default=True, help="'auto' picks CUDA when available, else CPU."
)
scene_mode_option = choice_option(
    "--scene-mode",
    choices=["auto", "bbox", "bbox+background", "cascade", "ndc"],
    default="auto",
    help="Grid in a bounding box (360 scenes), the box with a multi-sphere background behind it "
    "(content beyond the box), a cascade of nested boxes reaching every camera with the background "
    "beyond (real captures: content from beside the cameras to the far walls), or NDC (forward-facing, "
    "cameras near one pose); auto detects.",
)


def setting_option(flag: str, help: str):
    """A click option that sets one config key (`FLAG_KEYS` names it by the option's parameter name), its
    type and lower limit read from the key's declaration (`core.settings.setting`): the command line
    refuses what the config refuses, and the limit is written once. Not given (None), it leaves the key
    to the preset or the run."""
    hint, declared = fields_of(TrainConfig)[FLAG_KEYS[flag.lstrip("-").replace("-", "_")]]
    ranges = {int: click.IntRange, float: click.FloatRange}
    if hint not in ranges:
        raise TypeError(f"{flag}: a setting option is for an int or float setting, not {hint}")
    kind = ranges[hint](min=declared.metadata["at_least"], max=None)
    return click.option(flag, type=kind, default=None, help=help)


iters_option = click.option(
    "--iters", type=click.IntRange(min=1), default=None, help="Override the preset's number of iterations."
)


def preset_option(help_text: str, auto: bool = False):
    """`--preset NAME` (the parameter `preset_name`): one of the named schedules, `fast` by default, or
    with `auto` also `auto`, the default then (chosen per run: `train.presets.auto_preset`)."""
    choices = sorted(PRESETS) + ([AUTO] if auto else [])
    return choice_option(
        "--preset", "preset_name", choices=choices, default=AUTO if auto else "fast", help=help_text
    )


set_option = click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="SECTION.KEY=VALUE",
    help="Set one config field, typed as the config declares it (lists as JSON), after the preset and the "
    "other options; repeatable. E.g. optim.lr_sh=1e-3, tonemap.enabled=false, "
    "grid.reso_schedule=[[64,64,64],[128,128,128]].",
)


def checked_overrides(
    parse: Callable[[Iterable[str]], dict[str, Any]], items: Iterable[str]
) -> dict[str, Any]:
    """`--set` items typed by `parse`; a bad one is an InputError (one line, exit 2) before anything runs."""
    try:
        return parse(items)
    except OverrideError as e:
        raise InputError(None, f"--set: {e}") from None


def existing_path(value: str, what: str) -> Path:
    p = Path(value)
    if not p.exists():
        raise InputError(p, f"{what} does not exist")
    return p


def parse_resolution(value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT, e.g. 800x800, got {value!r}") from None
    if w < 8 or h < 8:
        raise click.BadParameter("width and height must be at least 8")
    return w, h


def load_model(run: str, device: str = "cpu"):
    """The model of a run folder, or a model file."""
    from hdrplenoxels.train.model import load_model as load

    return load(existing_path(run, "run folder or model file"), device)


def load_tones(source: str):
    """The learned tones (a ToneMapper) of a run folder, a model file, or a tone_params.json (an older
    run's camera_params.json reads the same)."""
    from hdrplenoxels.tonemap.module import ToneMapper

    path = existing_path(source, "run folder, model file or tone_params.json")
    if path.suffix == ".json":
        try:
            return ToneMapper.from_parameters_dict(json.loads(path.read_text()))
        except (ValueError, AttributeError) as e:  # JSONDecodeError is a ValueError
            raise InputError(path, str(e)) from None
    tonemapper = load_model(source).tonemapper
    if tonemapper is None:
        raise InputError(path, "--crf-run needs a run trained with --tonemap")
    return tonemapper
