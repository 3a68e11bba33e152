"""Renderer throughput and memory: the Warp kernel against the PyTorch reference, on the same rays.

Each (problem, backend) pair runs in its own subprocess so that its peak RSS is its own. Problems:
  spike  the 128^3 problem of shared/design/backend-spike.md (Gaussian blob, 14.8 % occupied, rays from a
         sphere of radius 2.5 aimed at the centre with N(0, 0.15^2) jitter)
  demo   the built-in procedural scene's ground-truth grid (48^3, sparse) seen from its orbit cameras
Prints a table with Warp/reference ratios and writes JSON (train_rays_per_s, render_rays_per_s, peak_mb).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch

PROBLEMS = ("spike", "demo")
BACKENDS = ("warp", "torch")


def make_problem(name: str, n_rays: int):
    from hdrplenoxels.grid import SparseGrid

    g = torch.Generator().manual_seed(1234)
    if name == "spike":
        r = 128
        lin = torch.linspace(-1, 1, r)
        x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
        density = 20 * torch.exp(-(x**2 + y**2 + z**2) / 0.1)
        density[density < 0.25] = 0
        sh = torch.randn(r, r, r, 27, generator=g) * 0.1
        grid = SparseGrid.from_dense(density, sh, (0, 0, 0), (1, 1, 1))
        o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 2.5
        d = torch.nn.functional.normalize(-o + 0.15 * torch.randn(n_rays, 3, generator=g), dim=-1)
        return grid, o, d
    from hdrplenoxels.data.procedural import ProceduralSceneSpec, make_grid, orbit_cameras
    from hdrplenoxels.scene_setup import SceneGeometry

    spec = ProceduralSceneSpec()
    grid = make_grid(spec.grid_reso)
    cams = orbit_cameras(spec)
    geom = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), torch.eye(4).numpy())
    ids = torch.randint(0, len(cams), (n_rays,), generator=g)
    rows = torch.randint(0, spec.height, (n_rays,), generator=g)
    cols = torch.randint(0, spec.width, (n_rays,), generator=g)
    c2w = torch.as_tensor(cams.c2w, dtype=torch.float32)[ids]
    k = torch.as_tensor(cams.intrinsics, dtype=torch.float32)[ids]
    o, d = geom.rays(c2w, k, cols, rows)
    return grid, o, d


def worker(problem: str, backend: str, n_rays: int, repeats: int) -> dict:
    from hdrplenoxels.render import RenderOptions, render_rays

    grid, o, d = make_problem(problem, n_rays)
    opt = RenderOptions(background=0.0)
    grid.density.requires_grad_(True)
    grid.sh.requires_grad_(True)
    target = torch.rand(n_rays, 3, generator=torch.Generator().manual_seed(0))
    base_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def train_step():
        rgb = render_rays(grid, o, d, opt, backend)
        loss = ((rgb - target) ** 2).sum()
        return torch.autograd.grad(loss, [grid.density, grid.sh])

    def render_only():
        with torch.no_grad():
            return render_rays(grid, o, d, opt, backend)

    out = {}
    for key, fn in (("render", render_only), ("train", train_step)):
        fn()  # warm-up (kernel compile / cache load)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        out[f"{key}_rays_per_s"] = n_rays / sorted(times)[len(times) // 2]
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base_mb
    out["rays"] = n_rays
    out["voxels"] = grid.num_voxels
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default="bench.json", help="where to write the results")
    ap.add_argument("--rays", type=int, default=2000, help="rays per batch (same batch for both backends)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    ap.add_argument("--worker", nargs=2, metavar=("PROBLEM", "BACKEND"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(*args.worker, args.rays, args.repeats)))
        return
    results: dict[str, dict[str, dict]] = {}
    for problem in args.problems:
        results[problem] = {}
        for backend in BACKENDS:
            cmd = [sys.executable, __file__, "--worker", problem, backend]
            cmd += ["--rays", str(args.rays), "--repeats", str(args.repeats)]
            proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
            results[problem][backend] = json.loads(proc.stdout.strip().splitlines()[-1])
    device = "cuda" if torch.cuda.is_available() else f"cpu ({torch.get_num_threads()} threads)"
    print(f"device: {device}; {args.rays} rays per batch, median of {args.repeats}")
    print(f"{'problem':<8}{'backend':<8}{'train rays/s':>14}{'render rays/s':>15}{'peak MB':>10}")
    for problem, by_backend in results.items():
        for backend, r in by_backend.items():
            row = f"{r['train_rays_per_s']:>14.0f}{r['render_rays_per_s']:>15.0f}{r['peak_mb']:>10.0f}"
            print(f"{problem:<8}{backend:<8}{row}")
        w, t = by_backend["warp"], by_backend["torch"]
        train_ratio = w["train_rays_per_s"] / t["train_rays_per_s"]
        render_ratio = w["render_rays_per_s"] / t["render_rays_per_s"]
        print(f"{problem:<8}{'ratio':<8}{train_ratio:>13.1f}x{render_ratio:>14.1f}x")
    with open(args.json, "w") as f:
        json.dump({"device": device, "rays": args.rays, "results": results}, f, indent=2)


if __name__ == "__main__":
    main()
