"""`hdrplenoxels synth`: render a scene's HDR truth once, then capture it with simulated cameras.

Output (OUT):
  hdr/view_XXX.exr                  linear HDR truth per view (never read by training)
  hdr/transforms.json, poses_bounds.npy  the cameras, from which `capture_dataset` makes more datasets
  varying/, static/                 one dataset per variant (and auto/ with `--camera auto`: a phone's auto
                                    exposure and white balance, `pipeline.auto_settings`), each with
    transforms.json                 nerfstudio layout (OpenGL camera-to-world, intrinsics, scene hints)
    images/view_XXX.png             the 8-bit LDR inputs
    camera_truth.json               per view: EV, white-balance gains, response curve (256 samples),
                                    vignetting, noise settings
    poses_bounds.npy                LLFF layout, forward-facing scenes only
  synth.json                        scene, resolution, samples per pixel (training and test views), render
                                    time, dynamic range, radiance percentiles, saturation per EV, share
                                    of pixels beyond the box (box scenes)
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_write, atomic_write_text
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.image_io import read_exr, write_exr, write_png
from hdrplenoxels.data.llff import write_llff
from hdrplenoxels.data.protocol import every_nth_split
from hdrplenoxels.geometry.cameras import image_rays, opencv_to_opengl
from hdrplenoxels.synth.mitsuba_render import load_scene_dict, render_view, select_variant
from hdrplenoxels.synth.pipeline import (
    PIPELINE_ORDER,
    SEED_RENDER,
    CameraSettings,
    PipelineConfig,
    auto_settings,
    capture,
    draw_settings,
    sensor_irradiance,
    view_seed,
)
from hdrplenoxels.synth.scenes import SCENES, SceneRig

VARIANTS = ("varying", "static")
AUTO_VARIANT = "auto"  # captured on request: its cameras follow the scene, not a seeded draw
DEPTH_SPP = 4


@dataclass
class SynthOptions:
    n_views: int = 50
    width: int | None = None  # None: the scene's CPU-sized default
    height: int | None = None
    spp: int | None = None
    # Samples per pixel of the test views (None: as `spp`). Their right halves are scored, and Monte Carlo
    # noise no model can predict otherwise sets a floor under every score; rendering only every 8th view
    # finely keeps the scored truth clean at a fraction of the cost of rendering all views so.
    test_spp: int | None = None


def view_name(i: int) -> str:
    return f"view_{i:03d}"


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def dynamic_range_stops(hdrs: list[np.ndarray]) -> float:
    """log2 of the 99.9th over the 1st percentile of non-zero luminance over all views.

    Percentiles keep Monte Carlo fireflies out; zero pixels (a hidden, black background) carry no
    dynamic range and are left out.
    """
    lum = np.concatenate([luminance(h).ravel() for h in hdrs])
    lo, hi = np.percentile(lum[lum > 0], [1.0, 99.9])
    return float(np.log2(hi / lo))


def radiance_percentiles(hdrs: list[np.ndarray]) -> dict[str, float]:
    """Luminance of the truth over all views: median, 99th, 99.9th percentile and maximum (the brightest
    emitter seen, e.g. a sun's disk)."""
    lum = np.concatenate([luminance(h).ravel() for h in hdrs])
    p50, p99, p999 = np.percentile(lum, [50.0, 99.0, 99.9])
    return {"p50": float(p50), "p99": float(p99), "p99.9": float(p999), "max": float(lum.max())}


def saturation_by_ev(hdrs: list[np.ndarray], evs) -> dict[str, float]:
    """Fraction of pixels with a clipped channel when every view is shot at each EV (neutral WB)."""
    out = {}
    for ev in evs:
        sat = [(sensor_irradiance(h, CameraSettings(ev=float(ev))) >= 1.0).any(-1).mean() for h in hdrs]
        out[f"{ev:+g}"] = float(np.mean(sat))
    return out


def depth_scene(rig: SceneRig):
    """The scene with an integrator that renders each pixel's distance along its ray (0 where rays miss)."""
    return load_scene_dict({**rig.scene, "integrator": {"type": "aov", "aovs": "dd.y:depth"}})


def beyond_box_fraction(rig: SceneRig) -> float:
    """Share of all views' pixels whose first surface lies outside the scene box, or that see no surface
    (the sky): what a model of the box alone cannot explain. From the cheap depth render at pixel centres'
    rays; a pixel straddling an edge counts by its mean distance."""
    scene, lo, hi = depth_scene(rig), np.asarray(rig.aabb[0]), np.asarray(rig.aabb[1])
    outside = []
    for i in range(len(rig.cameras)):
        dist = render_view(scene, rig.cameras, i, DEPTH_SPP)[..., 0].reshape(-1, 1).astype(np.float64)
        origins, dirs = image_rays(rig.cameras, i)
        hit = origins.double().numpy() + dist * dirs.double().numpy()
        inside = ((hit >= lo - 1e-3) & (hit <= hi + 1e-3)).all(-1) & (dist[:, 0] > 0)
        outside.append(~inside)
    return float(np.concatenate(outside).mean())


def depth_bounds(rig: SceneRig) -> list[tuple[float, float]]:
    """Per-view (near, far) camera-z depth, from a cheap depth render (as LLFF takes them from SfM points)."""
    scene = depth_scene(rig)
    bounds = []
    for i in range(len(rig.cameras)):
        dist = render_view(scene, rig.cameras, i, DEPTH_SPP)[..., 0].reshape(-1)  # distance along the ray
        _, dirs = image_rays(rig.cameras, i)
        z = dist * (dirs.double().numpy() @ rig.cameras.c2w[i][:3, 2])  # -> depth along the optical axis
        z = z[dist > 0]
        bounds.append((float(np.percentile(z, 0.5) * 0.9), float(np.percentile(z, 99.9) * 1.1)))
    return bounds


def transforms_json(rig: SceneRig, bounds, names: list[str]) -> dict:
    fx, fy, cx, cy = rig.cameras.intrinsics[0]
    w, h = rig.cameras.size(0)
    meta = {"camera_model": "PINHOLE", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(w), "h": int(h)}
    if rig.forward_facing:
        meta["forward_facing"] = True
        meta["near_far"] = [min(b[0] for b in bounds), max(b[1] for b in bounds)]
    else:
        meta["forward_facing"] = False
        meta["aabb"] = [list(rig.aabb[0]), list(rig.aabb[1])]
    if rig.aabb_scale is not None:
        meta["aabb_scale"] = rig.aabb_scale
    if rig.background is not None:
        meta["background"] = rig.background
    meta["frames"] = [
        {"file_path": f"images/{n}.png", "transform_matrix": opencv_to_opengl(rig.cameras.c2w[i]).tolist()}
        for i, n in enumerate(names)
    ]
    return meta


OUTPUTS = ("hdr", *VARIANTS, AUTO_VARIANT, "synth.json")


def claim_output(out: Path, overwrite: bool) -> None:
    """Never mix two renders: an OUT holding one is refused unless overwriting, which removes it first."""
    existing = [out / name for name in OUTPUTS if (out / name).exists()]
    if existing and not overwrite:
        raise InputError(out, "already holds a synthesised scene; pass --overwrite to replace it")
    for path in existing:
        shutil.rmtree(path) if path.is_dir() else path.unlink()


def capture_dataset(
    root: Path,
    folder: Path,
    variant: str,
    pipeline: PipelineConfig,
    settings_for: Callable[[int], CameraSettings] | None = None,
) -> None:
    """Capture the HDR truth under `root/hdr` with simulated cameras into a dataset `folder`.

    Re-capturing the same truth with other settings (exposure range, noise, response) costs seconds,
    while the Mitsuba render costs minutes: experiments render once and capture many times.
    `settings_for` (view index -> camera) replaces the variant's seeded draw, for cameras an experiment
    derives itself (they must follow from `pipeline`, which is what a kept capture is matched on). The
    `auto` variant meters each view's truth instead (`auto_settings`).
    """
    root, folder = Path(root), Path(folder)
    meta = json.loads((root / "hdr" / "transforms.json").read_text())
    views = []
    for i, frame in enumerate(meta["frames"]):
        name = Path(frame["file_path"]).stem
        hdr = read_exr(root / "hdr" / f"{name}.exr")
        if settings_for is not None:
            settings = settings_for(i)
        elif variant == "auto":
            settings = auto_settings(i, hdr, pipeline)
        else:
            settings = draw_settings(i, variant, pipeline)
        write_png(folder / "images" / f"{name}.png", capture(hdr, settings))
        hdr_rel = os.path.relpath(root / "hdr" / f"{name}.exr", folder)
        views.append({"file": frame["file_path"], "hdr": hdr_rel, **settings.to_dict()})
    truth = {"variant": variant, "pipeline": asdict(pipeline), "order": PIPELINE_ORDER, "views": views}
    atomic_write_text(folder / "camera_truth.json", json.dumps(truth, indent=1))
    atomic_write_text(folder / "transforms.json", json.dumps(meta, indent=1))
    bounds = root / "hdr" / "poses_bounds.npy"
    if bounds.exists():
        atomic_write(folder / "poses_bounds.npy", lambda p: shutil.copyfile(bounds, p))


def synthesize(
    scene_name: str,
    out: Path,
    opts: SynthOptions | None = None,
    pipeline: PipelineConfig | None = None,
    progress=None,
    overwrite: bool = False,
    auto: bool = False,
) -> dict:
    """Render `scene_name` into `out` (layout in the module docstring); returns the synth.json summary.
    `auto`: also capture the `auto` variant."""
    opts, pipeline = opts or SynthOptions(), pipeline or PipelineConfig()
    spec = SCENES[scene_name]
    width, height = opts.width or spec.width, opts.height or spec.height
    spp = opts.spp or spec.spp
    test_spp = opts.test_spp or spp
    _, test_views = every_nth_split(opts.n_views)
    out = Path(out)
    claim_output(out, overwrite)
    rig = spec.build(opts.n_views, width, height)
    names = [view_name(i) for i in range(opts.n_views)]
    t0 = time.perf_counter()
    scene = load_scene_dict(rig.scene)
    hdrs = []
    for i in range(opts.n_views):
        view_spp = test_spp if i in test_views else spp
        hdrs.append(
            render_view(scene, rig.cameras, i, view_spp, seed=view_seed(pipeline.seed, SEED_RENDER, i))
        )
        write_exr(out / "hdr" / f"{names[i]}.exr", hdrs[-1])
        if progress:
            progress(i + 1, opts.n_views)
    render_seconds = time.perf_counter() - t0
    bounds = depth_bounds(rig) if rig.forward_facing else None
    meta = transforms_json(rig, bounds, names)
    atomic_write_text(out / "hdr" / "transforms.json", json.dumps(meta, indent=1))
    if bounds is not None:
        write_llff(out / "hdr", rig.cameras, bounds)
    for variant in (*VARIANTS, AUTO_VARIANT) if auto else VARIANTS:
        capture_dataset(out, out / variant, variant, pipeline)
    summary = {
        "scene": scene_name,
        "description": rig.description,
        "resolution": [width, height],
        "views": opts.n_views,
        "spp": spp,
        "test_spp": test_spp,
        "mitsuba_variant": select_variant(),
        "render_seconds": render_seconds,
        "dynamic_range_stops": dynamic_range_stops(hdrs),
        "radiance_percentiles": radiance_percentiles(hdrs),
        "saturated_fraction_by_ev": saturation_by_ev(hdrs, sorted(set(pipeline.ev_set) | {0.0})),
        "test_views": test_views,
    }
    if rig.aabb is not None:
        summary["beyond_box_fraction"] = beyond_box_fraction(rig)
    atomic_write_text(out / "synth.json", json.dumps(summary, indent=1))
    return summary
