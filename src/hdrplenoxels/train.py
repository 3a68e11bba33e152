"""Plenoxels training loop (method-spec §3): random ray batches, MSE, TV gradients, RMSProp, upsampling.

One iteration: learning rates from the schedules, a uniform batch from the ray pool, render, MSE,
backward, TV gradients on a random contiguous run of cells, RMSProp on density and SH. The grid is
resampled to the next resolution every `upsample_every` steps (optimiser state discarded), and
checkpoints are written periodically and at the end.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hdrplenoxels.atomic import atomic_write_text
from hdrplenoxels.camera_plots import plot_camera_params
from hdrplenoxels.config import TrainConfig
from hdrplenoxels.data.rays import RayPool
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.errors import InputError
from hdrplenoxels.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.grid_io import load_grid, save_grid
from hdrplenoxels.model import MODEL_FILE, Model
from hdrplenoxels.optim import ExpSchedule, GridRMSProp
from hdrplenoxels.pruning import max_weight_score
from hdrplenoxels.render import RenderOptions, render_rays
from hdrplenoxels.render.ray_order import training_order
from hdrplenoxels.render.sample_record import SampleRecord
from hdrplenoxels.scene_setup import setup_scene
from hdrplenoxels.sh import basis_dim_for_degree
from hdrplenoxels.tonemap import (
    ToneMapper,
    make_optimizer,
)
from hdrplenoxels.tv import sample_tv_cells, tv_grad_

CHECKPOINT_DIR = "checkpoints"
LOG_FILE = "train_log.jsonl"
CAMERA_PARAMS_FILE = "camera_params.json"
CAMERA_PLOT_FILE = "camera_params.png"


def pick_device(name: str) -> torch.device:
    """`auto`: CUDA when torch sees a GPU, else the CPU; otherwise the named device, which must exist
    (asking for a missing GPU is an `InputError`, not torch's traceback deep inside the first kernel)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise InputError(None, f"--device {name}: not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise InputError(None, f"--device {name}: the Warp kernels run on cpu or cuda only")
    if not torch.cuda.is_available():
        why = "this torch is a CPU-only build" if torch.version.cuda is None else "torch sees no GPU"
        raise InputError(None, f"--device {name}: no CUDA device ({why}); use --device cpu or auto")
    if device.index is not None and device.index >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise InputError(None, f"--device {name}: torch sees {count} GPU(s), numbered from 0")
    return device


# Settings that may change when a run is resumed: they do not change what is being optimised.
RESUMABLE_CHANGES = {"optim.n_iters", "backend", "device", "log_every", "checkpoint_every"}


def config_changes(saved: TrainConfig, new: TrainConfig) -> list[str]:
    """Dotted names of settings that differ between two configs, other than those a resume may change."""

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    a, b = flat(saved.to_dict()), flat(new.to_dict())
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k) and k not in RESUMABLE_CHANGES)


def _camera_truth(scene: SceneData) -> dict | None:
    """The simulated cameras of a `synth` dataset (camera_truth.json beside it), for plots only."""
    folder = scene.source if scene.source.is_dir() else scene.source.parent
    path = folder / "camera_truth.json"
    try:
        truth = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return truth if len(truth.get("views", [])) == len(scene.names) else None


def _prefixed(arrays: dict, prefix: str) -> dict:
    return {k.removeprefix(prefix): v for k, v in arrays.items() if k.startswith(prefix)}


def mse_to_psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


@dataclass
class Schedules:
    sigma: ExpSchedule
    sh: ExpSchedule
    tonemap: ExpSchedule

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> Schedules:
        o, t = cfg.optim, cfg.tonemap
        return cls(
            ExpSchedule(
                o.lr_sigma, o.lr_sigma_final, o.lr_decay_steps, o.lr_sigma_delay_steps, o.lr_sigma_delay_mult
            ),
            ExpSchedule(o.lr_sh, o.lr_sh_final, o.lr_decay_steps),
            ExpSchedule(t.lr, t.lr_final, t.lr_decay_steps),
        )


