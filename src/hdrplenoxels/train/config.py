"""The training configuration: typed dataclasses, each field with its docstring and its limits beside it
(docs/method.md, "Grid", "Training", "Tone mapping"), and the rules between fields (`TrainConfig.check`).
Presets: `train/presets.py`; changing fields by name: `core/settings.py` (docs/design.md, "Config
overrides")."""

from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

from hdrplenoxels.core import settings
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.settings import (
    OverrideError,
    apply_overrides,
    at_most_one,
    flatten,
    positive,
    setting,
)
from hdrplenoxels.render.nerf import NerfConfig
from hdrplenoxels.tonemap.config import ToneMapConfig

EPOCH = 12_800  # HDR-Plenoxels iterations per "epoch"

Reso = tuple[int, int, int]


def _sh_degree(value: int) -> str | None:
    return None if value in (0, 1, 2) else "0, 1 or 2"


def _fraction(value: float) -> str | None:
    return None if value < 1.0 else "less than 1 (a fraction of the distance to the point)"


MAX_RESOLUTION = 4096  # voxels per axis; max_voxels bounds the total


def _schedule(value: list[Reso]) -> str | None:
    if value and all(2 <= r <= MAX_RESOLUTION for reso in value for r in reso):
        return None
    return f"a non-empty list of resolutions of 2 to {MAX_RESOLUTION} per axis"


@dataclass
class GridConfig:
    """The sparse voxel grid and its coarse-to-fine schedule (docs/method.md, "Grid")."""

    reso_schedule: list[Reso] = setting(factory=lambda: [(128, 128, 64), (256, 256, 128)], check=_schedule)
    """Resolutions (x, y, z) the grid passes through, coarsest first; it is resampled to the next every
    `upsample_every` steps."""
    upsample_every: int = setting(2 * EPOCH, at_least=1)
    """Steps between resamples to the next resolution."""
    sh_degree: int = setting(2, check=_sh_degree)
    """Spherical-harmonics degree of the colour: 0, 1 or 2 (1, 4 or 9 coefficients per channel)."""
    init_sigma: float = setting(0.1, at_least=0.0)
    """Density every voxel starts with."""
    prune: Literal["sigma", "weight"] = "sigma"
    """What decides the voxels kept at a resample: their density, or their largest weight along the
    training rays (svox2's two rules)."""
    density_thresh: float = setting(5.0, at_least=0.0)
    """The "sigma" rule: keep voxels whose resampled density is at least this."""
    weight_thresh: float = setting(0.256, at_least=0.0)
    """The "weight" rule: keep voxels whose largest ray weight is at least this over the z resolution."""
    weight_ray_stride: int = setting(1, at_least=1)
    """The "weight" rule marches every n-th training pixel (1: all, as svox2)."""
    dilate: int = setting(2, at_least=0)
    """Voxels kept around each kept voxel at a resample, per axis."""
    max_voxels: int = setting(44_000_000, at_least=1)
    """The most voxels a resample may keep, counted over every box of a cascade after the dilation;
    past it the pruning threshold rises until they fit."""
    min_views: int = setting(0, at_least=0)
    """Keep only voxels at least this many pooled views' frustums hold, from the start and at every
    resample (0: all): content one photo alone sees has no depth, and left in the grid it hangs as a
    blob in the views that look through it (docs/method.md, "Views per voxel"). Box scenes only."""


