"""What the MSI background adds to a render step on this machine (JOURNAL.md, "Background").

A 64^3 grid with half its voxels allocated and thin density (most rays reach the background), 27 SH
coefficients, 20 000 rays from a sphere of radius 3 aimed near the centre, and the default MSI
(`MSIBackground.create`: 32 layers of 64 x 128, 62 samples a ray). Times the foreground forward with the
constant and with a per-ray background, the foreground backward, and the MSI's forward and backward;
prints the median of 5 runs of each, in ms.
"""

from __future__ import annotations

import statistics
import time

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import background_kernel, march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.render import RenderOptions

RAYS = 20_000


def problem() -> tuple[SparseGrid, MSIBackground, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    grid = SparseGrid.create((64, 64, 64), basis_dim=9)
    grid.density = torch.rand(grid.num_voxels, generator=g) * 0.6 - 0.15
    grid.sh = torch.randn(grid.num_voxels, 27, generator=g) * 0.4
    grid = grid.prune(torch.rand(grid.num_voxels, generator=g) > 0.5)
    bg = MSIBackground.create(grid, layers=32, height=64, width=128)  # the measured problem
    bg.density = torch.rand(bg.density.shape, generator=g) * 0.3
    bg.color = torch.rand(bg.color.shape, generator=g) * 3.0
    o = torch.nn.functional.normalize(torch.randn(RAYS, 3, generator=g), dim=-1) * 3.0
    d = torch.nn.functional.normalize(-o + 0.4 * torch.randn(RAYS, 3, generator=g), dim=-1)
    return grid, bg, o, d


def median_ms(fn, reps: int = 5) -> float:
    fn()  # kernels loaded, buffers warm
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main() -> None:
    grid, bg, o, d = problem()
    opt = RenderOptions()
    grad = torch.randn(RAYS, 3, generator=torch.Generator().manual_seed(1))
    grads = GridGradients(grid, gradient_parts(grid))
    bg_grads = background_kernel.MSIGradients(bg, background_kernel.msi_gradient_parts(bg))
    rgb = march_kernel.render_forward(grid, o, d, opt)
    behind = background_kernel.msi_forward(bg, o, d, opt)
    t_fg = torch.empty(RAYS)
    rows = {
        "foreground forward, constant background": lambda: march_kernel.render_forward(grid, o, d, opt),
        "foreground forward, per-ray background": lambda: march_kernel.render_forward(
            grid, o, d, opt, behind=behind, transmittance=t_fg
        ),
        "foreground backward": lambda: march_kernel.accumulate_backward(grid, o, d, rgb, grad, opt, grads),
        "MSI forward": lambda: background_kernel.msi_forward(bg, o, d, opt),
        "MSI backward": lambda: background_kernel.msi_accumulate_backward(
            bg, o, d, behind, grad, opt, bg_grads
        ),
    }
    for name, fn in rows.items():
        print(f"{name:42s} {median_ms(fn):8.1f} ms")


if __name__ == "__main__":
    main()
