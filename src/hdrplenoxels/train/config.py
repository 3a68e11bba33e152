"""Typed training configuration, the named presets (docs/method.md, "Grid", "Training", "Tone mapping") and
the one way to override its fields by name (docs/design.md, "Config overrides")."""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import types
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.render.nerf import NerfConfig
from hdrplenoxels.tonemap.config import ToneMapConfig

EPOCH = 12_800  # HDR-Plenoxels iterations per "epoch"

Reso = tuple[int, int, int]


@dataclass
class GridConfig:
    reso_schedule: list[Reso] = field(default_factory=lambda: [(128, 128, 64), (256, 256, 128)])
    upsample_every: int = 2 * EPOCH  # steps between resamples to the next resolution
    sh_degree: int = 2  # 0, 1 or 2 -> 1, 4 or 9 coefficients per channel
    init_sigma: float = 0.1
    prune: Literal["sigma", "weight"] = "sigma"
    density_thresh: float = 5.0  # "sigma" rule: keep voxels whose resampled density >= this
    weight_thresh: float = 0.256  # "weight" rule: keep voxels whose max ray weight >= this / R_z
    weight_ray_stride: int = 1  # "weight" rule: march every n-th training pixel (1 = all, as svox2)
    dilate: int = 2
    max_voxels: int = 44_000_000


@dataclass
class OptimConfig:
    n_iters: int = 10 * EPOCH
    batch_size: int = 2500
    lr_sigma: float = 30.0
    lr_sigma_final: float = 0.05
    lr_sigma_delay_steps: int = 15_000
    lr_sigma_delay_mult: float = 0.01
    lr_sh: float = 1e-2
    lr_sh_final: float = 5e-6
    lr_decay_steps: int = 250_000
    rms_beta: float = 0.95
    lambda_tv_sigma: float = 5e-4
    lambda_tv_sh: float = 5e-3
    tv_sparsity: float = 0.01  # fraction of cells in each step's contiguous TV run
    tv_reference_reso: int = 256  # anisotropy normaliser of the TV gradient (svox2 convention)
    # Weight of the distortion loss (the batch's mean; docs/method.md, "Distortion"): it gathers each ray's
    # weight at one place, which keeps the empty space of a cascade free of floaters. None: 0.01 for a
    # cascade, off (0) for one box, whose cameras stand outside it.
    lambda_distortion: float | None = None
    # Samples nearer a ray's origin than this many finest-box half-sides learn with their gradient scaled
    # by the square of their distance over it (`RenderOptions.near_grad`), against floaters just in front
    # of a camera; off by default: neutral on the real captures' validation views at `fast`
    # (docs/performance.md, "Real captures"), and it slows walls that stand beside the cameras.
    near_grad: float = 0.0
    # Weight of the free-space prior (docs/method.md, "Free space along lines of sight"): the mean optical
    # depth of the segments from training cameras to the sparse points they saw, chosen on the real
    # captures' validation views (docs/performance.md, "Real captures"). It acts only on a dataset with
    # sparse points (`process` writes them; a COLMAP folder has them) in a box or cascade; 0: off.
    lambda_free_space: float = 1.0
    free_space_lines: int = 1024  # segments drawn per step
    free_space_samples: int = 16  # random points per segment per step
    free_space_margin: float = 0.1  # the fraction of each point's distance, in front of it, left out
    # Each segment widens to a cone from its camera whose radius at the point is this fraction of its
    # length, for a keypoint's neighbouring pixels (0: the lines alone; wider cones cut into thin
    # foreground near the keypoints: docs/performance.md, "Real captures").
    free_space_spread: float = 0.0


@dataclass
class RenderConfig:
    step_size: float = 0.5
    sigma_thresh: float = 1e-8
    stop_thresh: float = 1e-7
    background: float | None = None  # None: the dataset's own (1.0 for white-background layouts, else 0.5)


@dataclass
class BackgroundConfig:
    """The MSI behind the box (docs/method.md, "Background"): its size, initial values, optimiser and
    regularisers, separate from the grid's (svox2's background settings; smaller maps for the CPU)."""

    enabled: bool | None = None  # None: as the scene mode says ("bbox+background"); true/false force it
    layers: int = 16
    height: int = 32  # rows of polar angle; svox2 (Tanks and Temples) uses 64 layers of 768 x 1536
    width: int = 64  # columns of azimuth
    samples_per_layer: int = 2
    init_density: float = 0.5  # > 0: a density of exactly 0 gets no gradient (docs/performance.md)
    init_color: float = 0.5
    lr_density: float = 3.0
    lr_density_final: float = 3e-3
    lr_color: float = 0.1
    lr_color_final: float = 5e-6
    lr_decay_steps: int | None = None  # None: the grid's optim.lr_decay_steps
    lambda_tv_density: float = 1e-2
    lambda_tv_color: float = 1e-2
    lambda_sparsity: float = 0.0  # Cauchy loss on density; off as in svox2
    tv_sparsity: float = 1.0  # fraction of texels in each step's TV run, as the grid's (1: every texel)


