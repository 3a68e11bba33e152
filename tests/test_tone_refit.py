"""The response refitted after the last step with the field frozen (`train/tone_refit.py`)."""

from __future__ import annotations

import copy
from functools import partial

import numpy as np
import pytest
import torch

from hdrplenoxels.cli.main import main
from hdrplenoxels.render.fields import render_field
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.ray_pool import RayPool
from hdrplenoxels.train.tone_refit import RefitPixels, refit_pixels, refit_tone
from hdrplenoxels.train.trainer import Trainer


def pixels_of(tm: ToneMapper, n: int = 4096, seed: int = 0) -> RefitPixels:
    """Pixels whose photos `tm` took of random radiance (its curves as at test: clipped)."""
    g = torch.Generator().manual_seed(seed)
    n_images = tm.log_wb.shape[0]
    radiance = torch.rand(n, 3, generator=g) * 1.5
    ids = torch.randint(0, n_images, (n,), generator=g)
    rows, cols = torch.randint(0, 8, (n,), generator=g), torch.randint(0, 8, (n,), generator=g)
    with torch.no_grad():
        target = tm(radiance, ids, rows, cols, training=False)
    return RefitPixels(radiance, target, ids, rows, cols)


def test_refit_finds_the_response_and_keeps_the_exposures():
    cfg = ToneMapConfig(refit_steps=300, refit_lr=1e-2)
    truth = ToneMapper(4, np.full((4, 2), 8), cfg, reference=0)
    with torch.no_grad():
        truth.log_wb.copy_(torch.tensor([[0.0] * 3, [0.7] * 3, [-0.7] * 3, [0.2, 0.0, -0.3]]))
        truth.crf_interior.copy_(truth.crf_interior ** (1 / 2.2))  # a display-like response
    pixels = pixels_of(truth)
    start = copy.deepcopy(truth)
    with torch.no_grad():
        start.crf_interior.copy_(truth.crf_interior**1.3)  # a straighter curve
    gains = start.effective_log_wb().clone()
    before, after = refit_tone(start, cfg, pixels)
    assert after < before / 10
    error = (start.knots() - truth.knots()).abs()
    assert error.max() < 0.03 and error.mean() < 0.01
    # The exposures and white balance stay as trained (on the unweighted error clipped pixels would pull
    # them), and so does the reference that fixes the gauge.
    assert torch.equal(start.effective_log_wb(), gains)
    assert all(p.grad is None for p in start.parameters())


def test_refit_fits_the_unweighted_error():
    """Saturation weighting is for training the field; the refit sees every code, clipped ones too."""
    cfg = ToneMapConfig(saturation_weighting=True, refit_steps=0)
    tm = ToneMapper(2, np.full((2, 2), 8), cfg)
    pixels = pixels_of(tm)
    with torch.no_grad():
        tm.log_wb[1] += 0.5
        before, after = refit_tone(tm, cfg, pixels)
        pred = tm(pixels.radiance, pixels.image_ids, pixels.rows, pixels.cols, training=True)
        assert before == after == pytest.approx(float(tm.loss(pred, pixels.target, weighted=False)))
        assert before != pytest.approx(float(tm.loss(pred, pixels.target)))


def short_run(scene, out, refit_steps: int) -> Model:
    cfg = preset("fast")
    cfg.tonemap.enabled = True
    cfg.optim.n_iters = 150
    cfg.tonemap.refit_steps = refit_steps
    return Trainer(scene, cfg, out).run(progress=False)


def test_a_run_ends_with_the_refit(tiny_scene, tmp_path):
    scene = tiny_scene  # the suite's tiny procedural scene (conftest), the tone mapper forced on
    kept = short_run(scene, tmp_path / "kept", refit_steps=0)
    refitted = short_run(scene, tmp_path / "refit", refit_steps=300)
    # The field and the gains are the same to the bit; only the curves moved, and they fit the field's
    # renders better.
    assert torch.equal(kept.field.density, refitted.field.density)
    assert torch.equal(kept.field.sh, refitted.field.sh)
    assert torch.equal(kept.tonemapper.effective_log_wb(), refitted.tonemapper.effective_log_wb())
    assert not torch.equal(kept.tonemapper.crf_interior, refitted.tonemapper.crf_interior)
    pool = RayPool(scene.images, kept.cameras, kept.geometry, scene.train_ids, scene.test_ids, "right-half",
                   torch.device("cpu"))  # fmt: skip
    render = partial(render_field, kept.field, opt=kept.render_opt, background=kept.background)
    pixels = refit_pixels(pool, render, 1 << 14, seed=7)

    @torch.no_grad()
    def fit(model: Model) -> float:
        tm = model.tonemapper
        pred = tm(pixels.radiance, pixels.image_ids, pixels.rows, pixels.cols, training=True)
        return float(((pred - pixels.target) ** 2).mean())

    assert fit(refitted) < fit(kept)
    # Its curves are monotonic after the refit too (`ToneMapper.constrain` runs after it).
    knots = refitted.tonemapper.knots()
    assert bool((knots[..., 1:] >= knots[..., :-1]).all())


def test_the_command_line_says_it_refitted(tiny_scene, tmp_path, capsys):
    sets = ["optim.n_iters=20", "checkpoint_every=0", "tonemap.enabled=true", "tonemap.refit_steps=5"]
    main(["train", str(tiny_scene.source), "--out", str(tmp_path / "run"), "--preset", "fast", "--quiet",
          *[a for s in sets for a in ("--set", s)]])  # fmt: skip
    assert "response refitted with the field frozen" in capsys.readouterr().out