@dataclass
class OptimConfig:
    """Steps, batches, learning rates and regularisers of the grid (docs/method.md, "Training"); the
    learning rates follow svox2's delayed exponential decay."""

    n_iters: int = setting(10 * EPOCH, at_least=0)
    """Training steps."""
    batch_size: int = setting(2500, at_least=1)
    """Rays per step, drawn uniformly over the training pixels."""
    lr_sigma: float = setting(30.0, at_least=0.0)
    """Density learning rate at the start of the decay."""
    lr_sigma_final: float = setting(0.05, at_least=0.0)
    """Density learning rate at `lr_decay_steps`."""
    lr_sigma_delay_steps: int = setting(15_000, at_least=0)
    """Steps over which the density rate ramps up from `lr_sigma_delay_mult` of itself."""
    lr_sigma_delay_mult: float = setting(0.01, at_least=0.0)
    """The density rate's share at step 0 of the ramp."""
    lr_sh: float = setting(1e-2, at_least=0.0)
    """SH learning rate at the start of the decay."""
    lr_sh_final: float = setting(5e-6, at_least=0.0)
    """SH learning rate at `lr_decay_steps`."""
    lr_decay_steps: int = setting(250_000, at_least=1)
    """Steps over which the rates decay exponentially to their final values."""
    rms_beta: float = setting(0.95, at_least=0.0, below=1.0)
    """RMSProp's decay of the squared-gradient average."""
    lambda_tv_sigma: float = setting(5e-4, at_least=0.0)
    """Weight of the density's total variation."""
    lambda_tv_sh: float = setting(5e-3, at_least=0.0)
    """Weight of the SH coefficients' total variation."""
    tv_sparsity: float = setting(0.01, at_least=0.0, check=at_most_one)
    """Fraction of the cells in each step's contiguous TV run."""
    tv_reference_reso: int = setting(256, at_least=1)
    """Anisotropy normaliser of the TV gradient (svox2's convention)."""
    tv_photos: float = setting(0.0, at_least=0.0)
    """0: the TV weights as given. Otherwise both are multiplied by (this / photos)^2, between 1 and
    `TV_SCALE_MAX` (`tv_scale`), photos being the views the grid learns from (the training views, and
    the test views whose left halves train their tone): few photos see each voxel from few directions,
    and a smoother grid keeps what they leave open from turning into floaters (JOURNAL.md, "The
    grid's TV from the number of photos")."""
    lambda_distortion: float | None = setting(None, at_least=0.0)
    """Weight of the distortion loss (the batch's mean; docs/method.md, "Distortion"): it gathers each
    ray's weight at one place, which keeps the empty space of a cascade free of floaters. None: 0.01 for
    a cascade, off (0) for one box, whose cameras stand outside it."""
    near_grad: float = setting(0.0, at_least=0.0)
    """Samples nearer a ray's origin than this many finest-box half-sides learn with their gradient
    scaled by the square of their distance over it (`RenderOptions.near_grad`), against floaters just in
    front of a camera; off by default: neutral on the real captures' validation views at `fast`
    (JOURNAL.md, "Real captures"), and it slows walls that stand beside the cameras."""
    lambda_sparsity: float = setting(0.0, at_least=0.0)
    """Weight of svox2's Cauchy sparsity prior on the density of the voxels each step's rays reach
    (`train/sparsity.py`); off by default: at `fast` on the real captures' validation views its gains
    were within the spread between runs (JOURNAL.md, "Real captures"), and 1e-7 erodes a capture
    at `balanced` ("A GPU preset for real captures"); a candidate for the schedules a GPU affords."""
    lambda_free_space: float = setting(1.0, at_least=0.0)
    """Weight of the free-space prior (docs/method.md, "Free space along lines of sight"): the mean
    optical depth of the segments from training cameras to the sparse points they saw, chosen on the real
    captures' validation views (JOURNAL.md, "Real captures"). It acts only on a dataset with
    sparse points (`process` writes them; a COLMAP folder has them) in a box or cascade; 0: off."""
    free_space_lines: int = setting(1024, at_least=1)
    """Segments drawn per step."""
    free_space_samples: int = setting(16, at_least=1)
    """Random points per segment per step."""
    free_space_margin: float = setting(0.1, at_least=0.0, check=_fraction)
    """The fraction of each point's distance, in front of it, left out."""
    free_space_near: float = setting(0.7, at_least=0.0, check=_fraction)
    """Each training camera's view is empty, too, nearer than this fraction of the distance to the
    nearest sparse points it saw: segments from it through a grid of its pixels join the lines (0: the
    lines alone); a test view whose left half is pooled, to the nearest training-view point in that
    half. Against floaters in front of a camera whose keypoints lie far behind them, chosen on the real
    captures' validation views (JOURNAL.md, "Free space near the cameras")."""
    lambda_surface: float = setting(1.0, at_least=0.0)
    """Weight of the surface prior (docs/method.md, "Surfaces at the sparse points"): the mean shortfall,
    below `surface_target`, of the optical depth of each line of sight from `free_space_margin` in front
    of its point to `surface_behind` past it. Drawn like the free-space prior (`free_space_lines` windows
    of `free_space_samples` points a step), with the same sparse points and conditions; chosen on the
    real captures' validation views (JOURNAL.md, "Surfaces at the sparse points"); 0: off."""
    surface_target: float = setting(1.5, check=positive)
    """Optical depth a window around a sparse point is pulled up to (1.5: 78 % of a ray stops in it; 3
    and 6 left more of the real captures' surfaces thick: JOURNAL.md, "The surface prior's
    target")."""
    surface_behind: float = setting(0.2, at_least=0.0, check=_fraction)
    """How far each window reaches past its point, as a fraction of the point's distance: far enough to
    hold the surface's whole opacity wherever the point's error puts it (a window that ends at its point
    thickens every surface towards the cameras: JOURNAL.md, "Surfaces at the sparse points")."""
    free_space_spread: float = setting(0.0, at_least=0.0)
    """Each segment widens to a cone from its camera whose radius at the point is this fraction of its
    length, for a keypoint's neighbouring pixels (0: the lines alone; wider cones cut into thin
    foreground near the keypoints: JOURNAL.md, "Real captures")."""


