"""What every experiment shares: rendering the HDR truth once, capturing datasets from it, training a
named run (or reusing a finished one), and scoring it under the protocol."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
import torch

from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.eval.evaluate import METRIC_KEYS, PROTOCOLS, evaluate, novel_view_tones
from hdrplenoxels.eval.metrics import image_metrics, lpips_available
from hdrplenoxels.eval.truth import SynthTruth, truth_report
from hdrplenoxels.synth.generate import SynthOptions, capture_dataset, synthesize
from hdrplenoxels.synth.pipeline import CameraSettings, PipelineConfig
from hdrplenoxels.synth.scenes import SCENES
from hdrplenoxels.train.config import (
    OverrideError,
    TrainConfig,
    apply_overrides,
    flag_settings,
    parse_overrides,
)
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.runs import RunSpec

VALIDATION_SEED = 7  # the experiments capture with PipelineConfig's default seed
VALIDATION_SPP = 128
# The scenes an experiment runs on unless told otherwise ("demo" is a small objects360 for `make demo`).
PAPER_SCENES = tuple(s for s in SCENES if s not in ("demo", "gallery"))

PROTOCOL = (
    f"Protocol: {PROTOCOLS['right-half']}. Test views' tone parameters (white balance, exposure) are "
    "learned from their left halves only. Every model is the final step of its schedule: no checkpoint "
    "is selected and nothing is tuned on test pixels. Metrics are PSNR, SSIM (11x11 Gaussian, sigma 1.5) "
    "and LPIPS (VGG and Alex) on right halves."
)
TRUTH_PROTOCOL = (
    "Truth recovery: self-calibration is ambiguous up to an exponent (radiance^a, exposures^a and "
    "CRF(x^(1/a)) explain the images equally well), so `a` and a per-channel offset are fitted to the "
    "learned vs true per-view log gains, and scores are taken after that alignment; `a` is reported on "
    "its own (1 = the true scale). The radiance gain is fitted on training views' renders; HDR error is "
    "the mean |log2| error on test views' right halves over channels some training exposure recorded "
    "neither clipped nor black (also given: its median, and its mean off edges, i.e. over pixels whose 8 "
    "neighbours are scored too, since a pixel beside a black background or a clipped light has an "
    "unbounded error in stops when the grid's edge lands a fraction of a pixel off, and its mean over the "
    "brightest 1 % of scored pixels, e.g. a window or the sky by the sun); CRF RMSE is over x in [0, 1] "
    "against the true curve."
)


@dataclass
class ExperimentSettings:
    """Sizes and schedule of an experiment (defaults: the CPU-sized `fast` and `nerf-cpu` presets, the scene
    defaults)."""

    preset: str = "fast"
    nerf_preset: str = "nerf-cpu"  # the schedule of the NeRF engine's runs (baselines)
    iters: int | None = None
    scenes: tuple[str, ...] = ()  # empty: the experiment's own default
    n_views: int = 50
    resolution: tuple[int, int] | None = None
    spp: int | None = None
    test_spp: int | None = None  # the test views' samples per pixel (None: as `spp`); see SynthOptions
    lpips: bool = True
    backend: str = "warp"
    device: str = "auto"
    data_root: Path | None = None  # where rendered HDR truth is kept (reused across experiments)
    variants: tuple[str, ...] = ()  # `validation` only: tone settings to compare, "key=value,key=value"
    overrides: tuple[str, ...] = ()  # "section.key=value" settings of every run (`experiment --set`)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["data_root"] = str(self.data_root) if self.data_root else None
        return d


class Method(NamedTuple):
    """One trained run of an experiment, as data (so a run's plan follows from an experiment's tables):
    its report key, the dataset variant it trains on, tone mapping, the engine, and NeRF-A's per-image
    appearance embedding."""

    key: str
    variant: str
    tonemap: bool
    model: Literal["grid", "nerf"] = "grid"
    appearance: bool = False


def truth_root(scene: str, s: ExperimentSettings, out: Path) -> Path:
    """The scene's HDR truth (rendered on first use), named by everything that changes the render."""
    spec = SCENES[scene]
    w, h = s.resolution or (spec.width, spec.height)
    spp = s.spp or spec.spp
    test_suffix = f"_test{s.test_spp}spp" if s.test_spp and s.test_spp != spp else ""
    root = (s.data_root or out / "data") / f"{scene}_{w}x{h}_{s.n_views}v_{spp}spp{test_suffix}"
    if not (root / "synth.json").exists():
        synthesize(scene, root, SynthOptions(s.n_views, w, h, spp, s.test_spp), overwrite=True)
    return root


