"""Whether training holds the learned exposures to the stated ones, decided from the pixels at a step of the
schedule (`train/exposure_hold.py`), and the decision kept across a resume."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_train import tiny_config

from hdrplenoxels.grid.io import load_grid
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.gauge import stops_departure
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.exposure_hold import check_exposures, check_step
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR
from hdrplenoxels.train.trainer import Trainer

EVS = np.array([0.0, -1.0, -2.0, 1.0, 2.0, 0.0])


def test_the_departure_is_taken_in_the_fitted_gauge():
    """Learned log levels a * ln2 * EV plus an offset depart by nothing, whatever a; a view 0.3 stop off
    among six departs by its share of the RMS about the refitted line."""
    stated = torch.as_tensor(EVS)
    exact = 0.37 * math.log(2.0) * stated + 0.5
    assert stops_departure(exact, stated) == pytest.approx(0.0, abs=1e-9)
    bent = exact.clone()
    bent[3] += 0.37 * math.log(2.0) * 0.3
    assert 0.05 < stops_departure(bent, stated) < 0.3 / math.sqrt(6)
    with pytest.raises(ValueError, match="do not follow"):
        stops_departure(torch.zeros(6), stated)


def mapper(off_stops: float) -> ToneMapper:
    """Six views whose learned exposures follow EVS in the gauge a = 0.4, the +1 EV view `off_stops` off."""
    tm = ToneMapper(6, np.tile([16, 16], (6, 1)), ToneMapConfig(enabled=True))
    level = (
        0.4
        * math.log(2.0)
        * (torch.as_tensor(EVS, dtype=torch.float32) + torch.tensor([0, 0, 0, off_stops, 0, 0]))
    )
    with torch.no_grad():
        tm.log_wb.copy_(level[:, None].expand(-1, 3))
    tm.set_reference(0)
    return tm


def test_exposures_are_held_only_where_they_already_follow_the_stated_ones():
    t = ToneMapConfig(enabled=True)
    close, far = mapper(0.1), mapper(1.0)
    said = check_exposures(close, t, EVS, 120)
    assert said.startswith("exposures held to the stated ones from step 120")
    assert close.stated_stops is not None and close.stated_stops.tolist() == EVS.tolist()
    said = check_exposures(far, t, EVS, 120)
    assert said.startswith("exposures not held") and "from them (held within 0.15)" in said
    assert far.stated_stops is None
    assert check_exposures(mapper(0.0), t, None, 120) == ""  # the photos state none that vary


def test_the_check_comes_at_its_fraction_of_the_schedule_and_only_where_checked():
    t = ToneMapConfig(enabled=True)
    assert check_step(t, 600) == 120 and check_step(replace(t, exposure_check_at=0.0), 600) == 1
    assert check_step(replace(t, exposure_hold="always"), 600) is None
    assert check_step(replace(t, exposure_hold="off"), 600) is None
    assert check_step(replace(t, lambda_exposure_ratios=0.0), 600) is None


def bracketed(scene, evs: np.ndarray):
    """The scene's photos re-exposed by `evs` (stops, one a view), which their EXIF then states."""
    images = [
        np.clip(np.asarray(img, np.float64) * 2.0**ev, 0, 255).round().astype(np.uint8)
        for img, ev in zip(scene.images, evs, strict=True)
    ]
    return replace(scene, images=images, extras={**scene.extras, "exposure_init_ev": evs})


@pytest.mark.parametrize("within", [100.0, 0.0], ids=["held", "not held"])
def test_the_decision_is_kept_in_checkpoints_and_by_a_resume(tiny_scene, tmp_path, within):
    evs = np.array([0.0, -1.0] * (len(tiny_scene.names) // 2) + [0.0] * (len(tiny_scene.names) % 2))
    scene = bracketed(tiny_scene, evs)

    def config(n_iters: int):
        cfg = tiny_config(n_iters)
        cfg.device = "cpu"
        cfg.tonemap.enabled = True
        cfg.tonemap.exposure_check_at = 0.2  # step 4 of 20, 8 of 40
        cfg.tonemap.exposure_hold_within = within
        return cfg

    first = Trainer(scene, config(20), tmp_path)
    assert first.tonemapper.stated_stops is None  # nothing held before the check
    first.run(progress=False)
    held = within > 0
    assert (first.tonemapper.stated_stops is not None) == held
    _, meta, _ = load_grid(tmp_path / CHECKPOINT_DIR / "step_0000015.npz")
    assert meta["exposures_held"] == held
    resumed = Trainer(scene, config(40), tmp_path, resume=True)  # past its own check step
    assert resumed.step == 20 and (resumed.tonemapper.stated_stops is not None) == held
