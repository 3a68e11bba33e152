"""Truth-recovery scoring: the exponent fit, the aligned errors, and the CRF RMSE behave as documented."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hdrplenoxels.eval.truth import (
    RadianceAlignment,
    SynthTruth,
    crf_rmse,
    fit_exponent,
    gain_errors,
    interior,
    mu_law,
    recordable,
)
from hdrplenoxels.tonemap.response import CRF_SEGMENTS, ResponseCurve, knot_positions


def true_gains(n: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    evs = rng.choice([-3.0, 0.0, 3.0], n)
    wb = np.zeros((n, 3))
    wb[np.arange(n), rng.integers(0, 3, n)] = np.log2(1.25)
    return evs[:, None] + wb


def test_fit_exponent_recovers_slope_and_offsets():
    true = true_gains()
    learned = 0.6 * true + np.array([0.3, -0.1, 0.2])
    a, offset = fit_exponent(learned, true)
    assert a == pytest.approx(0.6) and np.allclose(offset, [0.3, -0.1, 0.2])
    errs = gain_errors(learned, true, a, offset)
    assert errs["ev_error_stops"] == pytest.approx(0.0, abs=1e-9)
    assert errs["wb_error_stops"] == pytest.approx(0.0, abs=1e-9)
    noisy = learned.copy()
    noisy[0] += 0.6 * 0.5  # view 0 half a stop too bright (in learned units: a x 0.5)
    assert gain_errors(noisy, true, a, offset)["ev_error_stops"] > 0.03


@pytest.mark.parametrize("a", [1.0, 0.5])
def test_crf_rmse_is_zero_for_the_ambiguous_equivalent_curve(a):
    """A model with radiance^a learns CRF(x^(1/a)); aligned by a, it scores as the true curve."""
    x = np.linspace(0, 1, 256)
    true_curve = x ** (1 / 3)
    pos = torch.as_tensor(knot_positions(CRF_SEGMENTS + 1, 0.5))
    learned = ResponseCurve((pos ** (1 / (3 * a)))[None].expand(3, -1).float(), 0.5)
    rmse, gains = crf_rmse(learned, true_curve, a)
    assert rmse < 0.005 and np.allclose(gains, 1.0, atol=0.02)
    wrong, _ = crf_rmse(learned, true_curve, 1.0 if a != 1.0 else 0.5)
    assert wrong > 0.03


def test_recordable_needs_one_view_neither_clipped_nor_black():
    truth = SynthTruth(
        true_log2_gain=np.array([[0.0] * 3, [-3.0] * 3]),
        evs=np.array([0.0, -3.0]),
        curves=np.tile(np.linspace(0, 1, 256), (2, 1)),  # linear response: black below 0.5/255
        hdr_paths=[],
    )
    radiance = np.array([[1e-4] * 3, [0.5] * 3, [4.0] * 3, [20.0] * 3])
    ok = recordable(truth, radiance, [0, 1])
    assert ok[:, 0].tolist() == [False, True, True, False]  # too dark for both; clipped in both
    assert recordable(truth, radiance, [0])[:, 0].tolist() == [False, True, False, False]


def test_interior_drops_pixels_beside_unrecorded_ones_and_the_border():
    mask = np.ones((6, 7, 3), dtype=bool)
    mask[2, 3, 1] = False  # one unrecorded pixel in channel 1
    inner = interior(mask)
    assert not inner[0].any() and not inner[:, -1].any()  # the image border has missing neighbours
    assert not inner[1:4, 2:5, 1].any() and inner[1:4, 2:5, 0].all()  # its 3x3 block, that channel only
    assert inner[4, 5].all() and inner.sum() == 4 * 5 * 3 - 9


def test_mu_law_maps_unit_range_monotonically():
    y = mu_law(np.array([0.0, 1e-3, 0.1, 1.0]))
    assert y[0] == 0.0 and y[-1] == pytest.approx(1.0) and np.all(np.diff(y) > 0)


def test_radiance_alignment_maps_between_the_learned_and_the_true_gauge():
    """Learned radiance is g_c L^a: `to_true` undoes it and `to_learned` applies it (the median
    report swaps radiances between our camera and the true one with these)."""
    rng = np.random.default_rng(0)
    true = rng.uniform(0.01, 8.0, size=(4, 5, 3))
    alignment = RadianceAlignment(0.5, np.array([0.3, -0.2, 0.1]))
    learned = np.exp2(alignment.log2_g) * true**0.5
    assert np.allclose(alignment.to_learned(true), learned)
    assert np.allclose(alignment.to_true(learned), true)


def test_synth_truth_is_none_without_true_radiance(tmp_path):
    """A re-shoot of real photos has simulated cameras but no HDR: not a synthetic scene's truth."""
    view = {"ev": 1.0, "wb_gains": [1.0, 1.0, 1.0], "crf_curve": [i / 255 for i in range(256)]}
    (tmp_path / "camera_truth.json").write_text(json.dumps({"views": [view]}))
    assert SynthTruth.load(tmp_path) is None
    (tmp_path / "camera_truth.json").write_text(json.dumps({"views": [view | {"hdr": "hdr/0.exr"}]}))
    truth = SynthTruth.load(tmp_path / "transforms.json")
    assert truth is not None and truth.hdr_paths == [tmp_path / "hdr/0.exr"] and truth.evs.tolist() == [1.0]
