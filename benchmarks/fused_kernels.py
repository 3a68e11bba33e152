"""The fused kernels that replace runs of small PyTorch operators on CUDA, each against the operators
(its oracle, what a CPU runs), timed in the same run on the same inputs: the tone mapper's loss and its
gradients (`tonemap/loss_kernel.py` against `loss_reference.py` with autograd's backward) and the ray
draw (`kernels/ray_draw_kernel.py` against `ray_draw_reference.py`). Each is timed launched from the host
and, on CUDA, replayed from a CUDA graph as a training step is (JOURNAL.md, "Fused kernels").
Prints milliseconds per call and the ratio.

Usage: python benchmarks/fused_kernels.py [--device cpu|cuda] [--rays 5000 100000] [--repeats 50]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from statistics import median

import numpy as np
import torch

from hdrplenoxels.kernels.ray_draw import PooledPixels
from hdrplenoxels.kernels.ray_draw_kernel import draw_rays
from hdrplenoxels.kernels.ray_draw_reference import draw_rays_reference
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.loss_kernel import fused_training_loss
from hdrplenoxels.tonemap.loss_reference import training_loss_reference
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.tonemap.pixels import PixelTargets

IMAGES, WIDTH, HEIGHT = 50, 1000, 750  # a real capture's photos at `--downscale 4`, one camera


def tone_loss_case(n_rays: int, device: torch.device) -> dict[str, Callable[[], None]]:
    """The loss and its gradients of `n_rays` rays over `IMAGES` views, each way."""
    g = torch.Generator().manual_seed(0)
    tm = ToneMapper(IMAGES, np.array([[WIDTH, HEIGHT]] * IMAGES), ToneMapConfig(enabled=True))
    with torch.no_grad():
        tm.log_wb.copy_(torch.randn(tm.log_wb.shape, generator=g) * 0.5)
    tm = tm.to(device)
    ids = torch.randint(0, IMAGES, (n_rays,), generator=g)
    rows, cols = (
        torch.randint(0, HEIGHT, (n_rays,), generator=g),
        torch.randint(0, WIDTH, (n_rays,), generator=g),
    )
    target = torch.rand(n_rays, 3, generator=g)
    rays = [torch.rand(n_rays, 3, generator=g), ids, rows, cols, target]
    radiance, *rest = (t.to(device) for t in rays)
    pixels = PixelTargets(*rest)
    radiance.requires_grad_(True)
    params = [p for p in tm.parameters() if p.requires_grad]

    def step(fn) -> Callable[[], None]:
        def run() -> None:
            loss, _ = fn(tm, radiance, pixels)
            torch.autograd.grad(loss, [radiance, *params])

        return run

    return {"torch": step(training_loss_reference), "kernel": step(fused_training_loss)}


def ray_draw_case(n_rays: int, device: torch.device) -> dict[str, Callable[[], None]]:
    """A batch of `n_rays` rays drawn from a pool of `IMAGES` photos (test views' left halves), each way."""
    g = torch.Generator().manual_seed(0)
    used = torch.tensor([WIDTH if i % 8 else WIDTH // 2 for i in range(IMAGES)])
    full = torch.full((IMAGES,), WIDTH)
    counts = used * HEIGHT
    starts = torch.cumsum(counts, 0) - counts
    offsets = torch.arange(IMAGES) * WIDTH * HEIGHT
    pixels = torch.randint(0, 256, (IMAGES * WIDTH * HEIGHT, 3), generator=g, dtype=torch.uint8)
    c2w = torch.eye(4).repeat(IMAGES, 1, 1)
    c2w[:, :3, 3] = torch.randn(IMAGES, 3, generator=g)
    intrinsics = torch.tensor([[800.0, 800.0, WIDTH / 2, HEIGHT / 2]]).repeat(IMAGES, 1)
    pool = PooledPixels(starts, used, full, torch.arange(IMAGES), offsets, pixels, c2w, intrinsics, None)
    pool = pool.to(device)
    flat = torch.randint(0, int(counts.sum()), (n_rays,), generator=g).to(device)
    return {
        "torch": lambda: draw_rays_reference(flat, pool),
        "kernel": lambda: draw_rays(flat, pool),
    }


CASES = {"tone_loss": tone_loss_case, "ray_draw": ray_draw_case}


def timer(device: torch.device, repeats: int) -> Callable[[Callable[[], None]], float]:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def seconds(fn: Callable[[], None]) -> float:
        for _ in range(3):  # compile, load, warm the allocator
            fn()
        times = []
        for _ in range(repeats):
            sync()
            t = time.perf_counter()
            fn()
            sync()
            times.append(time.perf_counter() - t)
        return median(times)

    return seconds


def graphed(fn: Callable[[], None], device: torch.device) -> Callable[[], None]:
    """`fn` recorded once in a CUDA graph (Warp's launches with torch's), returned as its replay."""
    import warp as wp

    from hdrplenoxels.core.warp_runtime import torch_stream

    side = torch.cuda.Stream(device=device)
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    mode = wp.CaptureMode.GLOBAL  # torch's mode for the capture it opens
    with torch.cuda.graph(graph, stream=side):  # noqa: SIM117 -- torch_stream() is the side stream only in here
        with wp.ScopedCapture(stream=torch_stream(), external=True, capture_mode=mode):
            fn()
    return graph.replay


def fused_kernel_times(
    device: str = "cpu", rays: tuple[int, ...] = (5000, 100000), repeats: int = 50
) -> dict:
    """Milliseconds per call of each case, each way, at each batch size: `{case}_{way}_{rays}[_graph]_ms`,
    launched and (on CUDA) from a graph, and `{case}_ratio_{rays}[_graph]`, the operators' time over the
    kernel's."""
    dev = torch.device(device)
    seconds = timer(dev, repeats)
    out: dict = {"device": device, "images": IMAGES}
    for case, make in CASES.items():
        for n in rays:
            ways = make(n, dev)
            for way, fn in ways.items():
                out[f"{case}_{way}_{n}_ms"] = 1e3 * seconds(fn)
                if dev.type == "cuda":
                    out[f"{case}_{way}_{n}_graph_ms"] = 1e3 * seconds(graphed(fn, dev))
            for run in ("", "_graph"):
                if f"{case}_kernel_{n}{run}_ms" in out:
                    out[f"{case}_ratio_{n}{run}"] = (
                        out[f"{case}_torch_{n}{run}_ms"] / out[f"{case}_kernel_{n}{run}_ms"]
                    )
    return out


def summary(out: dict, rays: tuple[int, ...]) -> list[str]:
    """One line per case and batch: torch / kernel ms, launched and from a graph."""
    lines = []
    for case in CASES:
        for n in rays:
            for run, label in (("", "launched"), ("_graph", "from a CUDA graph")):
                if f"{case}_kernel_{n}{run}_ms" in out:
                    lines.append(
                        f"{case}, {n} rays, {label}: torch {out[f'{case}_torch_{n}{run}_ms']:.3f} ms, kernel "
                        f"{out[f'{case}_kernel_{n}{run}_ms']:.3f} ms ({out[f'{case}_ratio_{n}{run}']:.1f}x)"
                    )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rays", type=int, nargs="+", default=[5000, 100000])
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    out = fused_kernel_times(args.device, tuple(args.rays), args.repeats)
    print("\n".join(summary(out, tuple(args.rays))))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
