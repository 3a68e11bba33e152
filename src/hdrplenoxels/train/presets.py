"""The named presets, each a set of replacements over the base `TrainConfig()` (whose defaults are the
paper's synthetic schedule): what a preset changes is all it says (docs/usage.md, "Presets")."""

from __future__ import annotations

import dataclasses
from typing import Any

from hdrplenoxels.core.settings import apply_overrides
from hdrplenoxels.train.config import EPOCH, NerfSettings, TrainConfig

PAPER_NERF = {f"nerf.{key}": value for key, value in dataclasses.asdict(NerfSettings.paper()).items()}

PAPER_SYNTHETIC: dict[str, Any] = {
    "grid.reso_schedule": [(128, 128, 64), (256, 256, 128), (512, 512, 256), (800, 800, 512)],
    "tonemap.lr": 1e-2,
    **PAPER_NERF,
}

PAPER_REAL: dict[str, Any] = {
    **PAPER_SYNTHETIC,
    "grid.reso_schedule": [(128, 128, 128), (256, 256, 256), (750, 600, 300)],
    "grid.upsample_every": 3 * EPOCH,
    "tonemap.lr": 1e-3,
    "checkpoint_every": 3 * EPOCH,
}

# The CPU presets checkpoint every so many steps, minutes apart on a CPU; on a GPU those steps take
# seconds and each checkpoint of a cascade seconds to write, so one comes at most once a minute there
# (JOURNAL.md, "Checkpoint writes").
CHECKPOINT_GAP_SECONDS = 60.0

# `optim.tv_photos` of the CPU grid presets: the grid's TV x (140 / photos)^2, 1-100x, so a capture of few
# photos gets the stronger TV it needs; chosen on validation views of real captures and synthetic scenes,
# at `balanced` and at `fast` on five validation folds (JOURNAL.md, "The grid's TV from the number
# of photos").
TV_PHOTOS = 140.0

# The tone mapper's loss in the CPU grid presets: saturation weighting (near-black and clipped codes count
# a quarter), which keeps a clipped photo from dragging the grid and its exposure about, then the tone
# refitted on the unweighted error with the grid frozen (`tonemap.refit_steps`), which takes back part of
# what the weighting costs the curve; chosen on validation views of the real re-shoots and the synthetic
# scenes (JOURNAL.md, "Saturation weighting with the tone refitted").
CPU_TONE_LOSS: dict[str, Any] = {"tonemap.saturation_weighting": True}

# A CPU-sized schedule: small grids, big batches, fast learning-rate decay. SH learns 5x faster than in
# the paper's schedule: with only 600 RMSProp steps (each moves a coefficient by about one learning rate)
# bright, saturated regions would otherwise never reach their colour, and the density compensates with
# floaters near the cameras. The tone mapper's 1e-2 overshoots in 600 steps: 3e-3. Its grid TV grows as
# the photos get fewer (`TV_PHOTOS`); its tone loss is weighted (`CPU_TONE_LOSS`).
FAST: dict[str, Any] = {
    "grid.reso_schedule": [(32, 32, 32), (64, 64, 64)],
    "grid.upsample_every": 250,
    "grid.sh_degree": 1,
    "optim.n_iters": 600,
    "optim.batch_size": 4096,
    "optim.lr_sigma_delay_steps": 100,
    "optim.lr_decay_steps": 600,
    "optim.lr_sh": 5e-2,
    "optim.lr_sh_final": 5e-3,
    "optim.lr_sigma_final": 1.0,
    "optim.lambda_tv_sigma": 1e-5,
    "optim.lambda_tv_sh": 1e-4,
    "optim.tv_reference_reso": 64,
    "optim.tv_photos": TV_PHOTOS,
    "tonemap.lr": 3e-3,
    **CPU_TONE_LOSS,
    "checkpoint_every": 500,
    "checkpoint_gap_seconds": CHECKPOINT_GAP_SECONDS,
    "log_every": 25,
}

