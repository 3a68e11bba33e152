"""A training run's folder: its lock, the files it holds (config, log, checkpoints, model) and what a
new, resumed or overwritten run may do with them (docs/usage.md, "Stopping and resuming")."""

from __future__ import annotations

import json
import shutil
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.atomic import atomic_write_text, ensure_space
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.run_lock import RunLock
from hdrplenoxels.core.writer_thread import WriterThread
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.io import write_npz
from hdrplenoxels.render.fields import Field
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.field_io import load_field_with_background
from hdrplenoxels.train.model import MODEL_FILE
from hdrplenoxels.train.run_state import field_path, is_run_state, load_run_state, resumable, settings_changed

CHECKPOINT_DIR = "checkpoints"
LOG_FILE = "train_log.jsonl"
CONFIG_FILE = "config.json"


def checkpoints(run: Path) -> list[Path]:
    """A run folder's complete checkpoints, oldest first (a write in progress is a temporary file, never
    listed)."""
    return sorted((Path(run) / CHECKPOINT_DIR).glob("step_*.npz"))


def resumable_checkpoints(run: Path) -> list[Path]:
    """The checkpoints `--resume` may continue from, oldest first: all but a finished run's last one
    (`train/run_state.py`) whose model file is missing or of another step (killed between the two)."""
    return [p for p in checkpoints(run) if resumable(p)]


class RunFolder:
    """The folder of one run, locked while it trains (`core.run_lock`)."""

    def __init__(self, path: Path, keep_checkpoints: int):
        self.path = Path(path)
        self.keep_checkpoints = keep_checkpoints
        """How many complete checkpoints stay (0: all)."""
        self.lock = RunLock(self.path).acquire()  # before anything in the folder is read or removed

    def open(self, resume: bool, overwrite: bool) -> Path | None:
        """The checkpoint a resumed run continues from (None: the run starts from step 0, in a folder
        claimed for it). A folder killed before its first checkpoint starts over; a finished run's
        state that does not go with its model is refused rather than thrown away."""
        usable = resumable_checkpoints(self.path) if resume else []
        if usable:
            return usable[-1]
        if resume:
            found = checkpoints(self.path)
            if found and (self.path / MODEL_FILE).exists():
                raise InputError(
                    found[-1],
                    f"its training state does not go with the run's {MODEL_FILE} (another step or "
                    "configuration); pass --overwrite to start the run over",
                )
            overwrite = True  # killed before its first checkpoint: nothing to lose
        self._claim(overwrite)
        return None

    def _claim(self, overwrite: bool) -> None:
        """A new run never mixes with an old one's checkpoints and log (a later --resume would pick them)."""
        old = [self.path / CHECKPOINT_DIR, self.path / LOG_FILE, self.path / MODEL_FILE]
        if not any(p.exists() for p in old):
            return
        if not overwrite:
            raise InputError(
                self.path,
                "already holds a training run; pass --resume to continue it or --overwrite to start over",
            )
        shutil.rmtree(old[0], ignore_errors=True)
        for p in old[1:]:
            p.unlink(missing_ok=True)

    def write_config(self, config: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path / CONFIG_FILE, json.dumps(config, indent=2))

    def checkpoint_path(self, step: int) -> Path:
        return self.path / CHECKPOINT_DIR / f"step_{step:07d}.npz"

    def write_checkpoint(self, path: Path, arrays: dict[str, np.ndarray], prune: bool = True) -> None:
        write_npz(path, arrays)
        if prune:
            self.prune_checkpoints()

    def write_behind(
        self, writer: WriterThread, path: Path, arrays: dict[str, np.ndarray], prune: bool = True
    ) -> Future:
        """Queue a checkpoint's write on `writer`; one that cannot fit on the disk is refused here, at
        once."""
        ensure_space(path, sum(a.nbytes for a in arrays.values()))
        return writer.submit(self.write_checkpoint, path, arrays, prune)

    def prune_checkpoints(self) -> None:
        """All but the newest `keep_checkpoints` go (the newest is complete first)."""
        keep = self.keep_checkpoints
        for stale in checkpoints(self.path)[:-keep] if keep > 0 else []:
            stale.unlink(missing_ok=True)

    def forget_log_after(self, step: int) -> None:
        """Drop log lines of steps a killed run made after its last checkpoint: they are trained again."""
        path = self.path / LOG_FILE
        if not path.exists():
            return
        kept = []
        # A kill can cut a line anywhere, even inside a character: undecodable bytes fail that line only.
        for line in path.read_bytes().decode("utf-8", errors="replace").splitlines():
            try:
                if json.loads(line)["step"] <= step:
                    kept.append(line)
            except (ValueError, KeyError, TypeError):
                continue  # a line cut short by the kill
        atomic_write_text(path, "".join(f"{line}\n" for line in kept))

    def release(self) -> None:
        self.lock.release()


def checkpoint_due(cfg: TrainConfig, step: int, since: float) -> bool:
    """Whether a periodic checkpoint is due after `step`, `since` seconds after the last: every
    `checkpoint_every` steps but at most once per `checkpoint_gap_seconds`, or every
    `checkpoint_seconds` whatever the step."""
    by_steps = (
        cfg.checkpoint_every and step % cfg.checkpoint_every == 0 and since >= cfg.checkpoint_gap_seconds
    )
    by_time = cfg.checkpoint_seconds and since >= cfg.checkpoint_seconds
    return bool(by_steps or by_time)


def load_checkpoint(
    checkpoint: Path, cfg: TrainConfig, device: torch.device
) -> tuple[Field, MSIBackground | None, dict, dict[str, np.ndarray]]:
    """The field, background, meta and arrays of a checkpoint a run of `cfg` resumes from; refused
    (`InputError`) when it is not this project's or was trained with other settings. A finished run's
    last checkpoint is a run state (`train/run_state.py`): its field is the model file's."""
    if is_run_state(checkpoint):
        meta, extra = load_run_state(checkpoint)
        field, background, _, _ = load_field_with_background(field_path(checkpoint, meta), device)
    else:
        field, background, meta, extra = load_field_with_background(checkpoint, device=device)
    if meta.get("kind") != "model":
        raise InputError(checkpoint, "not a training checkpoint of this project")
    try:
        saved = TrainConfig.from_dict(meta["config"])
    except (KeyError, ValueError) as e:
        raise InputError(checkpoint, f"cannot read the run's configuration: {e}") from None
    changed = settings_changed(saved.to_dict(), cfg.to_dict())
    if changed:
        raise InputError(
            checkpoint,
            f"a resumed run keeps its configuration, but these settings differ: {', '.join(changed)}",
        )
    return field, background, meta, extra