@dataclass
class RenderConfig:
    """The ray march (docs/method.md, "Rendering")."""

    step_size: float = setting(0.5, check=positive)
    """Distance between samples, in voxels of the finest level."""
    sigma_thresh: float = setting(1e-8, at_least=0.0)
    """Samples of lower density are skipped."""
    stop_thresh: float = setting(1e-7, at_least=0.0, below=1.0)
    """A ray stops once its transmittance falls below this."""
    background_brightness: float | None = setting(None, at_least=0.0)
    """Brightness seen where rays leave the field with no background model. None: the dataset's own (1.0
    for white-background layouts, else 0.5)."""


@dataclass
class BackgroundConfig:
    """The MSI behind the box (docs/method.md, "Background"): its size, initial values, optimiser and
    regularisers, separate from the grid's (svox2's background settings; smaller maps for the CPU)."""

    enabled: bool | None = None
    """None: as the scene mode says ("bbox+background", "cascade"); true or false force it."""
    layers: int = setting(16, at_least=1)
    """Spheres from the box's outer sphere to infinity, evenly spaced in inverse radius."""
    height: int = setting(32, at_least=2)
    """Rows of polar angle per layer (svox2, Tanks and Temples: 64 layers of 768 x 1536)."""
    width: int = setting(64, at_least=2)
    """Columns of azimuth per layer."""
    samples_per_layer: int = setting(2, at_least=1)
    """Samples a ray takes between two layers."""
    init_sigma: float = setting(0.5, check=positive)
    """Density every texel starts with; > 0, since a density of exactly 0 gets no gradient
    (JOURNAL.md)."""
    init_color: float = setting(0.5, at_least=0.0)
    """Colour every texel starts with."""
    lr_sigma: float = setting(3.0, at_least=0.0)
    """Density learning rate at the start of the decay."""
    lr_sigma_final: float = setting(3e-3, at_least=0.0)
    """Density learning rate at the end of the decay."""
    lr_color: float = setting(0.1, at_least=0.0)
    """Colour learning rate at the start of the decay."""
    lr_color_final: float = setting(5e-6, at_least=0.0)
    """Colour learning rate at the end of the decay."""
    lr_decay_steps: int | None = setting(None, at_least=1)
    """Steps of the decay. None: the grid's `optim.lr_decay_steps`."""
    lambda_tv_sigma: float = setting(1e-2, at_least=0.0)
    """Weight of the density's total variation over the texels."""
    lambda_tv_color: float = setting(1e-2, at_least=0.0)
    """Weight of the colour's total variation over the texels."""
    lambda_sparsity: float = setting(0.0, at_least=0.0)
    """Weight of a Cauchy loss on the density; off, as in svox2."""
    tv_sparsity: float = setting(1.0, at_least=0.0, check=at_most_one)
    """Fraction of the texels in each step's TV run, as the grid's (1: every texel)."""


@dataclass
class DataConfig:
    """How the dataset's images are read."""

    downscale: int = setting(1, at_least=1)
    """Images are reduced this many times on each side (area filter; data/downscale.py)."""
    pool_budget_gb: float = setting(4.0, check=positive)
    """Warn, suggesting a downscale, when the ray pool's pixels would exceed this."""


@dataclass
class NerfSettings(NerfConfig):
    """The NeRF engine's network and sampling (`NerfConfig`, saved with the model) and its Adam schedule
    (training's alone)."""

    lr: float = setting(5e-3, at_least=0.0)
    """Adam learning rate at the start of the decay."""
    lr_final: float = setting(2.5e-4, at_least=0.0)
    """Learning rate at `lr_decay_steps`."""
    lr_decay_steps: int = setting(3000, at_least=1)
    """Steps of the exponential decay."""

    def network(self) -> NerfConfig:
        """The part a saved field keeps."""
        return NerfConfig.among(dataclasses.asdict(self))

    @classmethod
    def paper(cls) -> NerfSettings:
        """Vanilla NeRF's network and Adam schedule: 5e-4 decaying tenfold over 250k steps."""
        network = dataclasses.asdict(NerfConfig.paper())
        return cls(**network, lr=5e-4, lr_final=5e-5, lr_decay_steps=250_000)


