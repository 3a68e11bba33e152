"""The training loop: one loop over any radiance-field engine, with the tone-mapping module after it.

One iteration (docs/method.md, "Training"): a uniform batch from the ray pool, the engine's forward,
the loss through the tone-mapping module, the engine's backward from d loss / d radiance, its
regularisers and optimiser step, then the tone parameters' step; on CUDA all of it replayed from a CUDA
graph (`train/step_graph.py`). The engine resamples itself on its schedule; checkpoints are written
periodically and at the end. Nothing here depends on the backend.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.devices import pick_device
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.signals import StopRequest, stop_signals
from hdrplenoxels.core.writer_thread import WriterThread
from hdrplenoxels.data.placement import choose_mode, setup_scene
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.render.fields import Field
from hdrplenoxels.train import exposure_hold
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines import Engine, GridHooks, new_engine
from hdrplenoxels.train.field_io import field_arrays
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.optim import ExpSchedule, StepClock, StepRates, make_tone_optimiser
from hdrplenoxels.train.ray_pool import RayPool
from hdrplenoxels.train.run_end import finish_run
from hdrplenoxels.train.run_folder import LOG_FILE, RunFolder, checkpoint_due, load_checkpoint
from hdrplenoxels.train.run_settings import run_settings
from hdrplenoxels.train.run_state import prefixed, restore_generator, training_state
from hdrplenoxels.train.sight_setup import restrict_to_views, use_sight_priors
from hdrplenoxels.train.step_graph import CudaCapture, StepGraph, held_key, uses_step_graph
from hdrplenoxels.train.tone_setup import initial_tonemapper, stated_exposures
from hdrplenoxels.train.train_log import TrainLog


class TrainingStopped(Exception):
    """A run stopped by a signal after writing the checkpoint of its last step."""

    def __init__(self, signal_name: str, step: int, checkpoint: Path):
        self.signal_name, self.step, self.checkpoint = signal_name, step, checkpoint
        super().__init__(f"stopped by {signal_name} at step {step}; checkpoint {checkpoint}")


class Trainer:
    """Owns the engine (field and optimiser), tone mapper and ray pool of one run; `run()` trains to
    `n_iters`."""

    def __init__(
        self, scene: SceneData, cfg: TrainConfig, out_dir: Path, resume: bool = False, overwrite: bool = False
    ):
        # The one check of the settings against each other and the capture, before anything is written
        # (a ConfigError); its lines say where a setting overrules the scene mode.
        self.config_notes = cfg.check(choose_mode(scene, cfg.scene_mode))
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.device = pick_device(cfg.device)  # a bad device fails before the run folder is made
        # Periodic checkpoints are written beside the next steps where the host copy they are written from
        # is made anyway (a GPU's state copied to the host); on a CPU they are written from views of the
        # state, in the foreground, rather than holding a second copy of it.
        self.background_checkpoints = self.device.type != "cpu"
        self.folder = RunFolder(self.out_dir, cfg.keep_checkpoints)
        self.lock = self.folder.lock
        start_from = self.folder.open(resume, overwrite)
        self.resumed = resume = start_from is not None
        self.scene = scene
        self.cameras, self.geometry = setup_scene(scene, cfg.scene_mode)
        cameras = self.cameras
        self.settings, notes = run_settings(cfg, scene, self.geometry)  # what trains
        self.config_notes += notes
        r = self.settings.render
        self.render_opt = RenderOptions(r.step_size, r.sigma_thresh, r.stop_thresh, r.background_brightness)
        self.pool = RayPool(
            scene.images, cameras, self.geometry, scene.train_ids, scene.test_ids, cfg.holdout, self.device
        )
        tone_lr = ExpSchedule(cfg.tonemap.lr, cfg.tonemap.lr_final, cfg.tonemap.lr_decay_steps)
        self.tone_rates = StepRates([tone_lr], self.device, cfg.optim.n_iters)
        self.step = 0
        # The step's number on the device, which a replayed step reads and advances (`StepClock`).
        self.step_count = torch.zeros(1, dtype=torch.int64, device=self.device)
        # Every random draw of a step (rays, TV cells, free-space samples) is made on the training device:
        # a GPU's step then never waits for numbers from the host.
        self.generator = torch.Generator(self.device).manual_seed(cfg.seed)
        self.step_graph: StepGraph | None = None  # the repeating part of a step from a CUDA graph
        if uses_step_graph(cfg, self.device.type):
            self.step_graph = StepGraph(CudaCapture(self.generator))
        self.engine: Engine = new_engine(
            self.settings, self.geometry, len(cameras), self.render_opt, self.device
        )
        # The grid's own hooks (priors, resampling, owed updates); None for an engine without them.
        self.hooks = self.engine if isinstance(self.engine, GridHooks) else None
        self.sight_priors_note = use_sight_priors(
            self.hooks, cfg, scene, cameras, self.geometry, self.pool, self.device
        )
        self.coverage_note = restrict_to_views(self.hooks, cfg, self.geometry, self.pool)
        # What `run` did after the last step (the tone's refit, the scale its EVs are in, the tone
        # controller), for the command line.
        self.end_notes: list[str] = []
        self.tonemapper = initial_tonemapper(
            self.settings.tonemap, scene, cameras, self.pool, self.device, resume
        )
        self.tone_optimiser = make_tone_optimiser(self.tonemapper) if self.tonemapper is not None else None
        # The exposures the photos state, and the step after which the tone's are checked against them.
        self.stated = stated_exposures(self.settings.tonemap, scene) if self.tonemapper is not None else None
        self.exposure_check = exposure_hold.check_step(self.settings.tonemap, cfg.optim.n_iters)
        if start_from is not None:
            self._resume(start_from)

    # ----------------------------------------------------------------------------- state
    def model(self) -> Model:
        """The model as trained so far (the grid settled first: `Engine.settle`)."""
        if self.hooks is not None:
            self.hooks.settle()
        return Model(
            field=self.engine.field,
            geometry=self.geometry,
            render_opt=self.render_opt,
            cameras=self.cameras,
            names=self.scene.names,
            train_ids=self.scene.train_ids,
            test_ids=self.scene.test_ids,
            data_path=str(self.scene.source),
            config=self.cfg.to_dict(),
            step=self.step,
            tonemapper=self.tonemapper,
            background=self.engine.background,
        )

    def checkpoint_path(self, step: int) -> Path:
        return self.folder.checkpoint_path(step)

    def save_checkpoint(self) -> Path:
        """Write the checkpoint of the step in hand, now."""
        path = self.checkpoint_path(self.step)
        self.folder.write_checkpoint(path, self.checkpoint_arrays())
        return path

    def checkpoint_arrays(self) -> dict[str, np.ndarray]:
        """What a checkpoint of the step in hand holds, as host arrays: on a GPU copies, on a CPU mostly
        views of the training state (`field_io.field_arrays`), valid until the next step changes it."""
        meta, extra = self.training_state()
        field, background = self.engine.field, self.engine.background
        return field_arrays(field, meta=meta, extra_arrays=extra, background=background)

    def training_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        return training_state(self.model(), self.engine, self.generator, self.tone_optimiser)

    def _checkpoint_during_run(self, writer: WriterThread) -> None:
        """A periodic checkpoint: in the background where `background_checkpoints` says so, from a host
        snapshot (one at a time: the previous write is waited for first, so the host holds one)."""
        writer.wait()
        path, arrays = self.checkpoint_path(self.step), self.checkpoint_arrays()
        if not self.background_checkpoints:
            self.folder.write_checkpoint(path, arrays)
            return
        if self.device.type == "cpu":  # views of what the next steps change
            arrays = {name: np.array(value, copy=True) for name, value in arrays.items()}
        self.folder.write_behind(writer, path, arrays)

    def _resume(self, checkpoint: Path) -> None:
        """Continue from `checkpoint`, the newest of `resumable_checkpoints`."""
        field, background, meta, extra = load_checkpoint(checkpoint, self.cfg, self.device)
        try:
            self._restore(field, background, meta, extra)
        except (KeyError, ValueError, TypeError, IndexError, OverflowError, RuntimeError) as e:
            # The same code restores every checkpoint this project writes: what fails is the file.
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(checkpoint, f"its training state does not fit this run ({reason})") from None
        self.folder.forget_log_after(self.step)  # last: a refused resume writes nothing

    def _restore(self, field: Field, background: MSIBackground | None, meta: dict, extra: dict) -> None:
        """The engine, step, sampler and tone state of a checkpoint."""
        self.engine.restore(field, int(meta["level"]), prefixed(extra, "optim/"), background)
        self.step = int(meta["step"])
        self.step_count.fill_(self.step)
        restore_generator(self.generator, np.asarray(extra["rng/state"]), self.cfg.seed + self.step)
        if self.tonemapper is not None:
            self.tonemapper.load_state_arrays(prefixed(extra, "tonemap/"))
            self.tone_optimiser = make_tone_optimiser(self.tonemapper)
            self.tone_optimiser.load_state_arrays(prefixed(extra, "tonemap_optim/"))
            if meta.get("exposures_held") and self.stated is not None:
                self.tonemapper.set_stated_exposures(torch.as_tensor(self.stated))

    # ----------------------------------------------------------------------------- loop
    @property
    def field(self) -> Field:
        """The radiance field being trained, as the last step left it: while rows owe the view prior's
        pull (`TrainConfig.view_prior_update`, CUDA's default) their SH are stale; `model` settles them."""
        return self.engine.field

    def train_step(self) -> torch.Tensor:
        """One iteration (docs/method.md, "Training"); returns the photometric MSE of the batch, a 0-d
        tensor on the device (read only when logging: reading it every step would make the CPU wait for
        the GPU)."""
        if self.step_graph is None:
            mse = self._step_region()
        else:
            mse = self.step_graph(self._graph_key(), self._step_region).clone()  # a replay overwrites it
        self.step += 1
        if self.hooks is not None:
            self.hooks.after_step(self.step)
        return mse

    def _step_region(self) -> torch.Tensor:
        """The whole step, which a CUDA graph may replay (`step_graph.py`): the gradients, the engine's
        and the tone parameters' optimiser steps at the rates of the device's step count, which it then
        advances. A replay runs no Python: nothing here may change host state a later step reads, and
        what depends on the step number reads `step_count` (the view prior's weight, which changes once,
        is in the graph's key instead). Returns the batch's MSE."""
        clock = StepClock(self.step, self.step_count)
        mse, grad_tone = self._gradients()
        self.engine.step(clock, self._view_prior_weight())
        if self.tone_optimiser is not None:
            self.tone_optimiser.step(grad_tone, self.tone_rates(clock.count))
        self.step_count.add_(1)
        return mse

    def _gradients(self) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The gradient part of a step: a batch, the engine's forward, the loss through the tone mapper,
        the engine's backward and regularisers into its gradient buffers. Returns the batch's MSE and
        the tone parameters' gradients."""
        batch = self.pool.sample(self.cfg.optim.batch_size, self.generator)
        rgb, batch = self.engine.forward(batch)
        tone_params = [] if self.tone_optimiser is None else self.tone_optimiser.params
        if self.tonemapper is None:
            loss = torch.mean((rgb - batch.target) ** 2)
            mse = loss.detach()
        else:
            loss, mse = self.tonemapper.training_loss(rgb, batch.pixels())
        grad_rgb, *grad_tone = torch.autograd.grad(loss, [rgb, *tone_params])
        self.engine.backward(grad_rgb)
        if self.hooks is not None:
            self.hooks.regularise(self.generator)
        return mse, grad_tone

    def _graph_key(self) -> tuple:
        tones = [] if self.tone_optimiser is None else list(self.tone_optimiser.params)
        if self.tonemapper is not None:
            tones += list(self.tonemapper.buffers())
        return held_key(self.engine, self._view_prior_weight(), tones)

    def _view_prior_weight(self) -> float:
        """lambda_sh_view while the prior acts (the tone-mapped model's first part of training, see
        ToneMapConfig), else 0."""
        if self.step >= self.settings.view_prior_end():  # 0 without the tone mapper
            return 0.0
        return self.settings.tonemap.lambda_sh_view

    def upsample(self) -> str:
        """After a step, the resample and pruning the schedule asks for at this step (a line saying what
        was done; '' when nothing was): the other half of a step as `run` takes it, for callers that
        drive `train_step` themselves."""
        if self.hooks is None:
            return ""
        return self.hooks.upsample(self.step, self._training_rays) or ""

    def check_exposures(self) -> str:
        """After a step, the check whether the exposures are held to the stated ones, at the step the
        schedule has it (`train/exposure_hold.py`); the line saying what it decided ('' at other steps).
        With `upsample`, what `run` does between steps."""
        if self.tonemapper is None or self.step != self.exposure_check:
            return ""
        return exposure_hold.check_exposures(self.tonemapper, self.settings.tonemap, self.stated, self.step)

    def _training_rays(self, stride: int):
        return ((b.origins, b.dirs) for b in self.pool.iter_all(stride))

    def run(self, progress: bool = True) -> Model:
        """Train to `n_iters`, then write the model. SIGINT or SIGTERM stop it cleanly: a checkpoint of
        the step in hand is written and `TrainingStopped` raised. The run folder is unlocked at the end."""
        try:
            with stop_signals() as stop:
                return self._run(progress, stop)
        finally:
            self.folder.release()

    def _run(self, progress: bool, stop: StopRequest) -> Model:
        cfg = self.cfg
        self.folder.write_config(cfg.to_dict())
        n = cfg.optim.n_iters
        last_checkpoint = time.perf_counter()
        with WriterThread() as writer, (self.out_dir / LOG_FILE).open("a") as file:
            log = TrainLog(file, n, self.step, progress)
            while self.step < n:
                log.add(self.train_step())
                failure = self.step_graph.failure if self.step_graph is not None else None
                if failure:
                    log.say(f"CUDA graph: the capture failed ({failure}); stepping without it", once=True)
                if self.step % cfg.log_every == 0 or self.step == n:
                    log.write(self.step, self.engine.log_fields(self.step))
                log.say(self.upsample())
                log.say(self.check_exposures())
                if stop.signal is not None:
                    writer.wait()
                    self.save_checkpoint()
                    log.close()
                    raise TrainingStopped(stop.signal, self.step, self.checkpoint_path(self.step))
                if checkpoint_due(cfg, self.step, time.perf_counter() - last_checkpoint):
                    self._checkpoint_during_run(writer)
                    last_checkpoint = time.perf_counter()
            log.close()
            model, self.end_notes = finish_run(self, writer)
            return model


def train_model(
    scene: SceneData,
    config: TrainConfig,
    out: str | Path,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = False,
) -> Model:
    """What `hdrplenoxels train` does, for a script: train `config` on `scene` into the run folder `out`
    (checkpoints, log, model.npz; `resume` one stopped there, `overwrite` one finished there) and return
    the model, its tone controller fitted when it learned tones."""
    return Trainer(scene, config, Path(out), resume=resume, overwrite=overwrite).run(progress)