@dataclass
class DataConfig:
    downscale: int = 1  # images are reduced this many times on each side (area filter; data/downscale.py)
    pool_budget_gb: float = 4.0  # warn, suggesting a downscale, when the ray pool's pixels would exceed this


@dataclass
class TrainConfig:
    preset: str = "paper-synthetic"
    grid: GridConfig = field(default_factory=GridConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    tonemap: ToneMapConfig = field(default_factory=ToneMapConfig)
    data: DataConfig = field(default_factory=DataConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    nerf: NerfConfig = field(default_factory=NerfConfig)  # used by model "nerf" only
    scene_mode: Literal["auto", "bbox", "bbox+background", "cascade", "ndc"] = "auto"
    holdout: Literal["right-half", "full"] = "right-half"  # right-half: test views' left halves train
    checkpoint_every: int = 2 * EPOCH
    checkpoint_seconds: float = 300.0  # also checkpoint when this much training time has passed (0: off)
    keep_checkpoints: int = 3  # newest checkpoints kept on disk (0: all); older ones are deleted
    log_every: int = 100
    seed: int = 20200823
    model: Literal["grid", "nerf"] = "grid"  # the engine family: a sparse voxel grid, or a NeRF MLP
    backend: Literal["warp", "torch"] = "warp"  # the grid's renderer (model "grid" only)
    device: str = "auto"  # "auto" picks CUDA when available

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """A config from its `to_dict` form, every value checked against its declared type (a saved
        config.json or checkpoint may have been edited or damaged): an OverrideError names a bad key."""
        if not isinstance(d, dict):
            raise OverrideError(f"a configuration is a JSON object, got {type(d).__name__}")
        flat: dict[str, Any] = {}
        for key, value in d.items():
            if isinstance(value, dict):
                flat.update({f"{key}.{k}": v for k, v in value.items()})
            else:
                flat[key] = value
        return apply_overrides(cls(), flat)


def _paper_synthetic() -> TrainConfig:
    return TrainConfig(
        preset="paper-synthetic",
        grid=GridConfig(
            reso_schedule=[(128, 128, 64), (256, 256, 128), (512, 512, 256), (800, 800, 512)],
            upsample_every=2 * EPOCH,
        ),
        optim=OptimConfig(n_iters=10 * EPOCH),
        tonemap=ToneMapConfig(enabled=True, lr=1e-2),
        nerf=NerfConfig.paper(),
    )


def _paper_real() -> TrainConfig:
    return TrainConfig(
        preset="paper-real",
        grid=GridConfig(
            reso_schedule=[(128, 128, 128), (256, 256, 256), (750, 600, 300)], upsample_every=3 * EPOCH
        ),
        optim=OptimConfig(n_iters=10 * EPOCH),
        tonemap=ToneMapConfig(enabled=True, lr=1e-3),
        nerf=NerfConfig.paper(),
        checkpoint_every=3 * EPOCH,
    )


def _fast() -> TrainConfig:
    """A CPU-sized schedule: small grids, big batches, fast learning-rate decay.

    SH learns 5x faster than in the paper's schedule: with only 600 RMSProp steps (each moves a
    coefficient by about one learning rate) bright, saturated regions would otherwise never reach
    their colour, and the density compensates with floaters near the cameras.
    """
    return TrainConfig(
        preset="fast",
        grid=GridConfig(reso_schedule=[(32, 32, 32), (64, 64, 64)], upsample_every=250, sh_degree=1),
        optim=OptimConfig(
            n_iters=600,
            batch_size=4096,
            lr_sigma_delay_steps=100,
            lr_decay_steps=600,
            lr_sh=5e-2,
            lr_sh_final=5e-3,
            lr_sigma_final=1.0,
            lambda_tv_sigma=1e-5,
            lambda_tv_sh=1e-4,
            tv_reference_reso=64,
        ),
        tonemap=ToneMapConfig(lr=3e-3),  # opt-in here (--tonemap); 1e-2 overshoots in 600 steps
        checkpoint_every=500,
        log_every=25,
    )


def _balanced() -> TrainConfig:
    """The CPU preset between `fast` and the paper's, its cost per step whatever the number of views,
    a grid to 256^3 with degree-2 SH and a background MSI 4x finer in angle
    than `fast`'s, chosen on validation captures (docs/performance.md, "The preset ladder")."""
    return TrainConfig(
        preset="balanced",
        grid=GridConfig(reso_schedule=[(64, 64, 64), (128, 128, 128), (256, 256, 256)], upsample_every=1000),
        optim=OptimConfig(
            n_iters=3000,
            batch_size=4096,
            lr_sigma_delay_steps=300,
            lr_decay_steps=3000,
            lr_sh=3e-2,
            lr_sh_final=1e-3,
            lr_sigma_final=0.5,
            lambda_tv_sigma=1e-5,
            lambda_tv_sh=1e-4,
            tv_reference_reso=256,
        ),
        tonemap=ToneMapConfig(lr=3e-3),
        background=BackgroundConfig(layers=16, height=128, width=256, samples_per_layer=1),
        checkpoint_every=1000,
        log_every=50,
    )


NERF_CRF_SMOOTH = 1e-2  # tonemap.lambda_crf_smooth of the NeRF presets (grid: ToneMapConfig's 1e-3)


def _nerf_fast() -> TrainConfig:
    """The NeRF engine at CPU sizes (`NerfConfig()`): Adam steps on smaller batches than the grid's, over
    the learning-rate decay of `NerfConfig.lr_decay_steps` (docs/performance.md, "NeRF engine").

    The response curve is held 10x smoother than after the grid: a small MLP's blur leaves residuals
    that a free curve absorbs as wiggles and false colour; chosen on validation captures (same section).
    """
    cfg = _fast()
    cfg.preset = "nerf-fast"
    cfg.model = "nerf"
    cfg.tonemap.lambda_crf_smooth = NERF_CRF_SMOOTH
    cfg.optim.n_iters = cfg.nerf.lr_decay_steps
    cfg.optim.batch_size = 1024
    cfg.checkpoint_every = 500
    cfg.log_every = 50
    return cfg


def _nerf_cpu() -> TrainConfig:
    """The NeRF engine sized for a CPU (a 64x64, 50-view scene in minutes on 2 cores): a 3 x 32 trunk,
    16 + 16 samples, 800 Adam steps of 512 rays at a larger learning rate, chosen on
    validation captures (docs/performance.md, "NeRF engine")."""
    cfg = _nerf_fast()
    cfg.preset = "nerf-cpu"
    cfg.nerf = NerfConfig(
        width=32,
        depth=3,
        skip=2,
        view_width=16,
        n_coarse=16,
        n_fine=16,
        lr=1e-2,
        lr_final=5e-4,
        lr_decay_steps=800,
    )
    cfg.optim.n_iters = cfg.nerf.lr_decay_steps
    cfg.optim.batch_size = 512
    return cfg


PRESETS = {
    "paper-synthetic": _paper_synthetic,
    "paper-real": _paper_real,
    "fast": _fast,
    "balanced": _balanced,
    "nerf-fast": _nerf_fast,
    "nerf-cpu": _nerf_cpu,
}


def preset(name: str) -> TrainConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]()


def read_config(path: Path) -> TrainConfig:
    """A run's saved config.json (a resumed run must keep the configuration it was started with)."""
    try:
        return TrainConfig.from_dict(json.loads(path.read_text()))
    except (ValueError, TypeError) as e:
        raise InputError(path, f"cannot read the run's configuration: {e}") from None


# ============================================================================ overrides by name
class OverrideError(ValueError):
    """An override that names no setting, or whose value does not fit the setting's declared type."""


_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


@functools.cache
def setting_types() -> dict[str, Any]:
    """Every settable key, 'section.key' or top-level 'key', with the type its dataclass declares."""
    out: dict[str, Any] = {}
    hints = get_type_hints(TrainConfig)
    for f in dataclasses.fields(TrainConfig):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            section = get_type_hints(hint)
            out.update({f"{f.name}.{g.name}": section[g.name] for g in dataclasses.fields(hint)})
        else:
            out[f.name] = hint
    return out


def _describe(hint: Any) -> str:
    """The accepted values of a type, for error messages."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join("none" if a is type(None) else _describe(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (list, tuple):
        return "a JSON array, " + str(hint).replace("typing.", "")
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return names.get(hint, str(hint))


def _coerce(value: Any, hint: Any) -> Any:
    """`value` (a string to parse, or a Python value to check) as type `hint`, or a ValueError."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if type(None) in args and (
            value is None or (isinstance(value, str) and value.lower() in ("none", "null"))
        ):
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg)
            except ValueError:
                pass
        raise ValueError(value)
    if origin is Literal:
        for choice in args:
            if value == choice or (isinstance(value, str) and value == str(choice)):
                return choice
        raise ValueError(value)
    if origin in (list, tuple):
        if isinstance(value, str):
            value = json.loads(value)  # a JSONDecodeError is a ValueError
        if not isinstance(value, list | tuple):
            raise ValueError(value)
        if origin is list:
            return [_coerce(v, args[0]) for v in value]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise ValueError(value)
        return tuple(_coerce(v, a) for v, a in zip(value, args, strict=True))
    if hint is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
    elif hint in (int, float):
        if isinstance(value, str):
            return hint(value)
        if (
            isinstance(value, int | float)
            and not isinstance(value, bool)
            and (hint is float or isinstance(value, int))
        ):
            return hint(value)
    elif hint is str and isinstance(value, str):
        return value
    raise ValueError(value)