CASCADE_DISTORTION = 0.01
"""`optim.lambda_distortion` where it is None, for a cascade (JOURNAL.md, "Real captures")."""
TV_SCALE_MAX = 100.0
"""The largest multiple of the TV weights `optim.tv_photos` sets: the largest measured on real captures
(JOURNAL.md, "The grid's TV from the number of photos")."""


def tv_scale(tv_photos: float, photos: int) -> float:
    """The multiple of the grid's TV weights for a capture of `photos` photos (`OptimConfig.tv_photos`)."""
    if tv_photos <= 0 or photos <= 0:
        return 1.0
    return min(max((tv_photos / photos) ** 2, 1.0), TV_SCALE_MAX)


@dataclass
class TrainConfig:
    """Everything a training run is set by: `config.json` in each run folder, presets in
    `train/presets.py`, any key changed by name with `--set section.key=value` (`apply_overrides`)."""

    preset: str = "paper-synthetic"
    """The preset this configuration started from."""
    grid: GridConfig = setting(factory=GridConfig)
    optim: OptimConfig = setting(factory=OptimConfig)
    render: RenderConfig = setting(factory=RenderConfig)
    tonemap: ToneMapConfig = setting(factory=ToneMapConfig)
    data: DataConfig = setting(factory=DataConfig)
    background: BackgroundConfig = setting(factory=BackgroundConfig)
    nerf: NerfSettings = setting(factory=NerfSettings)
    """The NeRF engine's settings (model "nerf" only)."""
    scene_mode: Literal["auto", "bbox", "bbox+background", "cascade", "ndc"] = "auto"
    """Where the field lives (docs/method.md, "Placement"); auto: chosen from the capture."""
    holdout: Literal["right-half", "full"] = "right-half"
    """right-half: test views' left halves train and their right halves are scored (HDR-Plenoxels);
    full: test views are held out whole."""
    checkpoint_every: int = setting(2 * EPOCH, at_least=0)
    """Steps between checkpoints (0: by time only)."""
    checkpoint_seconds: float = setting(300.0, at_least=0)
    """Also checkpoint when this much training time has passed (0: off)."""
    checkpoint_gap_seconds: float = setting(0.0, at_least=0)
    """Skip a `checkpoint_every` checkpoint that comes sooner than this after the last one (0: none
    skipped): a preset's every-N-steps are minutes apart on a CPU but seconds apart on a GPU, where each
    write of a cascade costs seconds."""
    keep_checkpoints: int = setting(3, at_least=0)
    """Newest checkpoints kept on disk (0: all); older ones are deleted."""
    log_every: int = setting(100, at_least=1)
    """Steps between lines of the training log."""
    seed: int = setting(20200823, at_least=0)
    """Seed of the ray sampling and of every random initialisation."""
    model: Literal["grid", "nerf"] = "grid"
    """The engine family: a sparse voxel grid, or a NeRF MLP."""
    backend: Literal["warp", "torch"] = "warp"
    """The grid's renderer (model "grid" only): the Warp kernels, or the PyTorch reference."""
    device: str = "auto"
    """"auto" picks CUDA when available; else "cpu", "cuda" or "cuda:N"."""
    view_prior_update: Literal["auto", "owed", "dense"] = "auto"
    """The Warp grid, while the view prior (`tonemap.lambda_sh_view`) acts: "owed", a voxel no ray or
    regulariser of a step touches owes the step's pull on its SH, paid in the dense update's own
    arithmetic when a step next reads or updates it, and every few dozen steps (JOURNAL.md,
    "The view prior's pull, owed"): the same training as "dense", the pass over every voxel every step,
    without that pass. "auto": owed on CUDA, where the dense pass is bound by memory; dense on a CPU,
    where it is bound by its arithmetic and owing it measured slower."""
    tv_layout: Literal["auto", "cell", "channel"] = "auto"
    """The Warp grid's TV kernel (`kernels/tv_kernel.py`): a thread per cell, or per (cell, channel), a
    variant for CUDA that reads and adds a row's neighbouring values from neighbouring threads; the same
    gradient either way. "auto": per cell on every device until a GPU's timing chooses."""
    owed_pay: Literal["auto", "every-row", "listed"] = "auto"
    """The Warp grid's pass that pays the view prior's owed pull on the rows a step reads
    (`kernels/rmsprop_kernel.py`): "every-row", a thread per value (CUDA) or per row (CPU) of every row,
    the unread returning at once; "listed", the rows that owe listed first and their values paid by a
    fixed number of threads, a variant for CUDA whose launch does not grow with the grid. The same
    numbers either way. "auto": every-row until a GPU's timing chooses."""
    touched_update: Literal["auto", "every-row", "listed"] = "auto"
    """The Warp grid's optimiser step on the rows a step's gradients touched (`kernels/rmsprop_kernel.py`):
    "every-row", a thread per row of the grid, the untouched returning at once; "listed", the touched
    rows listed first and their values updated by a fixed number of threads (neighbouring threads,
    neighbouring floats), a variant for CUDA. The same numbers either way. "auto": every-row until a
    GPU's timing chooses."""
    cuda_graph: bool = True
    """On CUDA, replay the part of each step that repeats (the batch, forward, tone mapping, backward,
    regularisers) from a CUDA graph instead of launching its kernels one by one (`train/step_graph.py`).
    The Warp grid only: ignored on a CPU and by the other engines. On since a GPU measured that it pays
    (JOURNAL.md, "CUDA graph"); false launches every kernel from the host."""

    RENAMED: ClassVar[dict[str, str]] = {
        "render.background": "render.background_brightness",
        "background.init_density": "background.init_sigma",
        "background.lr_density": "background.lr_sigma",
        "background.lr_density_final": "background.lr_sigma_final",
        "background.lambda_tv_density": "background.lambda_tv_sigma",
    }
    """Keys renamed (old -> new): runs saved before still load, and `--set` still takes them."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def view_prior_end(self) -> float:
        """The step from which the view prior (`ToneMapConfig.lambda_sh_view`) no longer acts: it acts
        with the tone mapper only, on SH beyond the DC term, for `sh_view_until` of the schedule. While
        it acts the grid's update is dense (every voxel, not those a step touched) or owed
        (`view_prior_update`), so a step costs more then. A config whose tone mapping the photos will
        decide (None) is priced as with it, the dearer case."""
        t = self.tonemap
        acts = t.enabled is not False and t.lambda_sh_view > 0 and self.grid.sh_degree > 0
        return t.sh_view_until * self.optim.n_iters if acts else 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """A config from its `to_dict` form, every value checked against its declared type (a saved
        config.json or checkpoint may have been edited or damaged): an OverrideError names a bad key."""
        if not isinstance(d, dict):
            raise OverrideError(f"a configuration is a JSON object, got {type(d).__name__}")
        return apply_overrides(cls(), flatten(d))

    RESOLVED: ClassVar[tuple[str, ...]] = (
        "tonemap.enabled",
        "render.background_brightness",
        "background.enabled",
        "background.lr_decay_steps",
        "optim.lambda_distortion",
    )
    """The keys whose None means "from the capture" or "as another key", filled in by `resolved`."""

    def resolved(
        self,
        *,
        background_brightness: float,
        wants_background: bool,
        levels: int,
        photos: int = 0,
        tone_mapping: bool = True,
    ) -> TrainConfig:
        """The settings a run trains with: a copy with each `RESOLVED` key that is None filled in, the one
        place they are (the trainer and the engines read no None; `unresolved` lists what is left). The
        run's config.json keeps the None, so a resumed run resolves it again, to the same values.

        tonemap.enabled: `tone_mapping`, what the photos say (`train.tone_choice`), or on where a setting
        that acts through the tone mapper is (`tone_switches`); render.background_brightness: the
        dataset's (`background_brightness`); background.enabled: the
        scene mode's choice (`wants_background`); background.lr_decay_steps: the grid's
        `optim.lr_decay_steps`; optim.lambda_distortion: `CASCADE_DISTORTION` for a cascade (`levels` >
        1), off for one box, whose cameras stand outside it. The grid's TV weights are multiplied by
        `tv_scale` for a capture of `photos` photos, and `optim.tv_photos` set to 0, so that resolving
        twice changes nothing."""
        out = copy.deepcopy(self)
        if out.tonemap.enabled is None:
            out.tonemap.enabled = tone_mapping or bool(out.tone_switches())
        if out.render.background_brightness is None:
            out.render.background_brightness = background_brightness
        if out.background.enabled is None:
            out.background.enabled = wants_background
        if out.background.lr_decay_steps is None:
            out.background.lr_decay_steps = out.optim.lr_decay_steps
        if out.optim.lambda_distortion is None:
            out.optim.lambda_distortion = CASCADE_DISTORTION if levels > 1 else 0.0
        scale = tv_scale(out.optim.tv_photos, photos)
        out.optim.lambda_tv_sigma *= scale
        out.optim.lambda_tv_sh *= scale
        out.optim.tv_photos = 0.0
        return out

    def unresolved(self) -> list[str]:
        """The `RESOLVED` keys still None (a config not passed through `resolved`)."""
        flat = flatten(self.to_dict())
        return [key for key in self.RESOLVED if flat[key] is None]

    def check(self, scene_mode: str) -> list[str]:
        """The rules between settings, given the scene mode the capture resolved to: a ConfigError for a
        combination no run can train, and a line for each setting that overrules the scene mode."""
        notes = []
        bg = self.background.enabled
        self._check_tone_switches()
        if self.nerf.appearance and self.model != "nerf":
            raise ConfigError("nerf.appearance (--appearance-embedding) needs model nerf (--model nerf)")
        if bg and self.model != "grid":
            raise ConfigError(
                "background.enabled=true is for the voxel grid (--model grid): a NeRF has no MSI"
            )
        if bg and scene_mode == "ndc":
            raise ConfigError(
                "background.enabled=true needs a bounding box (--scene-mode bbox+background); "
                "this scene is in NDC, whose grid already reaches to infinity"
            )
        if bg and scene_mode == "bbox":
            notes.append("background.enabled=true: a multi-sphere background behind the box all the same")
        if bg is False and scene_mode in ("bbox+background", "cascade"):
            notes.append(
                "background.enabled=false: no background model; beyond the box renders as the constant"
            )
        return notes

    def tone_switches(self) -> list[str]:
        """The tone-mapping settings on that act only through the tone mapper, each named with the `train`
        flags that set it: they need it on (`_check_tone_switches`), and turn it on where it is left to
        the photos (`resolved`)."""
        t = self.tonemap
        switches = (
            (t.known_exposure, "known_exposure", "--known-exposure"),
            (t.exposure_init_from_metadata, "exposure_init_from_metadata", "--exposure-init metadata"),
            (t.lambda_crf_loglog > 0, "lambda_crf_loglog", "--response-prior, --sparse-bracket"),
        )
        return [f"tonemap.{key} ({flags})" for is_on, key, flags in switches if is_on]

    def _check_tone_switches(self) -> None:
        """Tone-mapping settings that act only through the tone mapper are refused with it turned off, not
        silently ignored."""
        on = self.tone_switches()
        if self.tonemap.enabled is False and on:
            verb = "needs" if len(on) == 1 else "need"
            raise ConfigError(f"{' and '.join(on)} {verb} the tone mapper (tonemap.enabled, --tonemap)")


class ConfigError(ValueError):
    """Settings that contradict each other (`TrainConfig.check`)."""


def read_config(path: Path) -> TrainConfig:
    """A run's saved config.json (a resumed run must keep the configuration it was started with)."""
    try:
        return TrainConfig.from_dict(json.loads(path.read_text()))
    except (ValueError, TypeError) as e:
        raise InputError(path, f"cannot read the run's configuration: {e}") from None


