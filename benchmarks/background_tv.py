"""What the MSI's TV costs a training step, dense and sampled (docs/performance.md, "The preset ladder").

The engine's own regulariser (`GridEngine.regularise`, grid TV off so that only the MSI's runs) on
`balanced`'s MSI (16 layers of 128 x 256, random raw values), once with TV over every texel (the
default, `background.tv_sparsity=1`) and once per sampled fraction. Prints the median of `--reps` calls
in ms and each one's ratio to the dense TV measured in the same run.

Usage: python benchmarks/background_tv.py [--fractions 0.1 0.01] [--reps 20]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from background import median_ms

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.train.config import preset
from hdrplenoxels.train.engines.torch_grid import TorchGridEngine


def regulariser(fraction: float):
    """The engine's regularise() on `balanced`'s MSI with `background.tv_sparsity = fraction`."""
    cfg = preset("balanced")
    cfg.background.tv_sparsity = fraction
    cfg.optim.lambda_tv_sigma = cfg.optim.lambda_tv_sh = 0.0
    cfg.grid.reso_schedule = [(8, 8, 8)]  # the grid plays no part: its TV is off
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), background=True)
    field = TorchGridEngine.new_field(cfg, geometry, 1, torch.device("cpu"))
    background = TorchGridEngine.new_background(cfg, geometry, field)
    g = torch.Generator().manual_seed(0)
    background.density = torch.rand(background.density.shape, generator=g)
    background.color = torch.rand(background.color.shape, generator=g) * 3.0
    engine = TorchGridEngine(field, cfg, RenderOptions(), background)
    generator = torch.Generator().manual_seed(1)
    return lambda: engine.regularise(generator, 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.1, 0.01])
    parser.add_argument("--reps", type=int, default=20)
    args = parser.parse_args()
    dense = median_ms(regulariser(1.0), args.reps)
    print(f"{'MSI TV, every texel':28s} {dense:8.1f} ms  1.00")
    for fraction in args.fractions:
        ms = median_ms(regulariser(fraction), args.reps)
        print(f"{f'MSI TV, {fraction:g} of the texels':28s} {ms:8.1f} ms  {ms / dense:.3f}")


if __name__ == "__main__":
    main()
