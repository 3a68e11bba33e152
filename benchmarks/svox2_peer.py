"""Plenoxels' own CUDA code (svox2) and this package's Warp kernels, timed on the same problem on one GPU.

svox2's extension is built here from its source with the machine's `nvcc` (torch's C++ extension loader,
which needs `ninja`); the benchmark's spike problem (a 128³ grid, 5 000 rays: `benchmarks/run.py`) is
handed to it as an svox2 grid with the same links, density and SH, and the two are timed in one process,
round-robin: a render, a training forward + backward (svox2's fused kernel, which computes the loss
gradient itself), and a step (that with the RMSProp of density and SH). Nothing is downloaded: the
source is a copy of svox2's repository brought to the machine (JOURNAL.md, "svox2 on the same
GPU"), and without CUDA the script says so and exits 0.

`--check` (any machine): the svox2 grid made from the problem renders what ours does, through svox2's
PyTorch path, so that both time the same scene.

Usage: python benchmarks/svox2_peer.py --source DIR [--rays 5000] [--repeats 7] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import types
from pathlib import Path
from statistics import median

from hdrplenoxels.core.process_settings import apply_process_settings, available_cores

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402
from run import load_code, round_robin, spike_problem, step_functions  # noqa: E402

# svox2's extension, as its setup.py lists it.
SOURCES = ("svox2.cpp", "svox2_kernel.cu", "render_lerp_kernel_cuvol.cu", "render_lerp_kernel_nvol.cu",
           "render_svox1_kernel.cu", "misc_kernel.cu", "loss_kernel.cu", "optim_kernel.cu")  # fmt: skip
LR_SIGMA, LR_SH = 1e-3, 1e-4  # the benchmark's small constant rates: every timed step does the same work


def build_extension(source: Path, build_dir: Path) -> types.ModuleType:
    """svox2's CUDA extension, compiled for this machine's GPU only (one architecture, every core: the
    build is a device call's minutes)."""
    from torch.utils.cpp_extension import load

    major, minor = torch.cuda.get_device_capability()
    os.environ.setdefault("TORCH_CUDA_ARCH_LIST", f"{major}.{minor}")
    os.environ.setdefault("MAX_JOBS", str(available_cores()))

    csrc = source / "svox2" / "csrc"
    return load(
        "svox2_csrc",
        [str(csrc / name) for name in SOURCES],
        extra_include_paths=[str(csrc / "include")],
        extra_cuda_cflags=["-O3"],
        build_directory=str(build_dir),
    )


def import_svox2(source: Path, extension: types.ModuleType | None):
    """svox2's Python package from `source`, its `svox2.csrc` being `extension` (None: its PyTorch
    fallback, which svox2 takes when the extension lacks its functions)."""
    sys.modules["svox2.csrc"] = extension if extension is not None else types.ModuleType("svox2.csrc")
    try:
        import scipy.spatial.transform  # noqa: F401
    except ImportError:  # svox2 imports scipy's Rotation at the top, for one camera utility we never call
        transform = types.ModuleType("scipy.spatial.transform")
        transform.Rotation = None
        for name in ("scipy", "scipy.spatial"):
            sys.modules[name] = types.ModuleType(name)
        sys.modules["scipy.spatial.transform"] = transform
    sys.path.insert(0, str(source))
    import svox2

    return svox2


def svox2_grid(svox2, grid, background: float):
    """Our one-box grid as an svox2 grid: the same box, links, density and SH (both keep a row's SH
    channel by channel), rendered with the same step and thresholds."""
    if grid.levels != 1:
        raise ValueError("svox2 has no cascade: a one-box grid only")
    reso = list(grid.reso)
    peer = svox2.SparseGrid(
        reso=reso, center=list(grid.center), radius=list(grid.radius), basis_dim=grid.basis_dim, device="cpu"
    )
    device = grid.density.device
    peer.links = grid.links[0].to(torch.int32).clone()
    peer.density_data = torch.nn.Parameter(grid.density.detach()[:, None].clone())
    peer.sh_data = torch.nn.Parameter(grid.sh.detach().clone())
    peer.capacity = grid.num_voxels
    peer = peer.to(device)
    peer.opt.step_size = 0.5
    peer.opt.sigma_thresh = 1e-8
    peer.opt.stop_thresh = 1e-7
    peer.opt.background_brightness = background
    peer.opt.backend = "cuvol"
    return peer


def svox2_functions(svox2, peer, o: torch.Tensor, d: torch.Tensor, target: torch.Tensor) -> dict:
    rays = svox2.Rays(o, d)

    def render():
        with torch.no_grad():
            peer.volume_render(rays, use_kernel=True)

    def train():
        peer.volume_render_fused(rays, target)

    def step():
        train()
        peer.optim_density_step(LR_SIGMA, beta=0.95, optim="rmsprop")
        peer.optim_sh_step(LR_SH, beta=0.95, optim="rmsprop")

    return {"render": render, "train": train, "step": step}


def timed(functions: dict[str, dict], repeats: int, n_rays: int) -> dict:
    """Rays per second of each function, the median of `repeats` rounds over all of them in turn."""
    flat = {f"{who}_{key}": fn for who, fns in functions.items() for key, fn in fns.items()}
    times = round_robin(flat, repeats, torch.cuda.synchronize)
    return {f"{name}_rays_per_s": n_rays / median(v) for name, v in times.items()}


def check(source: Path, rays: int) -> dict:
    """Our render and svox2's PyTorch render of the same grid, on the CPU (a small batch)."""
    from hdrplenoxels.render import RenderOptions, render_rays

    svox2 = import_svox2(source, None)
    grid, o, d, background = spike_problem(rays)
    peer = svox2_grid(svox2, grid, background)
    ours = render_rays(grid, o, d, RenderOptions(background_brightness=background), "torch")
    with torch.no_grad():
        theirs = peer.volume_render(svox2.Rays(o, d), use_kernel=False)
    return {"rays": rays, "max_abs_difference": float((ours - theirs).abs().max())}


def measure(source: Path, rays: int, repeats: int, build_dir: Path) -> dict:
    device = torch.device("cuda")
    t = time.perf_counter()
    extension = build_extension(source, build_dir)
    build_seconds = time.perf_counter() - t
    svox2 = import_svox2(source, extension)
    load_code("warp", device)
    grid, o, d, background = spike_problem(rays)
    grid, o, d = grid.to(device), o.to(device), d.to(device)
    target = torch.rand(rays, 3, generator=torch.Generator().manual_seed(0)).to(device)
    peer = svox2_grid(svox2, grid, background)
    functions = {
        "ours": step_functions(grid, o, d, background, "warp"),
        "svox2": svox2_functions(svox2, peer, o, d, target),
    }
    out = timed(functions, repeats, rays)
    for key in ("render", "train", "step"):
        out[f"{key}_ours_over_svox2"] = out[f"ours_{key}_rays_per_s"] / out[f"svox2_{key}_rays_per_s"]
    return {"gpu": torch.cuda.get_device_name(0), "rays": rays, "build_seconds": build_seconds, **out}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", type=Path, required=True, help="a copy of svox2's repository")
    ap.add_argument("--rays", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, help="also write the figures here (JSON)")
    ap.add_argument(
        "--build-dir", type=Path, help="where the extension is compiled (default: a temporary folder)"
    )
    ap.add_argument("--check", action="store_true", help="compare the two renders of the problem on the CPU")
    args = ap.parse_args()
    if not (args.source / "svox2" / "csrc" / SOURCES[0]).is_file():
        sys.exit(f"{args.source}: not a copy of svox2's repository (no svox2/csrc/{SOURCES[0]})")
    if args.check:
        result = check(args.source, min(args.rays, 256))
    elif not torch.cuda.is_available():
        print("svox2_peer: no CUDA device here; svox2's extension is CUDA only (--check runs on a CPU)")
        return 0
    else:
        with tempfile.TemporaryDirectory(prefix="svox2-build-") as tmp:
            result = measure(args.source, args.rays, args.repeats, args.build_dir or Path(tmp))
    print(json.dumps(result, indent=2))
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