def _typed(key: str, value: Any) -> Any:
    """`value` typed for setting `key`, or an OverrideError naming the key and what it takes."""
    types_ = setting_types()
    if key not in types_:
        section, dot, _ = key.partition(".")
        sections = sorted({k.partition(".")[0] for k in types_ if "." in k})
        if dot and section in sections:
            keys = ", ".join(k.partition(".")[2] for k in types_ if k.startswith(f"{section}."))
            raise OverrideError(f"unknown setting {key!r}; {section} has {keys}")
        if key in sections:
            raise OverrideError(f"{key} is a section; set one of its keys, e.g. {key}.KEY=VALUE")
        top = ", ".join(k for k in types_ if "." not in k)
        raise OverrideError(
            f"unknown setting {key!r}; settings are SECTION.KEY for sections {', '.join(sections)}, or {top}"
        )
    try:
        typed = _coerce(value, types_[key])
    except ValueError:
        raise OverrideError(f"{key} takes {_describe(types_[key])}, got {value!r}") from None
    _check_range(key, typed)
    return typed


MAX_RESOLUTION = 4096  # voxels per axis; max_voxels bounds the total
_AT_LEAST = {  # settings whose type admits values that make no run
    "optim.batch_size": 1,
    "optim.n_iters": 0,
    "optim.lambda_distortion": 0.0,
    "optim.near_grad": 0.0,
    "optim.lambda_free_space": 0.0,
    "optim.free_space_lines": 1,
    "optim.free_space_samples": 1,
    "optim.free_space_margin": 0.0,
    "optim.free_space_spread": 0.0,
    "grid.upsample_every": 1,
    "grid.dilate": 0,
    "grid.max_voxels": 1,
    "grid.weight_ray_stride": 1,
    "data.downscale": 1,
    "log_every": 1,
    "checkpoint_every": 0,  # 0: by time only
    "checkpoint_seconds": 0,
    "keep_checkpoints": 0,
}


