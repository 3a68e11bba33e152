"""A finished run's last checkpoint without its field: the optimisers', sampler's and tones' state, beside
the model file that holds the very same field (docs/usage.md, "crash-safe" paragraph).

The field is the largest part of a checkpoint, and at the last step the model file holds it anyway:
writing it twice cost a GPU run most of its end (JOURNAL.md, "Checkpoint writes"). The state
names the model file it goes with; it counts as a checkpoint only while that file is of the same step
and configuration (a kill between the two writes leaves one without the other, and `--resume` then
takes the checkpoint before it).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.npy_files import read_npz
from hdrplenoxels.grid import io as grid_io

if TYPE_CHECKING:
    from hdrplenoxels.train.engines.base import Engine
    from hdrplenoxels.train.model import Model
    from hdrplenoxels.train.optim import TorchRMSProp

# Settings that may change when a run is resumed: they do not change what is being optimised.
RESUMABLE_CHANGES = {
    "optim.n_iters",
    "backend",
    "device",
    "cuda_graph",
    "log_every",
    "checkpoint_every",
    "checkpoint_seconds",
    "checkpoint_gap_seconds",
    "keep_checkpoints",
    "view_prior_update",  # owed or dense, the same training to the bit; a checkpoint owes nothing
    "tv_layout",  # a kernel's threads, the same gradient
    "owed_pay",  # the paying pass's threads, the same numbers
    "touched_update",  # the touched update's threads, the same numbers
}

STATE_FORMAT = "hdrplenoxels-run-state"
STATE_VERSION = 1
FIELD_FILE = "field_file"  # the meta entry naming the model file, in the run folder, that holds the field


def state_arrays(
    meta: dict[str, Any], extra: dict[str, np.ndarray], field_file: str
) -> dict[str, np.ndarray]:
    """The entries of a run state: a checkpoint's `meta` (naming `field_file`) and extra arrays."""
    return {
        "format": np.array(STATE_FORMAT),
        "version": np.array(STATE_VERSION, dtype=np.int64),
        "meta_json": np.array(json.dumps(meta | {FIELD_FILE: field_file})),
        **{grid_io.EXTRA_PREFIX + name: np.asarray(value) for name, value in extra.items()},
    }


def settings_changed(saved: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Dotted names of the settings that differ between two `TrainConfig.to_dict()`s, other than those a
    resume may change (`RESUMABLE_CHANGES`)."""

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    a, b = flat(saved), flat(new)
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k) and k not in RESUMABLE_CHANGES)


def _peek(path: Path) -> tuple[str, dict[str, Any]] | None:
    """(format, meta) of a native file, reading those two entries only; None where they can't be read."""
    try:
        with np.load(path, allow_pickle=False) as z:
            fmt, meta = str(z["format"].item()), json.loads(str(z["meta_json"].item()))
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, json.JSONDecodeError):
        return None
    return (fmt, meta) if isinstance(meta, dict) else None


def is_run_state(path: Path) -> bool:
    peeked = _peek(path)
    return peeked is not None and peeked[0] == STATE_FORMAT


def field_path(path: Path, meta: dict[str, Any]) -> Path:
    """The model file a state names: a file of the run folder, nothing outside it."""
    name = meta.get(FIELD_FILE)
    if not isinstance(name, str) or not name or Path(name).name != name:
        raise InputError(path, f"its {FIELD_FILE!r} must name a file of the run folder, got {name!r}")
    return path.parent.parent / name


def resumable(path: Path) -> bool:
    """Whether `--resume` may continue from the checkpoint at `path`: a whole one (or one too damaged to
    tell, which the resume then names), or a run state that goes with its model file."""
    state = _peek(path)
    return state is None or state[0] != STATE_FORMAT or _goes_with_its_field(path, state[1])


def _goes_with_its_field(path: Path, meta: dict[str, Any]) -> bool:
    try:
        field_file = field_path(path, meta)
    except InputError:
        return False
    model = _peek(field_file) if field_file.is_file() else None
    if model is None or model[1].get("step") != meta.get("step"):
        return False
    configs = model[1].get("config"), meta.get("config")
    return all(isinstance(c, dict) for c in configs) and not settings_changed(*configs)


def load_run_state(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(meta, extra arrays) of a run state; its defects are `InputError`s naming it."""
    z = read_npz(path)
    if "format" not in z or grid_io.scalar_str(path, z, "format") != STATE_FORMAT:
        raise InputError(path, "not a training state of this project")
    return grid_io.checked_meta(path, z, STATE_VERSION, "training state"), grid_io.extra_arrays(z)


def training_state(
    model: Model, engine: Engine, generator: torch.Generator, tone_optimiser: TorchRMSProp | None
) -> tuple[dict, dict[str, np.ndarray]]:
    """A checkpoint's meta and its arrays beside the field: the model's (tones, controller), the
    optimisers', the sampler's, and the engine's level."""
    extra = model.extra_arrays()
    extra.update({f"optim/{k}": v for k, v in engine.state_arrays().items()})
    extra["rng/state"] = generator.get_state().numpy()
    if tone_optimiser is not None:
        extra.update({f"tonemap_optim/{k}": v for k, v in tone_optimiser.state_arrays().items()})
    meta = model.meta()
    meta["level"] = engine.level
    if model.tonemapper is not None:  # the exposure check's decision (`train/exposure_hold.py`)
        meta["exposures_held"] = model.tonemapper.stated_stops is not None
    return meta, extra


def prefixed(arrays: dict, prefix: str) -> dict:
    return {k.removeprefix(prefix): v for k, v in arrays.items() if k.startswith(prefix)}


# Bytes of a torch generator's state on each kind of device: the CPU's Mersenne Twister; CUDA's Philox
# keeps a seed and an offset, 8 bytes each.
GENERATOR_STATE_BYTES = {"cpu": 5056, "cuda": 16}


def restore_generator(generator: torch.Generator, state: np.ndarray, reseed: int) -> None:
    """Continue `generator` from a checkpoint's `state`, so that a resumed run equals an unbroken one.
    A state saved on the other kind of device (a CPU run resumed on a GPU, or back) cannot continue
    there: the generator is seeded with `reseed` instead, and the draws differ from then on."""
    own = generator.get_state().numel()
    others = {n for kind, n in GENERATOR_STATE_BYTES.items() if kind != generator.device.type}
    if state.size != own and state.size in others:
        generator.manual_seed(reseed)
        return
    generator.set_state(torch.from_numpy(np.ascontiguousarray(state)))