def validation_views(s: ExperimentSettings) -> int:
    return max(8, s.n_views * 3 // 5)


def validation_root(scene: str, s: ExperimentSettings, out: Path) -> Path:
    """The scene's validation truth and captures (rendered on first use)."""
    spec = SCENES[scene]
    w, h = s.resolution or (spec.width, spec.height)
    n, spp = validation_views(s), s.spp or VALIDATION_SPP
    root = (s.data_root or out / "data") / f"{scene}_validation_{w}x{h}_{n}v_{spp}spp_seed{VALIDATION_SEED}"
    if not (root / "synth.json").exists():
        opts = SynthOptions(n, w, h, spp)
        synthesize(scene, root, opts, PipelineConfig(seed=VALIDATION_SEED), overwrite=True)
    return root


def captured(
    root: Path,
    name: str,
    variant: str,
    pipeline: PipelineConfig,
    settings_for: Callable[[int], CameraSettings] | None = None,
) -> Path:
    """A dataset captured from `root`'s truth with `pipeline` (kept, and reused while settings match);
    `settings_for`: per-view cameras derived from `pipeline` (see `capture_dataset`)."""
    folder = root / "captures" / name / variant
    truth = folder / "camera_truth.json"
    if truth.exists() and json.loads(truth.read_text()).get("pipeline") == json.loads(
        json.dumps(asdict(pipeline))
    ):
        return folder
    capture_dataset(root, folder, variant, pipeline, settings_for)
    return folder


# Settings each experiment chooses per run, or from its own options: `--set` and variants may not change them.
RUN_SETTINGS = {
    "tonemap.enabled": "chosen by the experiment for each run",
    "tonemap.known_exposure": "chosen by the experiment for each run",
    "model": "chosen by the experiment for each run (use --nerf-preset for the NeRF runs' schedule)",
    "nerf.appearance": "chosen by the experiment for each run",
    "backend": "use --backend",
    "device": "use --device",
}


def check_overrides(items: Iterable[str]) -> dict:
    """Typed `--set` items of an experiment; an OverrideError for a setting the experiment itself chooses."""
    typed = parse_overrides(items)
    for key in typed:
        if key in RUN_SETTINGS:
            raise OverrideError(f"{key} cannot be set for an experiment ({RUN_SETTINGS[key]})")
    return typed


def config_for(
    s: ExperimentSettings,
    tonemap: bool,
    known_exposure: bool = False,
    tone_settings: dict | None = None,
    model: str = "grid",
    appearance: bool = False,
) -> TrainConfig:
    """The preset's config for one run (`s.preset` for the grid, `s.nerf_preset` for NeRF): the
    experiment's options, `tone_settings` (tone-mapping settings by name, the run's own), then the
    user's `--set` overrides."""
    flags = flag_settings(
        {
            "tonemap": tonemap,
            "known_exposure": known_exposure,
            "appearance_embedding": appearance if model == "nerf" else None,
            "iters": s.iters,
            "backend": s.backend,
            "device": s.device,
        }
    )
    flags |= {f"tonemap.{key}": value for key, value in (tone_settings or {}).items()}
    base = preset(s.nerf_preset if model == "nerf" else s.preset)
    if base.model != model:
        raise OverrideError(f"preset {base.preset!r} is not a {model} preset")
    return apply_overrides(apply_overrides(base, flags), check_overrides(s.overrides))


def run_spec(
    data: Path, run: Path, s: ExperimentSettings, tonemap: bool, known_exposure: bool = False, **choice: Any
) -> RunSpec:
    """One run of an experiment: `data` trained into `run` with the experiment's configuration for it
    (`config_for`'s, whose `tone_settings`, `model` and `appearance` `choice` passes on)."""
    cfg = config_for(s, tonemap, known_exposure, **choice)
    return RunSpec(Path(data), Path(run), cfg, known_exposure)


def method_spec(
    root: Path, runs: Path, s: ExperimentSettings, m: Method, tone_settings: dict | None = None
) -> RunSpec:
    """The run of one row of an experiment's method table: `root / m.variant` into `runs / m.key`."""
    return run_spec(
        root / m.variant,
        runs / m.key,
        s,
        m.tonemap,
        tone_settings=tone_settings,
        model=m.model,
        appearance=m.appearance,
    )


def scores(model: Model, scene: SceneData, s: ExperimentSettings, truth: bool = False) -> dict:
    """Mean right-half metrics, plus the truth block for tone-mapped models on synthetic data."""
    # Beside the protocol's tone, from the same renders, the ones a view without a photo would get.
    result = evaluate(model, scene, s.backend, lpips=s.lpips, also=novel_view_tones(model))
    out = {k: result[k] for k in METRIC_KEYS if k in result}
    out["views"] = [{"index": v["index"], "psnr": v["psnr"]} for v in result["views"]]
    if "tones" in result:
        out["tones"] = {"own": result["psnr"], **result["tones"]}
    if truth and model.tonemapper is not None:
        synth = SynthTruth.load(scene.source)
        if synth is not None:
            out["truth"] = truth_report(model, synth, s.backend)
    return out


def right_half(img: np.ndarray) -> np.ndarray:
    return img[:, left_width(img.shape[1]) :]


def right_half_metrics(pred: np.ndarray, gt: np.ndarray, lpips: bool = False) -> dict:
    """PSNR, SSIM (and LPIPS when asked and available) of two images' right halves."""
    nets = ("vgg", "alex") if lpips and lpips_available() else ()
    return image_metrics(torch.as_tensor(right_half(pred)), torch.as_tensor(right_half(gt)), lpips_nets=nets)


def view_ldr(model: Model, i: int, backend: str) -> np.ndarray:
    """Test view `i` through its own learned tone (or clipped radiance without tone mapping)."""
    return model.to_ldr(model.render_camera(i, backend), i).cpu().numpy()


def strip(images: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Images of one height side by side on a white gap (for report figures)."""
    h = max(im.shape[0] for im in images)
    parts = []
    for im in images:
        pad = np.ones((h, im.shape[1], 3), dtype=np.float32)
        pad[: im.shape[0]] = np.asarray(im, dtype=np.float32)
        parts += [pad, np.ones((h, gap, 3), dtype=np.float32)]
    return np.concatenate(parts[:-1], axis=1)


def display_factor(size: tuple[int, int], long_side: int) -> int:
    """The smallest integer k for which a picture of `size` shown k times larger is at least `long_side`
    on its long side."""
    return max(1, -(-long_side // max(size)))


def enlarged(img: np.ndarray, k: int) -> np.ndarray:
    """`img` with each pixel repeated k times a side: a small render stays readable in a report without
    pretending to more detail."""
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


def labelled(img: np.ndarray, text: str, size: int = 14) -> np.ndarray:
    """`img` (H, W, 3 in [0, 1]) under a white band holding `text`: a report's pictures say what they are."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=size)
    band = Image.new("RGB", (img.shape[1], size + 8), "white")
    ImageDraw.Draw(band).text((3, 3), text, fill="black", font=font)
    return np.concatenate([np.asarray(band, dtype=np.float32) / 255.0, np.asarray(img, np.float32)], axis=0)


def mark_left_half(img: np.ndarray, k: int = 1) -> np.ndarray:
    """`img` (a test view shown with each pixel `k` x `k`) with its left half, which trained the view's
    tone, faded towards white and cut off from the scored right half by a dashed line."""
    out = np.array(img, dtype=np.float32)
    x = left_width(img.shape[1] // k) * k
    out[:, :x] = 0.55 * out[:, :x] + 0.45
    dashes = (np.arange(img.shape[0]) // 6) % 2 == 0
    out[dashes, max(x - 1, 0) : x + 1] = (0.9, 0.1, 0.1)
    return out


def stack(rows: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Image rows (e.g. `strip`s) one above the other on a white gap, padded to the widest."""
    w = max(r.shape[1] for r in rows)
    parts = []
    for r in rows:
        pad = np.ones((r.shape[0], w, 3), dtype=np.float32)
        pad[:, : r.shape[1]] = r
        parts += [pad, np.ones((gap, w, 3), dtype=np.float32)]
    return np.concatenate(parts[:-1], axis=0)
