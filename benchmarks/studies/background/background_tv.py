"""What the MSI's TV costs a training step, dense and sampled (JOURNAL.md, "The preset ladder").

On `balanced`'s MSI (16 layers of 128 x 256, random raw values): the reference, autograd through the
loss `msi_tv` over every texel (what training ran before the closed form), then the engine's own
regulariser (`GridEngine.regularise`, grid TV off so that only the MSI's runs) with TV over every texel
(the default, `background.tv_sparsity=1`) and once per sampled fraction. Prints the median of `--reps`
calls in ms and each one's ratio to the reference measured in the same run.

Usage: python benchmarks/studies/background/background_tv.py [--fractions 0.1 0.01] [--reps 20]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np
import torch
from background import median_ms

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.train.background_tv import msi_tv
from hdrplenoxels.train.engines.torch_grid import TorchGridEngine
from hdrplenoxels.train.presets import preset


def regulariser(fraction: float) -> tuple[TorchGridEngine, Callable[[], None]]:
    """An engine with `balanced`'s MSI and `background.tv_sparsity = fraction`, and its regularise()."""
    cfg = preset("balanced")
    cfg.background.tv_sparsity = fraction
    cfg.optim.lambda_tv_sigma = cfg.optim.lambda_tv_sh = 0.0
    cfg.grid.reso_schedule = [(8, 8, 8)]  # the grid plays no part: its TV is off
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), wants_background=True)
    cfg = cfg.resolved(background_brightness=0.5, wants_background=True, levels=1)
    field = TorchGridEngine.new_field(cfg, geometry, 1, torch.device("cpu"))
    background = TorchGridEngine.new_background(cfg, geometry, field)
    g = torch.Generator().manual_seed(0)
    background.density = torch.rand(background.density.shape, generator=g)
    background.color = torch.rand(background.color.shape, generator=g) * 3.0
    engine = TorchGridEngine(field, cfg, RenderOptions(), background)
    generator = torch.Generator().manual_seed(1)
    return engine, lambda: engine.regularise(generator)


def autograd_reference(engine: TorchGridEngine):
    """The dense TV's gradient through autograd, into the same buffers."""
    bg, grads = engine.background, engine.background_gradients()

    def run() -> None:
        density, color = bg.density.detach().requires_grad_(True), bg.color.detach().requires_grad_(True)
        leaves = MSIBackground(density, color, bg.center, bg.radius, bg.samples_per_layer)
        d_density, d_color = torch.autograd.grad(msi_tv(leaves, engine.bg_weights), [density, color])
        grads.density[0].add_(d_density)
        grads.color[0].add_(d_color)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.1, 0.01])
    parser.add_argument("--reps", type=int, default=20)
    args = parser.parse_args()
    engine, dense = regulariser(1.0)
    rows = {"autograd, every texel": autograd_reference(engine), "closed form, every texel": dense}
    for fraction in args.fractions:
        rows[f"closed form, {fraction:g} of the texels"] = regulariser(fraction)[1]
    reference = None
    for name, fn in rows.items():
        ms = median_ms(fn, args.reps)
        reference = reference or ms
        print(f"{name:36s} {ms:8.1f} ms  {ms / reference:.3f}")


if __name__ == "__main__":
    main()