# The options of `train`, `batch` and `experiment` that set one config key each, by option name: one
# table, so that a flag means the same key in every command.
FLAG_KEYS = {
    "iters": "optim.n_iters",
    "batch_size": "optim.batch_size",
    "downscale": "data.downscale",
    "tonemap": "tonemap.enabled",
    "known_exposure": "tonemap.known_exposure",
    "model_kind": "model",
    "appearance_embedding": "nerf.appearance",
    "backend": "backend",
    "device": "device",
}


def flag_settings(flags: dict[str, Any]) -> dict[str, Any]:
    """The config keys that the given options (by `FLAG_KEYS` name) set; an option left out or None
    (not given) leaves its key to the preset or the run."""
    unknown = set(flags) - set(FLAG_KEYS)
    if unknown:
        raise KeyError(f"not options that set a config key: {', '.join(sorted(unknown))}")
    return {FLAG_KEYS[name]: value for name, value in flags.items() if value is not None}


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """'section.key=value' strings -> {key: typed value} for a `TrainConfig` (`core.settings`)."""
    return settings.parse_overrides(TrainConfig, items)


def setting_types() -> dict[str, Any]:
    """Every settable key of a `TrainConfig` with its declared type."""
    return {key: hint for key, (hint, _) in settings.fields_of(TrainConfig).items()}
