"""Settings of the tone mapper (`ToneMapper`), and the named setting for sparse brackets.

Each default was chosen on validation renders (`experiment validation`), never on the experiments' test
views; the measurements behind them are in JOURNAL.md ("Tone-mapping defaults").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from hdrplenoxels.core.settings import at_most_one, positive, setting

CrfSharing = Literal["image", "camera", "scene"]

# Settings for brackets of few exposures far apart (the table-s2 experiment, `train --sparse-bracket`),
# chosen on validation renders trained on -3 and +3 EV views only (JOURNAL.md).
SPARSE_BRACKET = {"lambda_crf_loglog": 1e-2, "saturation_weighting": True}


@dataclass
class ToneMapConfig:
    """The per-image tone mapper (docs/method.md, "Tone mapping"), its regularisers and optimiser."""

    enabled: bool | None = None
    """Learn a tone per photo (HDR-Plenoxels) or not (plain Plenoxels). None, the default in every preset:
    on where the photos' camera settings vary and off for one fixed camera, as measured from the photos
    when the run starts (`train.tone_choice`)."""
    crf_sharing: CrfSharing = "camera"
    """One curve per camera (a physical camera has one response; cameras are told apart by image size,
    `Cameras.body_ids`); per image (the paper's choice) remains for data with mixed responses.
    Measured: JOURNAL.md."""
    leak: float = setting(0.01, at_least=0.0, below=1.0)
    """Slope of the response beyond [0, 1] while training."""
    lambda_crf_smooth: float = setting(1e-3, at_least=0.0)
    """Weight of the squared second differences of the knots ([-1, 1] units)."""
    lambda_crf_loglog: float = setting(0.0, at_least=0.0)
    """Weight of the squared second differences of log2 response vs log2 irradiance. A power law is a
    straight line there, so every gauge a of the exponential ambiguity costs nothing; what it removes is
    the wiggle, periodic in log irradiance, that few exposure ratios leave free (docs/method.md, "Tone
    mapping"). Needed for sparse brackets, off otherwise: JOURNAL.md."""
    response: Literal["monotonic", "free"] = "monotonic"
    """"monotonic": the paper's free knots while training, then each curve made non-decreasing, as a
    camera's is (`ToneMapper.constrain`, before the gauge is fitted): a curve that goes down has no
    inverse, so the HDR of such a view would not be the light that made the photo. Projecting after
    every update instead cost PSNR (JOURNAL.md, "A monotonic response"). "free": the paper's free
    knots, left as learned."""
    knot_power: float = setting(1.0, check=positive)
    """Knot k sits at irradiance (k / 256)^(1 / knot_power). 1 is the paper's even spacing; smaller
    values put more knots in the shadows, where camera responses are steepest."""
    init_gamma: float = setting(1.0, check=positive)
    """The starting response x^(1 / init_gamma); the white balance starts from image means linearised by
    the same gamma. The start sets the gauge the grid learns in, and the grid fits better near the pixels'
    own encoding, so the curve starts linear, not at the paper's 2.2 (docs/method.md, "Gauge"; measured:
    JOURNAL.md). Outputs are put back in a linear gauge (`output_prior_gamma`)."""
    vignetting: bool = False
    """Learn a radial vignetting per camera."""
    saturation_weighting: bool = False
    """Down-weight near-black and near-white targets in the loss (docs/method.md, "Tone mapping"). Off
    here, as the paper trains; on in the CPU grid presets (`presets.CPU_TONE_LOSS`), where it was chosen
    on validation views of real re-shoots together with the refit (`refit_steps`)."""
    refit_steps: int = setting(300, at_least=0)
    """After the last step the response curves are fitted once more to the field's renders with the field
    frozen, on the unweighted error, by this many full-batch Adam steps (0: not at all). With nothing
    left to trade against, the curves settle where the photos put them: it takes back part of what
    `saturation_weighting` costs the curve and keeps its pictures (docs/method.md, "Tone refit")."""
    refit_pixels: int = setting(1 << 18, at_least=1)
    """Pooled pixels the refit renders once: all of them in a pool no larger, else this many drawn
    uniformly."""
    refit_lr: float = setting(1e-3, at_least=0.0)
    """The refit's Adam learning rate (the fit stops falling within about 100 steps)."""
    lr: float = setting(1e-2, at_least=0.0)
    """Adam learning rate of the tone parameters at the start of the decay."""
    lr_final: float = setting(5e-6, at_least=0.0)
    """Their learning rate at `lr_decay_steps`."""
    lr_decay_steps: int = setting(250_000, at_least=1)
    """Steps of the exponential decay."""
    wb_init_from_data: bool = True
    """Start each view's white balance and exposure from its training pixels' means (else all at 1)."""
    exposure_init_from_metadata: bool = False
    """Start each view's exposure from the dataset's metadata (EXIF via `process`, HDR-NeRF exposure
    times) instead of image statistics; colour balance still starts from the data. A start only."""
    known_exposure: bool = False
    """Known exposure values (EXIF, or the generator's EVs) fix the exponential ambiguity of
    self-calibration: after training, a is fitted to the learned vs known exposures and every output is
    linearised by it (docs/method.md, "Gauge"; pinning them during training instead:
    JOURNAL.md)."""
    exposure_hold: Literal["checked", "always", "off"] = "checked"
    """Whether training holds the learned exposures' ratios to the ones the photos state (the
    `known_exposure` EVs, else their EXIF, where they span more than a third of a stop;
    `lambda_exposure_ratios`). A bracket's few exposure steps leave the exposures and the curve a bend
    to trade, so exact stated exposures (a bracket on a tripod, HDR-NeRF's exposure times) come back a
    tenth or two of a stop off unless held; but real cameras' EXIF departs from what their JPEGs show by
    a fifth to a third of a stop, and holding to it cost validation views of real captures. "checked":
    held from `exposure_check_at` of the schedule on where the learned EVs are by then within
    `exposure_hold_within` of the stated ones, so the pixels say whether the EXIF is exact
    (`train/exposure_hold.py`); "always": from the first step; "off": never (docs/method.md, "Gauge";
    measured: JOURNAL.md, "Holding exposures to the stated ones")."""
    lambda_exposure_ratios: float = setting(0.2, at_least=0.0)
    """Weight of the hold, where it acts: the mean squared departure of each view's log exposure from a
    line in its stated one, slope and offset fitted at each step (the slope is the exponent
    self-calibration leaves free)."""
    exposure_check_at: float = setting(0.2, at_least=0.0, check=at_most_one)
    """The fraction of the schedule after which "checked" compares the learned exposures with the stated
    ones: early, before the bend has grown, and late enough for the exposures to have left their start
    (JOURNAL.md)."""
    exposure_hold_within: float = setting(0.15, at_least=0.0)
    """Root mean square in stops, after the exponent is fitted, within which the learned EVs count as
    following the stated ones at the check: between what exact stated exposures and real cameras' EXIF
    measured there (JOURNAL.md)."""
    lambda_sh_view: float = setting(1e-6, at_least=0.0)
    """L2 on the grid's SH coefficients beyond the DC term, with the tone mapper only. Without it the SH
    absorb a per-view exposure that varies smoothly with the view direction, which biases the learned EVs
    and novel views' radiance (docs/method.md, "Training"; the weight's scan: JOURNAL.md)."""
    sh_view_until: float = setting(2.0 / 3.0, at_least=0.0, check=at_most_one)
    """The view prior applies for this fraction of the schedule only: where a step's rays miss a voxel,
    RMSProp turns the prior's tiny gradient into a pull of about one learning rate per step towards no
    view dependence, which costs fine detail; the exposure bias it prevents forms early
    (JOURNAL.md)."""
    output_prior_gamma: float | None = setting(2.2, check=positive)
    """Without known exposures the exponent is a free gauge; outputs (EXR, EV controls, the exported
    curves) use the one in which the learned response is closest to x^(1 / output_prior_gamma), the usual
    display-referred camera response. None: the learned gauge (docs/method.md, "Gauge")."""
