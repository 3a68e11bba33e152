"""3D Gaussian Splatting (gsplat) on the same processed captures, split, resolution and scoring as ours.

For each dataset folder (a capture as `process` or `benchmarks/real_captures.py` left it, or one of its
static / varying re-shoots), gsplat trains on our training pool: every training view whole and the left
half of every test view (columns [0, W//2)), at our `--downscale`; it is then scored as ours is, on the
right halves of the test views (`eval.evaluate.scored_region`; PSNR, SSIM, and LPIPS where its weights
are installed), with the wall time and peak GPU memory of its training, and a contact sheet of the two
test views ours are shown with (photo | render | depth). It is written with gsplat's library API
(`rasterization`, `DefaultStrategy`) as its documentation and its own trainer use them: Gaussians started
at the capture's sparse points (coloured from a training view that saw each), 3DGS's learning rates and
loss (0.8 L1 + 0.2 (1 - SSIM)), SH raised a degree every 1 000 steps, colours clamped only when scored,
the strategy's refinement after each update, and `--steps-scaler` shortening the whole schedule as
gsplat's trainer's `steps_scaler` does. With `--appearance` (how people run 3DGS on photos whose camera
settings vary) it learns 3DGS's exposure compensation with it: a 3 x 4 affine colour matrix per image,
the test views' from their left halves, as our tone mapper's are, its output clamped in training as 3DGS
clamps it.

gsplat is an optional extra (`pip install .[peers]`) and needs CUDA (its kernels build on first use with
the machine's `nvcc`); the package never imports it. Without CUDA the script says so and exits 0.
Protocol and results: JOURNAL.md, "3D Gaussian Splatting on the same captures".

Usage: python benchmarks/peers.py DATA [DATA ...] --downscale 4 [--steps-scaler F] [--seconds S]
       [--appearance] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402

from hdrplenoxels.data import load_scene  # noqa: E402
from hdrplenoxels.data.protocol import left_width  # noqa: E402
from hdrplenoxels.data.scene import SceneData  # noqa: E402
from hdrplenoxels.eval.evaluate import PROTOCOLS, scored_region  # noqa: E402
from hdrplenoxels.eval.metrics import image_metrics, lpips_available  # noqa: E402
from hdrplenoxels.viewer.display import geometry_image  # noqa: E402

SH_DEGREE = 3
SSIM_WEIGHT = 0.2  # the loss: (1 - w) L1 + w (1 - SSIM), 3DGS's
# 3DGS's exposure compensation as its repository's scripts run it with `--train_test_exp` (photos whose
# exposure varies): Adam from 1e-3 to 1e-4, ramped up from near 0 over its first 5 000 steps (of 30 000).
EXPOSURE_RATES = (1e-3, 1e-4)
EXPOSURE_DELAY_MULT = 1e-3


@dataclass(frozen=True)
class Schedule:
    """The step counts of a gsplat run: 3DGS's defaults (which gsplat 1.5.3's trainer and its
    `DefaultStrategy` keep), all scaled by `scaler` as that trainer's `steps_scaler` scales them, so that
    a shorter run is the same schedule compressed rather than the default one cut off."""

    scaler: float = 1.0

    def _scaled(self, steps: int) -> int:
        return int(steps * self.scaler)

    @property
    def steps(self) -> int:
        return self._scaled(30_000)

    @property
    def sh_every(self) -> int:
        """Steps between raising the SH degree by one."""
        return max(1, self._scaled(1_000))

    @property
    def exposure_delay(self) -> int:
        return self._scaled(5_000)

    def strategy(self) -> dict[str, int]:
        """`DefaultStrategy`'s step settings (its other settings stay gsplat's defaults)."""
        return {
            "refine_start_iter": self._scaled(500),
            "refine_stop_iter": self._scaled(15_000),
            "reset_every": max(1, self._scaled(3_000)),
            "refine_every": max(1, self._scaled(100)),
        }

    def exposure_rate(self, step: int) -> float:
        """3DGS's delayed exponential rate for the exposure matrices at `step`: log-linear from the first
        rate to the last over the run, scaled by a sine ramp from EXPOSURE_DELAY_MULT to 1 over the
        delay. Written here because it is a few lines of 3DGS's trainer, not a library's API."""
        first, last = EXPOSURE_RATES
        t = min(max(step / max(self.steps, 1), 0.0), 1.0)
        rate = math.exp((1 - t) * math.log(first) + t * math.log(last))
        if self.exposure_delay > 0:
            ramp = math.sin(0.5 * math.pi * min(max(step / self.exposure_delay, 0.0), 1.0))
            rate *= EXPOSURE_DELAY_MULT + (1 - EXPOSURE_DELAY_MULT) * ramp
        return rate


@dataclass
class PeerView:
    """A view of the training pool as gsplat takes it: the photo, OpenCV world-to-camera and intrinsics
    matrices, and how many columns from the left are in the pool (all of a training view, the left half
    of a test view)."""

    index: int
    image: torch.Tensor  # (H, W, 3) in [0, 1]
    viewmat: torch.Tensor  # (4, 4)
    K: torch.Tensor  # (3, 3)
    pooled_width: int

    @property
    def size(self) -> tuple[int, int]:
        return self.image.shape[1], self.image.shape[0]


def peer_views(scene: SceneData, device: torch.device | str = "cpu") -> list[PeerView]:
    """Our training pool, view by view (`RayPool`'s, with the right-half protocol). Pixel (u, v)'s centre
    is (u + 0.5, v + 0.5) for gsplat as for our rays, so the intrinsics carry over unchanged."""
    views = []
    for i in sorted(scene.train_ids + scene.test_ids):
        fx, fy, cx, cy = scene.cameras.intrinsics[i]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        viewmat = np.linalg.inv(scene.cameras.c2w[i])
        w, _ = scene.cameras.size(i)
        image = torch.tensor(np.asarray(scene.images[i]), dtype=torch.float32) / 255.0  # a copy
        views.append(
            PeerView(
                i,
                image.to(device),
                torch.as_tensor(viewmat, dtype=torch.float32, device=device),
                torch.as_tensor(K, dtype=torch.float32, device=device),
                w if i in scene.train_ids else left_width(w),
            )
        )
    return views


def initial_points(scene: SceneData) -> tuple[np.ndarray, np.ndarray]:
    """The capture's sparse points seen by a training view, (P, 3), each with the colour (P, 3) in [0, 1]
    of the pixel it falls on in the first training view that saw it."""
    if scene.sight_lines is None:
        raise SystemExit(f"{scene.source}: no sparse points to start Gaussians from (process writes them)")
    lines = scene.sight_lines.of_views(scene.train_ids)
    first = {}
    for view, point in zip(lines.view.tolist(), lines.point.tolist()):
        first.setdefault(point, view)
    ids = np.array(sorted(first), dtype=np.int64)
    seen_by = np.array([first[p] for p in ids.tolist()], dtype=np.int64)
    points = scene.sight_lines.points[ids]
    colours = np.zeros_like(points)
    for view in np.unique(seen_by).tolist():
        mine = np.flatnonzero(seen_by == view)
        w2c = np.linalg.inv(scene.cameras.c2w[view])
        cam = points[mine] @ w2c[:3, :3].T + w2c[:3, 3]
        fx, fy, cx, cy = scene.cameras.intrinsics[view]
        w, h = scene.cameras.size(view)
        u = np.clip(np.floor(fx * cam[:, 0] / cam[:, 2] + cx), 0, w - 1).astype(int)
        v = np.clip(np.floor(fy * cam[:, 1] / cam[:, 2] + cy), 0, h - 1).astype(int)
        colours[mine] = np.asarray(scene.images[view])[v, u] / 255.0
    return points, colours


def scene_scale(views: list[PeerView]) -> float:
    """3DGS's scene extent: 1.1 times the largest distance of a camera from the cameras' centre."""
    centres = torch.stack([torch.linalg.inv(v.viewmat)[:3, 3] for v in views])
    return 1.1 * float((centres - centres.mean(0)).norm(dim=-1).max())


class Appearance(torch.nn.Module):
    """3DGS's exposure compensation: a 3 x 4 affine colour matrix per image, applied to the rendered
    colours before any clamp, started at the identity (no correction)."""

    def __init__(self, n_images: int):
        super().__init__()
        self.matrix = torch.nn.Parameter(torch.eye(3, 4).repeat(n_images, 1, 1))

    def forward(self, rgb: torch.Tensor, image: int) -> torch.Tensor:
        m = self.matrix[image]
        return rgb @ m[:, :3].T + m[:, 3]


def new_gaussians(points: np.ndarray, colours: np.ndarray, device) -> torch.nn.ParameterDict:
    """gsplat's trainer's start: a Gaussian per point, isotropic with the root mean square distance to its
    3 nearest points, opacity 0.1, a random rotation, colour in the SH's DC term."""
    means = torch.as_tensor(points, dtype=torch.float32, device=device)
    near = []
    for chunk in means.split(4096):
        d = torch.cdist(chunk, means).topk(4, largest=False).values[:, 1:]
        near.append(d.square().mean(1).sqrt())
    scale = torch.cat(near).clamp_min(1e-7)
    n = means.shape[0]
    rotations = torch.rand(n, 4, generator=torch.Generator().manual_seed(0)).to(device)
    sh0 = (torch.as_tensor(colours, dtype=torch.float32, device=device) - 0.5) / 0.28209479177387814
    return torch.nn.ParameterDict(
        {
            "means": means,
            "scales": scale.log()[:, None].repeat(1, 3),
            "quats": rotations,  # rasterization normalises them
            "opacities": torch.logit(torch.full((n,), 0.1, device=device)),
            "sh0": sh0[:, None, :],
            "shN": torch.zeros(n, (SH_DEGREE + 1) ** 2 - 1, 3, device=device),
        }
    )


def render(
    splats: torch.nn.ParameterDict, view: PeerView, sh_degree: int, depth: bool = False
) -> tuple[torch.Tensor, dict]:
    """The view's colours (H, W, 3), not clamped (gsplat's trainer clamps only what it scores), and
    gsplat's info; with `depth`, also its expected depth and opacity in the info (`"depth"`, `"opacity"`,
    (H, W) each)."""
    from gsplat import rasterization

    w, h = view.size
    colors = torch.cat([splats["sh0"], splats["shN"]], 1)
    out, alpha, info = rasterization(
        splats["means"],
        splats["quats"],
        splats["scales"].exp(),
        splats["opacities"].sigmoid(),
        colors,
        view.viewmat[None],
        view.K[None],
        w,
        h,
        sh_degree=sh_degree,
        packed=False,
        render_mode="RGB+ED" if depth else "RGB",
    )
    if depth:
        info = info | {"depth": out[0, ..., 3], "opacity": alpha[0, ..., 0]}
    return out[0, ..., :3], info


def view_order(n_views: int, steps: int, seed: int = 0) -> list[int]:
    """The views of each step: every view once per pass in a new random order, as gsplat's trainer
    draws them (a shuffled data loader, one image a step)."""
    generator, order = torch.Generator().manual_seed(seed), []
    while len(order) < steps:
        order += torch.randperm(n_views, generator=generator).tolist()
    return order[:steps]


def train(
    views: list[PeerView], scene: SceneData, schedule: Schedule, seconds: float | None, appearance: bool
) -> dict:
    """gsplat trained on the views' pooled pixels, one view a step; the Gaussians, the appearance and
    the training's seconds and steps. gsplat's kernels are built (on first use) and its first calls made
    before the clock starts, so the seconds are training's alone."""
    from gsplat import DefaultStrategy
    from pytorch_msssim import ssim

    device = views[0].image.device
    splats = new_gaussians(*initial_points(scene), device)
    extent = scene_scale(views)
    rates = {"means": 1.6e-4 * extent, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3,
             "shN": 2.5e-3 / 20}  # fmt: skip
    optimisers = {k: torch.optim.Adam([splats[k]], lr=lr, eps=1e-15) for k, lr in rates.items()}
    strategy = DefaultStrategy(**schedule.strategy())
    strategy.check_sanity(splats, optimisers)
    state = strategy.initialize_state(scene_scale=extent)
    look = Appearance(len(scene.cameras)).to(device)
    look_optimiser = torch.optim.Adam(look.parameters(), lr=schedule.exposure_rate(0)) if appearance else None
    steps = schedule.steps
    decay = (0.01) ** (1.0 / max(steps, 1))  # means: 1.6e-4 -> 1.6e-6 over the schedule, as 3DGS
    rgb, _ = render(splats, views[0], SH_DEGREE)  # gsplat's kernels built and loaded: not training time
    rgb.sum().backward()
    for optimiser in optimisers.values():
        optimiser.zero_grad(set_to_none=True)
    order = view_order(len(views), steps)
    torch.cuda.synchronize()
    start = time.perf_counter()
    step = 0
    for step in range(steps):
        view = views[order[step]]
        rgb, info = render(splats, view, min(step // schedule.sh_every, SH_DEGREE))
        if appearance:  # 3DGS clamps the exposure-compensated render, in training too
            rgb = look(rgb, view.index).clamp(0.0, 1.0)
        strategy.step_pre_backward(splats, optimisers, state, step, info)
        pred = rgb[:, : view.pooled_width]
        truth = view.image[:, : view.pooled_width]
        l1 = (pred - truth).abs().mean()
        structure = ssim(pred.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0)
        loss = (1 - SSIM_WEIGHT) * l1 + SSIM_WEIGHT * (1 - structure)
        loss.backward()
        if appearance:  # 3DGS counts its steps from 1
            for group in look_optimiser.param_groups:
                group["lr"] = schedule.exposure_rate(step + 1)
        for optimiser in [*optimisers.values(), *([look_optimiser] if appearance else [])]:
            optimiser.step()
            optimiser.zero_grad(set_to_none=True)
        for group in optimisers["means"].param_groups:
            group["lr"] *= decay
        # After the update, as gsplat's trainer: a refinement replaces the parameters (their gradients
        # gone), so before it the step's update of every Gaussian would be lost.
        strategy.step_post_backward(splats, optimisers, state, step, info, packed=False)
        if seconds is not None and step % 50 == 0:
            torch.cuda.synchronize()
            if time.perf_counter() - start >= seconds:
                break
    torch.cuda.synchronize()
    return {"splats": splats, "look": look, "seconds": time.perf_counter() - start, "steps": step + 1}


def trained_render(trained: dict, view: PeerView, appearance: bool, depth: bool = False) -> tuple:
    """`render` of the trained Gaussians at full SH, through the view's learned correction if any, clamped
    to [0, 1] as gsplat's trainer clamps what it scores."""
    rgb, info = render(trained["splats"], view, SH_DEGREE, depth)
    if appearance:
        rgb = trained["look"](rgb, view.index)
    return rgb.clamp(0.0, 1.0), info


@torch.no_grad()
def score(scene: SceneData, views: list[PeerView], trained: dict, appearance: bool) -> dict:
    """Right halves of the test views, each rendered with its view's correction (from its left half)."""
    metrics = []
    nets = ("vgg",) if lpips_available("vgg") else ()
    for view in (v for v in views if v.index in scene.test_ids):
        rgb, _ = trained_render(trained, view, appearance)
        metrics.append(
            image_metrics(scored_region(rgb, "right-half"), scored_region(view.image, "right-half"), nets)
        )
    return {key: float(np.mean([m[key] for m in metrics])) for key in metrics[0]} | {
        "test_views": len(metrics)
    }


@torch.no_grad()
def contact_sheet(
    scene: SceneData, views: list[PeerView], trained: dict, appearance: bool, path: Path
) -> None:
    """The two test views `benchmarks/real_captures.py`'s sheets show, each a row: photo | render | depth
    (turbo, near blue), for looking at floaters, fog and smears beside ours."""
    rows = []
    by_index = {v.index: v for v in views}
    for i in scene.test_ids[:: max(1, len(scene.test_ids) // 2)][:2]:
        view = by_index[i]
        rgb, info = trained_render(trained, view, appearance, depth=True)
        rows.append(sheet_row(scene.images[i], rgb.cpu(), info["depth"].cpu(), info["opacity"].cpu()))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)


def sheet_row(photo: np.ndarray, rgb: torch.Tensor, depth: torch.Tensor, opacity: torch.Tensor) -> np.ndarray:
    """photo | render | depth, as uint8 (H, 3W, 3)."""
    render_u8 = (rgb.numpy() * 255.0 + 0.5).astype(np.uint8)
    return np.concatenate([np.asarray(photo), render_u8, geometry_image(depth, opacity, "depth")], axis=1)


def run(
    data: Path,
    downscale: int,
    schedule: Schedule,
    seconds: float | None,
    appearance: bool,
    sheet: Path | None,
) -> dict:
    """gsplat trained on the dataset `data` at `downscale` and scored, on CUDA: its metrics, seconds,
    steps, Gaussians and peak GPU memory; its contact sheet written to `sheet` if given."""
    scene = load_scene(data, downscale)
    torch.cuda.reset_peak_memory_stats()
    views = peer_views(scene, "cuda")
    trained = train(views, scene, schedule, seconds, appearance)
    result = score(scene, views, trained, appearance) | {
        "seconds": trained["seconds"],
        "steps": trained["steps"],
        "gaussians": int(trained["splats"]["means"].shape[0]),
        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20,
    }
    if sheet is not None:
        contact_sheet(scene, views, trained, appearance, sheet)
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, nargs="+", help="processed capture folders (or their re-shoots)")
    ap.add_argument("--downscale", type=int, default=1, help="as `train --downscale`")
    ap.add_argument(
        "--steps-scaler",
        type=float,
        default=1.0,
        help="scale gsplat's whole schedule (30 000 steps at 1), as its trainer's steps_scaler does",
    )
    ap.add_argument("--seconds", type=float, help="stop when training has taken this long, if sooner")
    ap.add_argument("--appearance", action="store_true", help="learn a per-image colour correction")
    ap.add_argument("--out", type=Path, help="where the JSON, markdown and contact sheets go")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("peers: no CUDA device here; gsplat's kernels are CUDA only")
        return 0
    results = {}
    for data in args.data:
        sheet = args.out / f"{Path(data).resolve().parent.name}-{Path(data).name}.png" if args.out else None
        schedule = Schedule(args.steps_scaler)
        results[str(data)] = run(data, args.downscale, schedule, args.seconds, args.appearance, sheet)
        print(data, json.dumps(results[str(data)]), flush=True)
    report = {
        "method": "gsplat" + (" with per-image appearance" if args.appearance else ""),
        "protocol": PROTOCOLS["right-half"],
        "gpu": torch.cuda.get_device_name(0),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "data"},
        "results": results,
    }
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "peers.json").write_text(json.dumps(report, indent=2))
        (args.out / "peers.md").write_text(markdown(report))
    return 0


def markdown(report: dict) -> str:
    """The report as a table: a row per dataset."""
    lines = [f"{report['method']} on {report['gpu']}. Protocol: {report['protocol']}.", ""]
    lines += ["| data | PSNR | SSIM | LPIPS (vgg) | seconds | steps | Gaussians | peak GPU MB |"]
    lines += ["|---|---|---|---|---|---|---|---|"]
    for data, r in report["results"].items():
        lpips = f"{r['lpips_vgg']:.3f}" if "lpips_vgg" in r else "–"
        lines.append(
            f"| {data} | {r['psnr']:.2f} | {r['ssim']:.3f} | {lpips} | {r['seconds']:.0f} | {r['steps']} | "
            f"{r['gaussians']:,} | {r['peak_gpu_mb']:.0f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
