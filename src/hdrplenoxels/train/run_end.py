"""The end of a run, after its last step: the final checkpoint, the tone's refit, gauge and controller,
the tone plot and parameters, and the model file, with the older checkpoints pruned once all of it is
written."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.writer_thread import WriterThread
from hdrplenoxels.tonemap.plots import plot_tone_params
from hdrplenoxels.train.controller_fit import controller_note, fit_controller
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.run_state import resumable, state_arrays
from hdrplenoxels.train.tone_refit import refit_after_training
from hdrplenoxels.train.tone_setup import camera_truth, finish_tones

if TYPE_CHECKING:
    from hdrplenoxels.train.trainer import Trainer

TONE_PARAMS_FILE = "tone_params.json"
TONE_PLOT_FILE = "tone_params.png"


def finish_run(trainer: Trainer, writer: WriterThread) -> tuple[Model, list[str]]:
    """The model, and the lines saying how the tone was refitted, the scale its EVs are in and the tone
    controller fitted (none without a tone mapper).

    The final checkpoint and the tone plot are written on the writer thread while the tone is refitted
    (`train/tone_refit.py`) and its gauge and controller fitted here. The final checkpoint is a run state
    (`train/run_state.py`): the training state without the field, which the model file holds, and the
    tone as trained (a run resumed from it refits the same). Nothing after the last step changes the
    optimisers' state, so it is written from views of it (the tone mapper's arrays, which the refit and
    the gauge's fit change, are copies). Older checkpoints are pruned only once the model is written too:
    until then the state is not one `--resume` takes."""
    writer.wait()
    folder, final, written = trainer.folder, trainer.checkpoint_path(trainer.step), None
    # A state left by a run killed before its model is rewritten: the model will be this run's.
    if not final.exists() or not resumable(final):
        meta, extra = trainer.training_state()
        written = folder.write_behind(writer, final, state_arrays(meta, extra, MODEL_FILE), prune=False)
    notes, params = [], None
    if trainer.tonemapper is not None:
        t, render = trainer.cfg.tonemap, trainer.engine.render
        notes.append(refit_after_training(trainer.tonemapper, t, trainer.pool, render, trainer.cfg.seed))
        gauge, params = finish_tones(trainer.tonemapper, t, trainer.scene)
        notes.append(gauge)
    model = trainer.model()
    if params is not None:
        writer.submit(plot_tone_params, params, trainer.out_dir / TONE_PLOT_FILE, camera_truth(trainer.scene))
        model.controller, errors = fit_controller(model, trainer.cfg.backend)
        notes.append(controller_note(model.controller, errors))
    if written is not None:
        written.result()
    model.save(trainer.out_dir / MODEL_FILE)  # beside the plot, if it is still being drawn
    if written is not None:  # the older checkpoints go once both halves of the last are written
        folder.prune_checkpoints()
    if params is not None:
        atomic_write_text(trainer.out_dir / TONE_PARAMS_FILE, json.dumps(params))
    writer.wait()
    return model, [note for note in notes if note]
