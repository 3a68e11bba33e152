"""Which stated exposures a run holds its learned exposures' ratios to (`train/tone_setup.py`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.train.tone_setup import initial_tonemapper

N = 4


class ChannelMeans:
    """What the tone mapper's start reads of a ray pool: each view's linearised channel means."""

    def linear_channel_means(self, n: int, gamma: float) -> torch.Tensor:
        return torch.full((n, 3), 0.3)


def scene(exif: list[float], known: list[float] | None) -> SceneData:
    cams = Cameras(
        np.tile(np.eye(4), (N, 1, 1)), np.tile([20.0, 20.0, 8.0, 8.0], (N, 1)), np.tile([16, 16], (N, 1))
    )
    images = [np.zeros((16, 16, 3), np.uint8)] * N
    out = SceneData(images, cams, list("abcd"), [0, 1, 2], [3], source="scene.json")
    out.extras["exposure_init_ev"] = np.array(exif)
    out.exposures = None if known is None else np.array(known)
    return out


@pytest.mark.parametrize("known", [None, [0.0, -1.0, -2.0, 0.5]], ids=["EXIF", "a known-exposure file"])
def test_the_ratios_held_from_the_start_are_the_known_exposures_else_the_exif(known):
    s = scene([0.0, 1.0, 2.0, 3.0], known)
    t = ToneMapConfig(enabled=True, known_exposure=known is not None, exposure_hold="always")
    start = (s, s.cameras, ChannelMeans(), torch.device("cpu"), False)
    held = initial_tonemapper(t, *start).stated_stops
    assert held is not None and held.tolist() == (known or [0.0, 1.0, 2.0, 3.0])
    for later_or_never in ("checked", "off"):  # "checked" decides at its step (test_exposure_hold.py)
        assert initial_tonemapper(replace(t, exposure_hold=later_or_never), *start).stated_stops is None
    # EXIF within a third of a stop says the camera did not change its exposure: nothing to hold
    still = scene([0.0, 0.1, 0.2, 0.3], None)
    steady = (still, still.cameras, ChannelMeans(), torch.device("cpu"), False)
    assert initial_tonemapper(replace(t, known_exposure=False), *steady).stated_stops is None
