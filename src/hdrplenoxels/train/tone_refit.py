"""The response fitted once more after the last step, with the field frozen (docs/method.md, "Tone refit").

While training, the field and the tone share the light: the exposures, the curves and the field's scale
trade against one another, and a weighted loss (`ToneMapConfig.saturation_weighting`) fits the curve
loosely where the photos clip, which is where a camera's response bends most. Once the field is fixed
nothing is left to trade against, so a short fit of the curves alone to the field's own renders, on the
unweighted error, puts them where the photos say. The exposures and white balance stay as trained: on
the unweighted error a clipped pixel pulls its photo's exposure up, which is what the weighting is for.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.ray_pool import RayPool

Render = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""Linear radiance (N, 3) of rays (origins, dirs), without gradients."""

CHUNK = 1 << 15  # rays rendered at a time


@dataclass
class RefitPixels:
    """The pooled pixels the refit fits, with the frozen field's radiance along their rays."""

    radiance: torch.Tensor  # (N, 3)
    target: torch.Tensor  # (N, 3) in [0, 1]
    image_ids: torch.Tensor  # (N,)
    rows: torch.Tensor  # (N,)
    cols: torch.Tensor  # (N,)


def refit_pixels(pool: RayPool, render: Render, count: int, seed: int) -> RefitPixels:
    """Every pooled pixel where the pool holds no more than `count`, else `count` drawn uniformly (with
    replacement: a pool can hold a hundred million), and their radiance rendered once."""
    if len(pool) <= count:
        batches = pool.iter_all(chunk=CHUNK)
    else:
        generator = torch.Generator(pool.device).manual_seed(seed)
        batches = (pool.sample(min(CHUNK, count - start), generator) for start in range(0, count, CHUNK))
    parts = []
    for batch in batches:
        with torch.no_grad():
            radiance = render(batch.origins, batch.dirs).float()
        parts.append((radiance, batch.target, batch.image_ids, batch.rows, batch.cols))
    return RefitPixels(*(torch.cat(column) for column in zip(*parts, strict=True)))


def refit_tone(tm: ToneMapper, t: ToneMapConfig, pixels: RefitPixels) -> tuple[float, float]:
    """`t.refit_steps` full-batch Adam steps at `t.refit_lr` on the response curves (and the vignetting,
    where it is learned), the unweighted error with the curves' priors. Returns the loss before and
    after."""
    params = [p for p in (tm.crf_interior, tm.vignetting) if p.requires_grad]
    optimiser = torch.optim.Adam(params, lr=t.refit_lr)

    def loss() -> torch.Tensor:
        pred = tm(pixels.radiance, pixels.image_ids, pixels.rows, pixels.cols, training=True)
        return tm.loss(pred, pixels.target, weighted=False)

    with torch.no_grad():
        before = float(loss())
    for _ in range(t.refit_steps):  # gradients of the curves only: the gains' are not wanted
        for p, grad in zip(params, torch.autograd.grad(loss(), params), strict=True):
            p.grad = grad
        optimiser.step()
    with torch.no_grad():
        after = float(loss())
    for p in params:
        p.grad = None
    return before, after


def refit_after_training(tm: ToneMapper, t: ToneMapConfig, pool: RayPool, render: Render, seed: int) -> str:
    """The refit as a run's end does it (nothing where `t.refit_steps` is 0); the line saying what it did."""
    if t.refit_steps == 0:
        return ""
    pixels = refit_pixels(pool, render, t.refit_pixels, seed)
    before, after = refit_tone(tm, t, pixels)
    return (
        f"response refitted with the field frozen: loss {before:.5f} -> {after:.5f} over "
        f"{pixels.target.shape[0]} pixels, {t.refit_steps} steps"
    )
