"""The training loop: one loop over any radiance-field engine, with the tone-mapping module after it.

One iteration (docs/method.md, "Training"): a uniform batch from the ray pool, the engine's forward,
the loss through the tone-mapping module, the engine's backward from d loss / d radiance, its
regularisers and optimiser step, then the tone parameters' step; on CUDA all of it replayed from a CUDA
graph (`train/step_graph.py`). The engine resamples itself on its schedule; checkpoints are written
periodically and at the end. Nothing here depends on the backend.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hdrplenoxels.core.atomic import atomic_write_text, ensure_space
from hdrplenoxels.core.devices import pick_device
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.run_lock import RunLock
from hdrplenoxels.core.signals import StopRequest, stop_signals
from hdrplenoxels.core.writer_thread import WriterThread
from hdrplenoxels.data.camera_spread import exif_evs
from hdrplenoxels.data.placement import choose_mode, setup_scene
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.io import write_npz
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.render.fields import Field
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.tonemap.plots import plot_tone_params
from hdrplenoxels.train.config import TrainConfig, tv_scale
from hdrplenoxels.train.controller_fit import controller_note, fit_controller
from hdrplenoxels.train.engines import Engine, engine_class, engine_key
from hdrplenoxels.train.field_io import field_arrays, load_field_with_background
from hdrplenoxels.train.free_space import (
    ObservedLines,
    SightSegments,
    line_stretches,
    near_segments,
    observed_lines,
)
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.optim import ExpSchedule, StepClock, StepRates, make_tone_optimiser
from hdrplenoxels.train.ray_pool import RayPool, pooled_views
from hdrplenoxels.train.run_state import (
    field_path,
    is_run_state,
    load_run_state,
    resumable,
    settings_changed,
    state_arrays,
)
from hdrplenoxels.train.step_graph import CudaCapture, StepGraph, uses_step_graph
from hdrplenoxels.train.tone_choice import EXIF_STOPS, choose_tone_mapping
from hdrplenoxels.train.view_coverage import pooled_frustums

CHECKPOINT_DIR = "checkpoints"
LOG_FILE = "train_log.jsonl"
TONE_PARAMS_FILE = "tone_params.json"
TONE_PLOT_FILE = "tone_params.png"


def _camera_truth(scene: SceneData) -> dict | None:
    """The simulated cameras of a `synth` dataset (camera_truth.json beside it), for plots only."""
    folder = scene.source if scene.source.is_dir() else scene.source.parent
    path = folder / "camera_truth.json"
    try:
        truth = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(truth, dict) or not isinstance(truth.get("views"), list):
        return None  # not synth's file: the plot goes without truth
    return truth if len(truth["views"]) == len(scene.names) else None


def _prefixed(arrays: dict, prefix: str) -> dict:
    return {k.removeprefix(prefix): v for k, v in arrays.items() if k.startswith(prefix)}


def mse_to_psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


def checkpoints(run: Path) -> list[Path]:
    """A run folder's complete checkpoints, oldest first (a write in progress is a temporary file, never
    listed)."""
    return sorted((Path(run) / CHECKPOINT_DIR).glob("step_*.npz"))


def resumable_checkpoints(run: Path) -> list[Path]:
    """The checkpoints `--resume` may continue from, oldest first: all but a finished run's last one
    (`train/run_state.py`) whose model file is missing or of another step (killed between the two)."""
    return [p for p in checkpoints(run) if resumable(p)]


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
        self.lock = RunLock(self.out_dir).acquire()  # before anything in the folder is read or removed
        usable = resumable_checkpoints(self.out_dir) if resume else []
        if resume and not usable:
            found = checkpoints(self.out_dir)
            if found and (self.out_dir / MODEL_FILE).exists():  # a finished run's: never thrown away
                raise InputError(
                    found[-1],
                    f"its training state does not go with the run's {MODEL_FILE} (another step or "
                    "configuration); pass --overwrite to start the run over",
                )
            resume, overwrite = False, True  # killed before its first checkpoint: nothing to lose
        self.resumed = resume
        if not resume:
            self._claim_out_dir(overwrite)
        self.scene = scene
        cameras, self.geometry = setup_scene(scene, cfg.scene_mode)
        self.cameras = cameras
        # What trains: `cfg` with its None defaults filled from the capture (config.json keeps `cfg`).
        photos = len(pooled_views(scene.train_ids, scene.test_ids, cfg.holdout))  # those the grid learns from
        scale = tv_scale(cfg.optim.tv_photos, photos)
        tone_mapping, why = self._tone_mapping(cfg, scene)
        self.settings = cfg.resolved(
            background_brightness=scene.background_brightness,
            wants_background=self.geometry.wants_background,
            levels=self.geometry.levels,
            photos=photos,
            tone_mapping=tone_mapping,
        )
        on = self.settings.tonemap.enabled
        note = f"tone mapping: {'on' if on else 'off'} ({why})"
        if cfg.tonemap.enabled is None:
            note += "; --no-tonemap trains plain Plenoxels" if on else "; --tonemap learns a tone per photo"
        self.config_notes.append(note)
        if scale != 1.0:
            self.config_notes.append(
                f"the grid's TV weights x{scale:.3g} for {photos} photos "
                f"(optim.tv_photos={cfg.optim.tv_photos:g})"
            )
        r = self.settings.render
        self.render_opt = RenderOptions(r.step_size, r.sigma_thresh, r.stop_thresh, r.background_brightness)
        self.pool = RayPool(
            scene.images, cameras, self.geometry, scene.train_ids, scene.test_ids, cfg.holdout, self.device
        )
        t = cfg.tonemap
        self.tone_lr = ExpSchedule(t.lr, t.lr_final, t.lr_decay_steps)
        self.tone_rates = StepRates([self.tone_lr], self.device, cfg.optim.n_iters)
        self.step = 0
        # The step's number on the device, which a replayed step reads and advances (`StepClock`).
        self.step_count = torch.zeros(1, dtype=torch.int64, device=self.device)
        # Every random draw of a step (rays, TV cells, free-space samples) is made on the training device:
        # a GPU's step then never waits for numbers from the host.
        self.generator = torch.Generator(self.device).manual_seed(cfg.seed)
        self.step_graph: StepGraph | None = None  # the repeating part of a step from a CUDA graph
        if uses_step_graph(cfg, self.device.type):
            self.step_graph = StepGraph(CudaCapture(self.generator))
        engine = engine_class(engine_key(cfg))
        field = engine.new_field(self.settings, self.geometry, len(self.cameras), self.device)
        background = engine.new_background(self.settings, self.geometry, field)
        self.engine: Engine = engine(field, self.settings, self.render_opt, background)
        self.sight_priors_note = self._use_sight_priors()
        self.coverage_note = self._restrict_to_views()
        self.controller_note = ""  # what `run` fitted as the tone controller, for the command line
        self.gauge_note = ""  # ... and the scale its EVs are in
        self.tonemapper = self._initial_tonemapper(resume)
        self.tone_optimiser = make_tone_optimiser(self.tonemapper) if self.tonemapper is not None else None
        if resume:
            self._resume(usable[-1])

    # ----------------------------------------------------------------------------- state
    def _claim_out_dir(self, overwrite: bool) -> None:
        """A new run never mixes with an old one's checkpoints and log (a later --resume would pick them)."""
        old = [self.out_dir / CHECKPOINT_DIR, self.out_dir / LOG_FILE, self.out_dir / MODEL_FILE]
        if not any(p.exists() for p in old):
            return
        if not overwrite:
            raise InputError(
                self.out_dir,
                "already holds a training run; pass --resume to continue it or --overwrite to start over",
            )
        shutil.rmtree(old[0], ignore_errors=True)
        for p in old[1:]:
            p.unlink(missing_ok=True)

    @staticmethod
    def _tone_mapping(cfg: TrainConfig, scene: SceneData) -> tuple[bool, str]:
        """Whether the run learns a tone per photo, and why in words: as configured, or, left to the
        photos (None), as the training views' camera settings vary (`choose_tone_mapping`); a setting that
        acts through the tone mapper turns it on."""
        if cfg.tonemap.enabled is not None:
            return cfg.tonemap.enabled, "tonemap.enabled, --tonemap / --no-tonemap"
        if cfg.tone_switches():
            return True, f"{cfg.tone_switches()[0]} acts through it"
        on, why, _ = choose_tone_mapping(scene, list(scene.train_ids))
        return on, why

    def _initial_tonemapper(self, resume: bool) -> ToneMapper | None:
        """The per-image tone mapper, white balance and reference from training pixels only (docs/method.md,
        "Fixes to the reference code")."""
        t = self.settings.tonemap
        if not t.enabled:
            return None
        n = len(self.cameras)
        tm = ToneMapper(n, self.cameras.sizes, t, camera_ids=self.cameras.body_ids()).to(self.device)
        if t.known_exposure and self.scene.exposures is not None:
            tm.set_known_exposures(torch.as_tensor(self.scene.exposures))
        elif t.known_exposure and not resume:  # a resumed run restores them from its checkpoint
            raise InputError(self.scene.source, "known-exposure mode needs an EV per view (--known-exposure)")
        if t.wb_init_from_data:
            tm.init_from_images(self.pool.linear_channel_means(n, t.init_gamma), list(self.scene.train_ids))
        else:
            tm.set_reference(self.scene.train_ids[0])
        if t.exposure_init_from_metadata and not resume:
            evs = self.scene.extras.get("exposure_init_ev")
            if evs is None:
                raise InputError(
                    self.scene.source,
                    "no exposure metadata to start from (EXIF from `process`, HDR-NeRF exposure times)",
                )
            tm.init_exposures(torch.as_tensor(np.asarray(evs)))
        return tm

    def model(self) -> Model:
        """The model as trained so far (the grid settled first: `Engine.settle`)."""
        self.engine.settle()
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
        return self.out_dir / CHECKPOINT_DIR / f"step_{step:07d}.npz"

    def save_checkpoint(self) -> Path:
        """Write the checkpoint of the step in hand, now."""
        path = self.checkpoint_path(self.step)
        self._write_checkpoint(path, self.checkpoint_arrays())
        return path

    def checkpoint_arrays(self) -> dict[str, np.ndarray]:
        """What a checkpoint of the step in hand holds, as host arrays: on a GPU copies, on a CPU mostly
        views of the training state (`field_io.field_arrays`), valid until the next step changes it."""
        meta, extra = self._training_state()
        field, background = self.engine.field, self.engine.background
        return field_arrays(field, meta=meta, extra_arrays=extra, background=background)

    def _training_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """A checkpoint's meta and its arrays beside the field: the optimisers', sampler's and tones'."""
        model = self.model()
        extra = model.extra_arrays()
        extra.update({f"optim/{k}": v for k, v in self.engine.state_arrays().items()})
        extra["rng/state"] = self.generator.get_state().numpy()
        if self.tone_optimiser is not None:
            extra.update({f"tonemap_optim/{k}": v for k, v in self.tone_optimiser.state_arrays().items()})
        meta = model.meta()
        meta["level"] = self.engine.level
        return meta, extra

    def _write_checkpoint(self, path: Path, arrays: dict[str, np.ndarray], prune: bool = True) -> None:
        write_npz(path, arrays)
        if prune:
            self._prune_checkpoints()

    def _prune_checkpoints(self) -> None:
        keep = self.cfg.keep_checkpoints
        for stale in checkpoints(self.out_dir)[:-keep] if keep > 0 else []:  # the new one is complete first
            stale.unlink(missing_ok=True)

    def _checkpoint_during_run(self, writer: WriterThread) -> None:
        """A periodic checkpoint: in the background where `background_checkpoints` says so, from a host
        snapshot (one at a time: the previous write is waited for first, so the host holds one)."""
        writer.wait()
        path, arrays = self.checkpoint_path(self.step), self.checkpoint_arrays()
        if not self.background_checkpoints:
            self._write_checkpoint(path, arrays)
            return
        if self.device.type == "cpu":  # views of what the next steps change
            arrays = {name: np.array(value, copy=True) for name, value in arrays.items()}
        self._write_behind(writer, path, arrays)

    def _write_behind(
        self, writer: WriterThread, path: Path, arrays: dict[str, np.ndarray], prune: bool = True
    ) -> Future:
        """Queue a checkpoint's write; one that cannot fit on the disk is refused here, at once."""
        ensure_space(path, sum(a.nbytes for a in arrays.values()))
        return writer.submit(self._write_checkpoint, path, arrays, prune)

    def _resume(self, checkpoint: Path) -> None:
        """Continue from `checkpoint`, the newest of `resumable_checkpoints`."""
        if is_run_state(checkpoint):  # a finished run's last checkpoint: its field is the model's
            meta, extra = load_run_state(checkpoint)
            field, background, _, _ = load_field_with_background(field_path(checkpoint, meta), self.device)
        else:
            field, background, meta, extra = load_field_with_background(checkpoint, device=self.device)
        if meta.get("kind") != "model":
            raise InputError(checkpoint, "not a training checkpoint of this project")
        try:
            saved = TrainConfig.from_dict(meta["config"])
        except (KeyError, ValueError) as e:
            raise InputError(checkpoint, f"cannot read the run's configuration: {e}") from None
        changed = settings_changed(saved.to_dict(), self.cfg.to_dict())
        if changed:
            raise InputError(
                checkpoint,
                f"a resumed run keeps its configuration, but these settings differ: {', '.join(changed)}",
            )
        try:
            self._restore(field, background, meta, extra)
        except (KeyError, ValueError, TypeError, IndexError, OverflowError, RuntimeError) as e:
            # The same code restores every checkpoint this project writes: what fails is the file.
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(checkpoint, f"its training state does not fit this run ({reason})") from None
        self._forget_log_after(self.step)  # last: a refused resume writes nothing

    def _restore(self, field: Field, background: MSIBackground | None, meta: dict, extra: dict) -> None:
        """The engine, step, sampler and tone state of a checkpoint."""
        self.engine.restore(field, int(meta["level"]), _prefixed(extra, "optim/"), background)
        self.step = int(meta["step"])
        self.step_count.fill_(self.step)
        restore_generator(self.generator, np.asarray(extra["rng/state"]), self.cfg.seed + self.step)
        if self.tonemapper is not None:
            self.tonemapper.load_state_arrays(_prefixed(extra, "tonemap/"))
            self.tone_optimiser = make_tone_optimiser(self.tonemapper)
            self.tone_optimiser.load_state_arrays(_prefixed(extra, "tonemap_optim/"))

    def _forget_log_after(self, step: int) -> None:
        """Drop log lines of steps a killed run made after its last checkpoint: they are trained again."""
        path = self.out_dir / LOG_FILE
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

    def _use_sight_priors(self) -> str | None:
        """Hand the engine the free-space and surface priors' segments when they are on; a line saying
        what they use."""
        o, lines = self.cfg.optim, self.scene.sight_lines
        if o.lambda_free_space <= 0 and o.lambda_surface <= 0:
            return None
        why = self._sight_priors_off()
        if why is not None:
            return f"free space and surfaces: off ({why})"
        tests = set(self.scene.test_ids)
        views = [i for i in self.scene.train_ids if i not in tests]
        cams, world_from_data = self.cameras, self.geometry.world_from_data
        seen = observed_lines(lines, cams.c2w, world_from_data, views)
        margin, notes = o.free_space_margin, []
        if o.lambda_free_space > 0:
            segments = line_stretches(seen, 0.0, 1.0 - margin, self.device)
            note = (
                f"free space: {len(segments):,} lines of sight to {len(lines.points):,} sparse points "
                f"from {len(views)} training views (weight {o.lambda_free_space:g})"
            )
            if o.free_space_near > 0:
                near, words = self._near_cameras(seen, tests)
                segments = segments + near
                note += f", and {len(near):,} near the cameras ({words})"
            self.engine.use_free_space(segments)
            notes.append(note)
        if o.lambda_surface > 0:
            windows = line_stretches(seen, 1.0 - margin, 1.0 + o.surface_behind, self.device)
            self.engine.use_surface(windows)
            notes.append(f"surfaces: {len(windows):,} windows at the points (weight {o.lambda_surface:g})")
        return "; ".join(notes)

    def _near_cameras(self, seen: ObservedLines, tests: set[int]) -> tuple[SightSegments, str]:
        """The near-camera segments of the training views and of the pooled test views' left halves; what
        the note says of them."""
        cams, fraction = self.cameras, self.cfg.optim.free_space_near
        pooled = zip(self.pool.image_ids.tolist(), self.pool.used_width.tolist(), strict=True)
        halves = {i: w for i, w in pooled if i in tests}
        near = near_segments(seen, cams.c2w, cams.intrinsics, cams.sizes, fraction, self.device, halves)
        words = f"{fraction:g} of their nearest points"
        if not halves:
            return near, words
        held = "1 test view's left half" if len(halves) == 1 else f"{len(halves)} test views' left halves"
        return near, f"{words}; {held} among them"

    def _restrict_to_views(self) -> str | None:
        """Keep the grid to voxels `grid.min_views` pooled views see, when set; a line saying what it
        dropped."""
        k = self.cfg.grid.min_views
        if k <= 0:
            return None
        if self.cfg.model != "grid" or self.geometry.mode != "bbox":
            where = f"{self.cfg.model}, {self.geometry.mode}"
            return f"views per voxel: off (it is the voxel grid's, in a box scene; this is {where})"
        p = self.pool
        frustums = pooled_frustums(p.c2w, p.intrinsics, p.image_ids, p.used_width, p.heights)
        before = self.engine.field.num_voxels
        self.engine.restrict_to_views(frustums, k)
        dropped = before - self.engine.field.num_voxels
        return f"views per voxel: at least {k}; {dropped:,} of {before:,} voxels seen by fewer dropped"

    def _sight_priors_off(self) -> str | None:
        """Why the sight priors cannot run on this model and dataset, or None."""
        if self.cfg.model != "grid":
            return "it is the voxel grid's prior; the NeRF engine ignores it"
        if self.scene.sight_lines is None:
            return "the dataset has no sparse points"
        if self.geometry.mode != "bbox":
            return "NDC has no metric segments"
        return None

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
        self.engine.after_step(self.step)
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
        self.engine.regularise(self.generator)
        return mse, grad_tone

    def _graph_key(self) -> tuple:
        """What a captured step holds the addresses of, which a resample or a resume replaces (the
        grid's and the background's tensors, the tone parameters and the tone mapper's buffers: its
        reference, sizes and curve groups), and the view prior's weight, a constant of the recorded work
        that the schedule switches off once (`step_graph.StepGraph`)."""
        field, background = self.engine.field, self.engine.background
        held = [field.links, field.density, field.sh]
        if background is not None:
            held += [background.density, background.color]
        if self.tone_optimiser is not None:
            held += self.tone_optimiser.params
        if self.tonemapper is not None:
            held += list(self.tonemapper.buffers())
        return (self.engine.graph_key(), self._view_prior_weight(), *(t.data_ptr() for t in held))

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
        return self.engine.upsample(self.step, self._training_rays)

    def _training_rays(self, stride: int):
        return ((b.origins, b.dirs) for b in self.pool.iter_all(stride))

    def run(self, progress: bool = True) -> Model:
        """Train to `n_iters`, then write the model. SIGINT or SIGTERM stop it cleanly: a checkpoint of
        the step in hand is written and `TrainingStopped` raised. The run folder is unlocked at the end."""
        try:
            with stop_signals() as stop:
                return self._run(progress, stop)
        finally:
            self.lock.release()

    def _run(self, progress: bool, stop: StopRequest) -> Model:
        cfg = self.cfg
        self.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.out_dir / "config.json", json.dumps(cfg.to_dict(), indent=2))
        log_path = self.out_dir / LOG_FILE
        n = cfg.optim.n_iters
        bar = tqdm(total=n, initial=self.step, disable=not progress, dynamic_ncols=True, mininterval=0.5)
        t0 = last_checkpoint = time.perf_counter()
        losses: list[torch.Tensor] = []
        graph_failure_shown = False
        with WriterThread() as writer, log_path.open("a") as log:
            while self.step < cfg.optim.n_iters:
                losses.append(self.train_step())
                bar.update(1)
                if self.step_graph is not None and self.step_graph.failure and not graph_failure_shown:
                    failure = self.step_graph.failure
                    bar.write(f"CUDA graph: the capture failed ({failure}); stepping without it")
                    graph_failure_shown = True
                if self.step % cfg.log_every == 0 or self.step == cfg.optim.n_iters:
                    mse = float(torch.stack(losses).mean())
                    losses.clear()
                    engine_fields = self.engine.log_fields(self.step)
                    entry = {"step": self.step, "mse": mse, "psnr": mse_to_psnr(mse), **engine_fields}
                    entry["seconds"] = time.perf_counter() - t0
                    log.write(json.dumps(entry) + "\n")
                    log.flush()  # so that a running job's progress can be followed (tail -f)
                    shown = {k: f"{v:.3g}" if isinstance(v, float) else v for k, v in engine_fields.items()}
                    bar.set_postfix(loss=f"{mse:.2e}", psnr=f"{entry['psnr']:.2f}", **shown)
                message = self.upsample()
                if message:
                    bar.write(message)
                since = time.perf_counter() - last_checkpoint
                by_steps = (
                    cfg.checkpoint_every
                    and self.step % cfg.checkpoint_every == 0
                    and since >= cfg.checkpoint_gap_seconds
                )
                by_time = cfg.checkpoint_seconds and since >= cfg.checkpoint_seconds
                if stop.signal is not None:
                    writer.wait()
                    self.save_checkpoint()
                    bar.close()
                    raise TrainingStopped(stop.signal, self.step, self.checkpoint_path(self.step))
                if by_steps or by_time:
                    self._checkpoint_during_run(writer)
                    last_checkpoint = time.perf_counter()
            bar.close()
            return self._finish(writer)

    def _fit_gauge(self) -> str:
        """The exponent that puts the tone-mapped outputs (the EXR, the learned EVs, `--ev`) in a linear
        scale, and a line saying which: fitted to the known exposures, or to the photos' EXIF exposures
        where they vary (true stops either way), else where the learned response looks like a camera's
        (`output_prior_gamma`: a learned scale). Self-calibration alone cannot tell (docs/method.md,
        "Gauge")."""
        tm, t = self.tonemapper, self.cfg.tonemap
        if t.known_exposure:
            return f"EV in true stops: fitted to the known exposures (a = {tm.fit_exponent_to_known():.3f})"
        evs = exif_evs(self.scene)
        why = "the photos have no EXIF exposure"
        if evs is not None and float(evs.max() - evs.min()) > EXIF_STOPS:
            try:
                a = tm.fit_exponent_to_exposures(torch.as_tensor(evs))
                span = float(evs.max() - evs.min())
                return (
                    f"EV in true stops: fitted to the photos' EXIF exposures ({span:.2f} stops; a = {a:.3f})"
                )
            except ValueError as e:
                why = f"the learned exposures do not follow the photos' EXIF ones ({e})"
        elif evs is not None:
            why = "the photos' EXIF exposures do not vary"
        if t.output_prior_gamma:
            tm.fit_exponent_to_response_prior(t.output_prior_gamma)
        return f"EV in the learned scale ({why}; --known-exposure gives true stops)"

    def _finish(self, writer: WriterThread) -> Model:
        """After the last step: the final checkpoint and the tone plot are written on the writer thread
        while the tones' gauge and controller are fitted here. The final checkpoint is a run state
        (`train/run_state.py`): the training state without the field, which the model file holds.
        Nothing after the last step changes the optimisers' state, so it is written from views of it
        (the tone mapper's arrays, which the gauge's fit changes, are copies). Older checkpoints are
        pruned only once the model is written too: until then the state is not one `--resume` takes."""
        writer.wait()
        final, written = self.checkpoint_path(self.step), None
        # A state left by a run killed before its model is rewritten: the model will be this run's.
        if not final.exists() or not resumable(final):
            meta, extra = self._training_state()
            written = self._write_behind(writer, final, state_arrays(meta, extra, MODEL_FILE), prune=False)
        if self.tonemapper is not None:
            with torch.no_grad():
                self.tonemapper.constrain()  # before the gauge: outputs invert the final curves
            self.gauge_note = self._fit_gauge()
        model = self.model()
        params = None
        if self.tonemapper is not None:  # the learned tones, readable without loading the model
            params = self.tonemapper.parameters_dict() | {
                "names": self.scene.names,
                "ev_scale": self.gauge_note,
            }
            writer.submit(plot_tone_params, params, self.out_dir / TONE_PLOT_FILE, _camera_truth(self.scene))
            model.controller, errors = fit_controller(model, self.cfg.backend)
            self.controller_note = controller_note(model.controller, errors)
        if written is not None:
            written.result()
        model.save(self.out_dir / MODEL_FILE)  # beside the plot, if it is still being drawn
        if written is not None:  # the older checkpoints go once both halves of the last are written
            self._prune_checkpoints()
        if params is not None:
            atomic_write_text(self.out_dir / TONE_PARAMS_FILE, json.dumps(params))
        writer.wait()
        return model


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
