"""The tone mapper of a run: whether it learns one (from the settings or the photos), its start from the
training pixels, and, after the last step, the gauge that says what its EVs mean (docs/method.md,
"Gauge")."""

from __future__ import annotations

import json

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.camera_spread import exif_evs
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.gauge import stops_departure
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.ray_pool import RayPool
from hdrplenoxels.train.tone_choice import EXIF_STOPS, choose_tone_mapping


def tone_mapping_choice(cfg: TrainConfig, scene: SceneData) -> tuple[bool, str]:
    """Whether the run learns a tone per photo, and why in words: as configured, or, left to the photos
    (None), as the training views' camera settings vary (`choose_tone_mapping`); a setting that acts
    through the tone mapper turns it on."""
    if cfg.tonemap.enabled is not None:
        return cfg.tonemap.enabled, "tonemap.enabled, --tonemap / --no-tonemap"
    if cfg.tone_switches():
        return True, f"{cfg.tone_switches()[0]} acts through it"
    on, why, _ = choose_tone_mapping(scene, list(scene.train_ids))
    return on, why


def initial_tonemapper(
    t: ToneMapConfig, scene: SceneData, cameras: Cameras, pool: RayPool, device: torch.device, resume: bool
) -> ToneMapper | None:
    """The per-image tone mapper of settings `t` (None when off), white balance and reference from
    training pixels only (docs/method.md, "Fixes to the reference code"). A resumed run restores its
    exposures from its checkpoint."""
    if not t.enabled:
        return None
    n = len(cameras)
    tm = ToneMapper(n, cameras.sizes, t, camera_ids=cameras.body_ids()).to(device)
    if t.known_exposure and scene.exposures is not None:
        tm.set_known_exposures(torch.as_tensor(scene.exposures))
    elif t.known_exposure and not resume:
        raise InputError(scene.source, "known-exposure mode needs an EV per view (--known-exposure)")
    if t.wb_init_from_data:
        tm.init_from_images(pool.linear_channel_means(n, t.init_gamma), list(scene.train_ids))
    else:
        tm.set_reference(scene.train_ids[0])
    stated = stated_exposures(t, scene)
    if t.exposure_hold == "always" and stated is not None:
        tm.set_stated_exposures(torch.as_tensor(stated))
    if t.exposure_init_from_metadata and not resume:
        evs = scene.extras.get("exposure_init_ev")
        if evs is None:
            raise InputError(
                scene.source,
                "no exposure metadata to start from (EXIF from `process`, HDR-NeRF exposure times)",
            )
        tm.init_exposures(torch.as_tensor(np.asarray(evs)))
    return tm


def stated_exposures(t: ToneMapConfig, scene: SceneData) -> np.ndarray | None:
    """The exposures the photos state, in stops, where they vary enough to hold the learned ones to
    (`varying`): the known-exposure EVs in that mode, else the EXIF; None otherwise."""
    stated = scene.exposures if t.known_exposure else exif_evs(scene)
    return np.asarray(stated, dtype=np.float64) if varying(stated) else None


def fit_gauge(tm: ToneMapper, t: ToneMapConfig, scene: SceneData) -> str:
    """The exponent that puts the tone-mapped outputs (the EXR, the learned EVs, `--ev`) in a linear
    scale, and a line saying which: fitted to the known exposures, or to the photos' EXIF exposures where
    they vary (true stops either way), else where the learned response looks like a camera's
    (`output_prior_gamma`: a learned scale). Self-calibration alone cannot tell (docs/method.md,
    "Gauge")."""
    held = "; held to them while training" if tm.stated_stops is not None else ""
    if t.known_exposure:
        a = tm.fit_exponent_to_known()
        off = departure(tm, tm.known_log_exposure.cpu().double().numpy() / np.log(2.0))
        return (
            f"EV in true stops: fitted to the known exposures (a = {a:.3f}{held}; "
            f"the learned EVs {off:.2f} stop RMS from them)"
        )
    evs = exif_evs(scene)
    why = "the photos have no EXIF exposure"
    if varying(evs):
        try:
            a = tm.fit_exponent_to_exposures(torch.as_tensor(evs))
            span = float(evs.max() - evs.min())
            return (
                f"EV in true stops: fitted to the photos' EXIF exposures ({span:.2f} stops; "
                f"a = {a:.3f}{held}; the learned EVs {departure(tm, evs):.2f} stop RMS from them)"
            )
        except ValueError as e:
            why = f"the learned exposures do not follow the photos' EXIF ones ({e})"
    elif evs is not None:
        why = "the photos' EXIF exposures do not vary"
    if t.output_prior_gamma:
        tm.fit_exponent_to_response_prior(t.output_prior_gamma)
    return f"EV in the learned scale ({why}; --known-exposure gives true stops)"


def varying(evs: np.ndarray | None) -> bool:
    """Whether the exposures the photos state (None: not every photo has one) vary enough to say the
    camera's exposure changed (`tone_choice.EXIF_STOPS`)."""
    return evs is not None and float(evs.max() - evs.min()) > EXIF_STOPS


def departure(tm: ToneMapper, evs: np.ndarray) -> float:
    """Root mean square in stops of the learned EVs about the stated ones (EXIF or a known-exposure
    file) once the gauge is fitted to them (`gauge.stops_departure`)."""
    return stops_departure(tm.effective_log_wb().detach().mean(1), torch.as_tensor(evs))


def camera_truth(scene: SceneData) -> dict | None:
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


def finish_tones(tm: ToneMapper, t: ToneMapConfig, scene: SceneData) -> tuple[str, dict]:
    """After the last step: each curve made monotonic where `t.response` says so (before the gauge: the
    outputs invert the final curves), the gauge fitted; the line saying what the EVs mean, and the learned
    tones as `tone_params.json` holds them, readable without loading the model."""
    with torch.no_grad():
        tm.constrain()
    note = fit_gauge(tm, t, scene)
    return note, tm.parameters_dict() | {"names": scene.names, "ev_scale": note}