class Trainer:
    """Owns the grid, optimiser and ray pool of one run; `run()` trains to `n_iters`."""

    def __init__(
        self, scene: SceneData, cfg: TrainConfig, out_dir: Path, resume: bool = False, overwrite: bool = False
    ):
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        if not resume:
            self._claim_out_dir(overwrite)
        self.device = pick_device(cfg.device)
        self.scene = scene
        cameras, self.geometry = setup_scene(scene, cfg.scene_mode)
        self.cameras = cameras
        background = cfg.render.background
        if background is None:
            background = scene.background
        r = cfg.render
        self.render_opt = RenderOptions(r.step_size, r.sigma_thresh, r.stop_thresh, background)
        self.pool = RayPool(
            scene.images, cameras, self.geometry, scene.train_ids, scene.test_ids, cfg.holdout, self.device
        )
        self.schedules = Schedules.from_config(cfg)
        self.optimizer = GridRMSProp(beta=cfg.optim.rms_beta)
        self.step = 0
        self.level = 0
        self._grads: GridGradients | None = None
        self._sample_record: SampleRecord | None = None
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.grid = self._initial_grid()
        self.tonemapper = self._initial_tonemapper(resume)
        self.tone_optimizer = make_optimizer(self.tonemapper) if self.tonemapper is not None else None
        if resume:
            self._resume()

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

    def _initial_grid(self) -> SparseGrid:
        g = self.geometry
        return SparseGrid.create(
            self.cfg.grid.reso_schedule[0],
            g.center,
            g.radius,
            basis_dim_for_degree(self.cfg.grid.sh_degree),
            self.cfg.grid.init_sigma,
            self.device,
        )

    def _initial_tonemapper(self, resume: bool) -> ToneMapper | None:
        """The per-image camera model, white balance and reference from training pixels only (§7.5)."""
        t = self.cfg.tonemap
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
        return Model(
            grid=self.grid,
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
        )

    def checkpoint_path(self, step: int) -> Path:
        return self.out_dir / CHECKPOINT_DIR / f"step_{step:07d}.npz"

    def save_checkpoint(self) -> Path:
        path = self.checkpoint_path(self.step)
        model = self.model()
        extra = model.extra_arrays()
        extra.update({f"optim/{k}": v for k, v in self.optimizer.state_dict().items()})
        extra["rng/state"] = self.generator.get_state().numpy()
        if self.tone_optimizer is not None:
            extra.update({f"tonemap_optim/{k}": v for k, v in self.tone_optimizer.state_arrays().items()})
        meta = model.meta()
        meta["level"] = self.level
        save_grid(path, self.grid, meta=meta, extra_arrays=extra)
        return path

    def _resume(self) -> None:
        ckpts = sorted((self.out_dir / CHECKPOINT_DIR).glob("step_*.npz"))
        if not ckpts:
            raise InputError(self.out_dir, "--resume given but the run has no checkpoints to resume from")
        grid, meta, extra = load_grid(ckpts[-1], device=self.device)
        if meta.get("kind") != "model":
            raise InputError(ckpts[-1], "not a training checkpoint of this project")
        changed = config_changes(TrainConfig.from_dict(meta["config"]), self.cfg)
        if changed:
            raise InputError(
                ckpts[-1],
                f"a resumed run keeps its configuration, but these settings differ: {', '.join(changed)}",
            )
        self.grid = grid
        self.step = int(meta["step"])
        self.level = int(meta["level"])
        self.optimizer.load_state_dict(_prefixed(extra, "optim/"))
        # The batch sampler continues exactly where it stopped, so a resumed run equals an unbroken one.
        self.generator.set_state(torch.from_numpy(extra["rng/state"]))
        if self.tonemapper is not None:
            self.tonemapper.load_state_arrays(_prefixed(extra, "tonemap/"))
            self.tone_optimizer = make_optimizer(self.tonemapper)
            self.tone_optimizer.load_state_arrays(_prefixed(extra, "tonemap_optim/"))

    # ----------------------------------------------------------------------------- loop
    def train_step(self) -> torch.Tensor:
        """One iteration (§3.9); returns the photometric MSE of the batch, a 0-d tensor on the device
        (read only when logging: reading it every step would make the CPU wait for the GPU)."""
        cfg = self.cfg
        lr_sigma = self.schedules.sigma(self.step)
        lr_sh = self.schedules.sh(self.step)
        batch = self.pool.sample(cfg.optim.batch_size, self.generator)
        grads = self._grid_gradients()
        fused = cfg.backend == "warp"
        if fused:  # forward kernel; the backward kernel adds straight into the gradient buffers
            from hdrplenoxels.render.occupancy import occupancy_for  # these start Warp
            from hdrplenoxels.render.warp_backend import accumulate_backward, render_forward

            order = training_order(self.grid, batch.origins, batch.dirs)
            if order is not None:  # CPU threads march rays in turn: neighbours should share voxels
                batch = batch.reordered(order)
            record = self._record_for(len(batch.origins))
            rgb = render_forward(self.grid, batch.origins, batch.dirs, self.render_opt, record=record)
            rgb.requires_grad_(True)
            grid_inputs = [rgb]
        else:  # the PyTorch reference through autograd
            self.grid.density.requires_grad_(True)
            self.grid.sh.requires_grad_(True)
            rgb = render_rays(self.grid, batch.origins, batch.dirs, self.render_opt, "torch")
            grid_inputs = [self.grid.density, self.grid.sh]
        tone_params = [] if self.tone_optimizer is None else self.tone_optimizer.params
        if self.tonemapper is None:
            pred = rgb
            loss = torch.mean((pred - batch.target) ** 2)
        else:
            pred = self.tonemapper(rgb, batch.image_ids, batch.rows, batch.cols, training=True)
            loss = self.tonemapper.loss(pred, batch.target)
        g_grid_inputs = torch.autograd.grad(loss, [*grid_inputs, *tone_params])
        g_tone = g_grid_inputs[len(grid_inputs) :]
        if fused:
            accumulate_backward(
                self.grid,
                batch.origins,
                batch.dirs,
                rgb.detach(),
                g_grid_inputs[0],
                self.render_opt,
                grads,
                record=record,
            )
        else:
            grads.density[0].add_(g_grid_inputs[0])
            grads.sh[0].add_(g_grid_inputs[1])
        self._add_tv(grads)
        self._add_view_prior(grads)
        # The fused update visits only the rows this step's gradients touched (the result of a dense
        # update) and marks the renderer's occupancy for the new density in the same pass.
        occupancy = occupancy_for(self.grid) if fused else None
        self.optimizer.step_accumulated(
            [self.grid.density, self.grid.sh],
            [grads.density, grads.sh],
            [lr_sigma, lr_sh],
            fused,
            occupancy,
            touched=grads.take_touched() if fused else None,
        )
        if self.tone_optimizer is not None:
            self.tone_optimizer.step(list(g_tone), self.schedules.tonemap(self.step))
        self.step += 1
        return torch.mean((pred.detach() - batch.target) ** 2)

    def _grid_gradients(self) -> GridGradients:
        """The gradient buffers of the current grid (new ones only after a resample)."""
        if self._grads is None or not self._grads.fits(self.grid):
            self._grads = None  # free the old resolution's buffers before sizing and allocating new ones
            parts = gradient_parts(self.grid) if self.cfg.backend == "warp" else 1
            self._grads = GridGradients(self.grid, parts)
        return self._grads

    def _record_for(self, rays: int) -> SampleRecord | None:
        """The forward's record of a batch's samples, for the backward (reused from step to step);
        None where the kernels keep none (CUDA)."""
        from hdrplenoxels.render.warp_backend import records_samples
        from hdrplenoxels.warp_runtime import warp_device

        if not records_samples(warp_device(self.grid.density)):
            return None
        if self._sample_record is None or self._sample_record.rays != rays:
            self._sample_record = SampleRecord.empty(rays, self.device)
        return self._sample_record

    def _add_tv(self, grads: GridGradients) -> None:
        o = self.cfg.optim
        reso = self.grid.reso
        terms = (
            (o.lambda_tv_sigma, self.grid.density, grads.density[0], "zero"),
            (o.lambda_tv_sh, self.grid.sh, grads.sh[0], "self"),
        )
        for weight, values, grad, missing in terms:
            if weight > 0:
                cells = sample_tv_cells(reso, o.tv_sparsity, self.generator, self.device)
                args = (self.grid.links, values.detach(), grad, weight, cells, missing, o.tv_reference_reso)
                if self.cfg.backend == "warp":
                    from hdrplenoxels.tv_kernel import tv_grad_warp_

                    tv_grad_warp_(*args, touched=grads.touched)
                else:
                    tv_grad_(*args)

    def _add_view_prior(self, grads: GridGradients) -> None:
        """Gradient of lambda_sh_view * sum of squared non-DC SH coefficients (see ToneMapConfig)."""
        if self.tonemapper is None:
            return
        weight, basis = self.cfg.tonemap.lambda_sh_view, self.grid.basis_dim
        if self.step >= self.cfg.tonemap.sh_view_until * self.cfg.optim.n_iters:
            return
        if weight > 0 and basis > 1:
            sh = self.grid.sh.detach().view(-1, 3, basis)[..., 1:]
            grads.sh[0].view(-1, 3, basis)[..., 1:].add_(sh, alpha=2.0 * weight)
            grads.mark_all()  # a gradient on every row: the optimiser's update is dense

    def maybe_upsample(self) -> bool:
        g = self.cfg.grid
        last = self.level + 1 >= len(g.reso_schedule)
        if last or self.step % g.upsample_every != 0 or self.step >= self.cfg.optim.n_iters:
            return False  # never resample after the final step: the saved grid would be untrained
        self.level += 1
        reso = g.reso_schedule[self.level]
        # Both are discarded at a resample; freeing them first leaves the memory to the resample.
        self.optimizer.reset()
        self._grads = None
        score, thresh = None, g.density_thresh
        if g.prune == "weight":
            rays = ((b.origins, b.dirs) for b in self.pool.iter_all(g.weight_ray_stride))
            score = max_weight_score(self.grid, reso, rays, self.render_opt)
            thresh = g.weight_thresh / reso[2]
        self.grid = self.grid.resample(reso, score, thresh, dilate=g.dilate, max_voxels=g.max_voxels)
        if self.grid.num_voxels == 0:
            raise RuntimeError(
                f"step {self.step}: no voxel passed the {g.prune} pruning threshold ({thresh:g}) when "
                f"resampling to {reso}; the scene has not formed yet — lower the threshold or upsample later"
            )
        return True

    def run(self, progress: bool = True) -> Model:
        cfg = self.cfg
        self.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.out_dir / "config.json", json.dumps(cfg.to_dict(), indent=2))
        log_path = self.out_dir / LOG_FILE
        n = cfg.optim.n_iters
        bar = tqdm(total=n, initial=self.step, disable=not progress, dynamic_ncols=True, mininterval=0.5)
        t0 = time.perf_counter()
        losses: list[torch.Tensor] = []
        with log_path.open("a") as log:
            while self.step < cfg.optim.n_iters:
                losses.append(self.train_step())
                bar.update(1)
                if self.step % cfg.log_every == 0 or self.step == cfg.optim.n_iters:
                    mse = float(torch.stack(losses).mean())
                    losses.clear()
                    entry = {
                        "step": self.step,
                        "mse": mse,
                        "psnr": mse_to_psnr(mse),
                        "lr_sigma": self.schedules.sigma(self.step),
                        "lr_sh": self.schedules.sh(self.step),
                        "voxels": self.grid.num_voxels,
                        "seconds": time.perf_counter() - t0,
                    }
                    log.write(json.dumps(entry) + "\n")
                    bar.set_postfix(
                        loss=f"{mse:.2e}",
                        psnr=f"{entry['psnr']:.2f}",
                        lr_s=f"{entry['lr_sigma']:.3g}",
                        lr_sh=f"{entry['lr_sh']:.2g}",
                        vox=self.grid.num_voxels,
                    )
                if self.maybe_upsample():
                    bar.write(
                        f"step {self.step}: resampled to {self.grid.reso}, {self.grid.num_voxels} voxels kept"
                    )
                if cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
        bar.close()
        if not self.checkpoint_path(self.step).exists():
            self.save_checkpoint()
        if self.tonemapper is not None and self.cfg.tonemap.known_exposure:
            self.tonemapper.fit_exponent_to_known()
        elif self.tonemapper is not None and self.cfg.tonemap.output_prior_gamma:
            self.tonemapper.fit_exponent_to_response_prior(self.cfg.tonemap.output_prior_gamma)
        model = self.model()
        model.save(self.out_dir / MODEL_FILE)
        if self.tonemapper is not None:  # the learned cameras, readable without loading the model
            params = self.tonemapper.parameters_dict() | {"names": self.scene.names}
            atomic_write_text(self.out_dir / CAMERA_PARAMS_FILE, json.dumps(params))
            plot_camera_params(params, self.out_dir / CAMERA_PLOT_FILE, _camera_truth(self.scene))
        return model