def _check_range(key: str, value: Any) -> None:
    """An OverrideError for a typed value no run can use (NaN, a zero batch, SH degree 7...)."""
    bad = None
    if isinstance(value, float) and not math.isfinite(value):
        bad = "a finite number"
    elif key in _AT_LEAST and value is not None and value < _AT_LEAST[key]:
        bad = f"at least {_AT_LEAST[key]}"
    elif key == "optim.free_space_margin" and value >= 1.0:
        bad = "less than 1 (a fraction of the distance to the point)"
    elif key == "grid.sh_degree" and value not in (0, 1, 2):
        bad = "0, 1 or 2"
    elif key == "render.step_size" and value <= 0:
        bad = "a positive number"
    elif key == "grid.reso_schedule" and (
        not value or not all(2 <= r <= MAX_RESOLUTION for reso in value for r in reso)
    ):
        bad = f"a non-empty list of resolutions of 2 to {MAX_RESOLUTION} per axis"
    if bad:
        raise OverrideError(f"{key} must be {bad}, got {value!r}")


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """'section.key=value' (or 'key=value') strings -> {key: typed value}, later items winning.

    Values are typed as the config dataclasses declare them; lists and tuples are written as JSON.
    """
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise OverrideError(f"{item!r}: expected KEY=VALUE, e.g. optim.lr_sh=1e-3")
        out[key.strip()] = _typed(key.strip(), value.strip())
    return out


def apply_overrides(cfg: TrainConfig, overrides: Iterable[str] | Mapping[str, Any]) -> TrainConfig:
    """A copy of `cfg` with settings changed by name, in order: 'key=value' strings (see
    `parse_overrides`), or a mapping of key -> value (a string is parsed, a Python value is checked)."""
    if isinstance(overrides, Mapping):
        typed = {key: _typed(key, value) for key, value in overrides.items()}
    else:
        typed = parse_overrides(overrides)
    out = copy.deepcopy(cfg)
    for key, value in typed.items():
        section, _, name = key.rpartition(".")
        setattr(getattr(out, section) if section else out, name, value)
    return out