# The CPU preset between `fast` and the paper's, its cost per step whatever the number of views: a grid to
# 256^3 with degree-2 SH and a background MSI 4x finer in angle than `fast`'s, chosen on validation
# captures (JOURNAL.md, "The preset ladder"). Its grid TV grows as the photos get fewer
# (`TV_PHOTOS`). Its checkpoints come every 1000 steps, minutes apart; a cascade's at 256^3 writes
# gigabytes, so the time rule waits 10 minutes, not the default 5 (JOURNAL.md, "Constants
# justified by timings").
BALANCED: dict[str, Any] = {
    "grid.reso_schedule": [(64, 64, 64), (128, 128, 128), (256, 256, 256)],
    "grid.upsample_every": 1000,
    "optim.n_iters": 3000,
    "optim.batch_size": 4096,
    "optim.lr_sigma_delay_steps": 300,
    "optim.lr_decay_steps": 3000,
    "optim.lr_sh": 3e-2,
    "optim.lr_sh_final": 1e-3,
    "optim.lr_sigma_final": 0.5,
    "optim.lambda_tv_sigma": 1e-5,
    "optim.lambda_tv_sh": 1e-4,
    "optim.tv_reference_reso": 256,
    "optim.tv_photos": TV_PHOTOS,
    "tonemap.lr": 3e-3,
    **CPU_TONE_LOSS,
    "background.height": 128,
    "background.width": 256,
    "background.samples_per_layer": 1,
    "checkpoint_every": 1000,
    "checkpoint_seconds": 600.0,
    "checkpoint_gap_seconds": CHECKPOINT_GAP_SECONDS,
    "log_every": 50,
}

NERF_CRF_SMOOTH = 1e-2  # tonemap.lambda_crf_smooth of the NeRF presets (grid: ToneMapConfig's 1e-3)

# The NeRF engine at CPU sizes (`NerfSettings()`): Adam steps on smaller batches than the grid's, over the
# learning-rate decay of `NerfSettings.lr_decay_steps` (JOURNAL.md, "NeRF engine"). The response
# curve is held 10x smoother than after the grid: a small MLP's blur leaves residuals that a free curve
# absorbs as wiggles and false colour; chosen on validation captures (same section).
NERF_FAST: dict[str, Any] = {
    **FAST,
    "model": "nerf",
    "tonemap.lambda_crf_smooth": NERF_CRF_SMOOTH,
    "tonemap.saturation_weighting": False,  # measured on the grid only (CPU_TONE_LOSS)
    "optim.tv_photos": 0.0,  # no grid to smooth
    "optim.n_iters": NerfSettings().lr_decay_steps,
    "optim.batch_size": 1024,
    "checkpoint_every": 500,
    "log_every": 50,
}

# The NeRF engine sized for a CPU (a 64x64, 50-view scene in minutes on 2 cores): a 3 x 32 trunk, 16 + 16
# samples, 800 Adam steps of 512 rays at a larger learning rate, chosen on validation captures
# (JOURNAL.md, "NeRF engine").
NERF_CPU: dict[str, Any] = {
    **NERF_FAST,
    "nerf.width": 32,
    "nerf.depth": 3,
    "nerf.view_width": 16,
    "nerf.n_coarse": 16,
    "nerf.n_fine": 16,
    "nerf.lr": 1e-2,
    "nerf.lr_final": 5e-4,
    "nerf.lr_decay_steps": 800,
    "optim.n_iters": 800,
    "optim.batch_size": 512,
}

PRESETS: dict[str, dict[str, Any]] = {
    "paper-synthetic": PAPER_SYNTHETIC,
    "paper-real": PAPER_REAL,
    "fast": FAST,
    "balanced": BALANCED,
    "nerf-fast": NERF_FAST,
    "nerf-cpu": NERF_CPU,
}


AUTO = "auto"  # `train --preset auto`, the default: `auto_preset` names one of the above per run


def auto_preset(device_type: str, scene_mode: str) -> tuple[str, str]:
    """The preset `--preset auto` trains with, and why: on a CPU `fast` (minutes on a laptop); on a GPU
    the paper's schedule for the kind of capture, `paper-synthetic` for an object in a box and
    `paper-real` for everything else (the paper's forward-facing scenes, a real capture's cascade),
    until the GPU is measured on real captures for a preset of their own."""
    if device_type != "cuda":
        return "fast", "no CUDA device; --preset balanced trains longer for more quality"
    if scene_mode == "bbox":
        return "paper-synthetic", "a CUDA device, and an object in a box (the paper's synthetic scenes)"
    return "paper-real", f"a CUDA device, and a {scene_mode} scene (a real capture)"


def preset(name: str) -> TrainConfig:
    """The configuration of preset `name`: the base with the preset's replacements."""
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return apply_overrides(TrainConfig(), {"preset": name, **PRESETS[name]})
