"""3D Gaussian Splatting (gsplat) on the same processed captures, split, resolution and scoring as ours.

For each dataset folder (a capture as `process` or `benchmarks/real_captures.py` left it, or one of its
static / varying re-shoots), gsplat trains on our training pool: every training view whole and the left
half of every test view (columns [0, W//2)), at our `--downscale`; it is then scored as ours is, on the
right halves of the test views (`eval.evaluate.scored_region`; PSNR, SSIM, and LPIPS where its weights
are installed), with the wall time and peak GPU memory of its training, and a contact sheet of the two
test views ours are shown with (photo | render | depth). It is written with gsplat's library API
(`rasterization`, `DefaultStrategy`) as its documentation describes them: Gaussians started at the
capture's sparse points (coloured from a training view that saw each), 3DGS's learning rates and loss
(0.8 L1 + 0.2 (1 - SSIM)), SH raised a degree every 1 000 steps, and, with `--appearance` (how people run
it on photos whose camera settings vary), a per-image colour correction learned with it: a gain and an
offset per channel, the test views' from their left halves, as our tone mapper's are.

gsplat is an optional extra (`pip install .[peers]`) and needs CUDA (its kernels build on first use with
the machine's `nvcc`); the package never imports it. Without CUDA the script says so and exits 0.
Protocol and results: docs/performance.md, "3D Gaussian Splatting on the same captures".

Usage: python benchmarks/peers.py DATA [DATA ...] --downscale 4 [--steps 30000] [--seconds S]
       [--appearance] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
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
SH_EVERY = 1000  # steps between raising the SH degree by one (3DGS)
SSIM_WEIGHT = 0.2  # the loss: (1 - w) L1 + w (1 - SSIM), 3DGS's


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
    """A per-image colour correction: rgb * exp(gain) + offset, per channel (zero: none)."""

    def __init__(self, n_images: int):
        super().__init__()
        self.gain = torch.nn.Parameter(torch.zeros(n_images, 3))
        self.offset = torch.nn.Parameter(torch.zeros(n_images, 3))

    def forward(self, rgb: torch.Tensor, image: int) -> torch.Tensor:
        return rgb * self.gain[image].exp() + self.offset[image]


def new_gaussians(points: np.ndarray, colours: np.ndarray, device) -> torch.nn.ParameterDict:
    """3DGS's start: a Gaussian per point, isotropic with the mean distance to its 3 nearest points,
    opacity 0.1, colour in the SH's DC term."""
    means = torch.as_tensor(points, dtype=torch.float32, device=device)
    near = []
    for chunk in means.split(4096):
        d = torch.cdist(chunk, means).topk(4, largest=False).values[:, 1:]
        near.append(d.mean(1))
    scale = torch.cat(near).clamp_min(1e-7)
    n = means.shape[0]
    sh0 = (torch.as_tensor(colours, dtype=torch.float32, device=device) - 0.5) / 0.28209479177387814
    return torch.nn.ParameterDict(
        {
            "means": means,
            "scales": scale.log()[:, None].repeat(1, 3),
            "quats": torch.nn.functional.normalize(torch.randn(n, 4, device=device), dim=-1),
            "opacities": torch.logit(torch.full((n,), 0.1, device=device)),
            "sh0": sh0[:, None, :],
            "shN": torch.zeros(n, (SH_DEGREE + 1) ** 2 - 1, 3, device=device),
        }
    )


def render(
    splats: torch.nn.ParameterDict, view: PeerView, sh_degree: int, depth: bool = False
) -> tuple[torch.Tensor, dict]:
    """The view's colours (H, W, 3) and gsplat's info; with `depth`, also its expected depth and opacity
    in the info (`"depth"`, `"opacity"`, (H, W) each)."""
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
    return out[0, ..., :3].clamp(0.0, 1.0), info


def train(
    views: list[PeerView], scene: SceneData, steps: int, seconds: float | None, appearance: bool
) -> dict:
    """gsplat trained on the views' pooled pixels, one view a step; the Gaussians, the appearance and
    the training's seconds and steps."""
    from gsplat import DefaultStrategy
    from pytorch_msssim import ssim

    device = views[0].image.device
    splats = new_gaussians(*initial_points(scene), device)
    extent = scene_scale(views)
    rates = {"means": 1.6e-4 * extent, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3,
             "shN": 2.5e-3 / 20}  # fmt: skip
    optimisers = {k: torch.optim.Adam([splats[k]], lr=lr, eps=1e-15) for k, lr in rates.items()}
    strategy = DefaultStrategy()
    strategy.check_sanity(splats, optimisers)
    state = strategy.initialize_state(scene_scale=extent)
    look = Appearance(len(scene.cameras)).to(device)
    look_optimiser = torch.optim.Adam(look.parameters(), lr=1e-3) if appearance else None
    decay = (0.01) ** (1.0 / max(steps, 1))  # means: 1.6e-4 -> 1.6e-6 over the schedule, as 3DGS
    order = torch.Generator().manual_seed(0)
    torch.cuda.synchronize()
    start = time.perf_counter()
    step = 0
    for step in range(steps):
        view = views[int(torch.randint(len(views), (1,), generator=order))]
        rgb, info = render(splats, view, min(step // SH_EVERY, SH_DEGREE))
        if appearance:
            rgb = look(rgb, view.index)
        strategy.step_pre_backward(splats, optimisers, state, step, info)
        pred = rgb[:, : view.pooled_width]
        truth = view.image[:, : view.pooled_width]
        l1 = (pred - truth).abs().mean()
        structure = ssim(pred.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], data_range=1.0)
        loss = (1 - SSIM_WEIGHT) * l1 + SSIM_WEIGHT * (1 - structure)
        loss.backward()
        strategy.step_post_backward(splats, optimisers, state, step, info, packed=False)
        for optimiser in [*optimisers.values(), *([look_optimiser] if appearance else [])]:
            optimiser.step()
            optimiser.zero_grad(set_to_none=True)
        for group in optimisers["means"].param_groups:
            group["lr"] *= decay
        if seconds is not None and step % 50 == 0:
            torch.cuda.synchronize()
            if time.perf_counter() - start >= seconds:
                break
    torch.cuda.synchronize()
    return {"splats": splats, "look": look, "seconds": time.perf_counter() - start, "steps": step + 1}


def trained_render(trained: dict, view: PeerView, appearance: bool, depth: bool = False) -> tuple:
    """`render` of the trained Gaussians at full SH, through the view's learned correction if any."""
    rgb, info = render(trained["splats"], view, SH_DEGREE, depth)
    if appearance:
        rgb = trained["look"](rgb, view.index).clamp(0.0, 1.0)
    return rgb, info


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, nargs="+", help="processed capture folders (or their re-shoots)")
    ap.add_argument("--downscale", type=int, default=1, help="as `train --downscale`")
    ap.add_argument("--steps", type=int, default=30_000, help="gsplat's schedule (3DGS's default)")
    ap.add_argument(
        "--seconds", type=float, help="stop when training has taken this long (our preset's time)"
    )
    ap.add_argument("--appearance", action="store_true", help="learn a per-image colour correction")
    ap.add_argument("--out", type=Path, help="where the JSON, markdown and contact sheets go")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("peers: no CUDA device here; gsplat's kernels are CUDA only")
        return 0
    results = {}
    for data in args.data:
        scene = load_scene(data, args.downscale)
        torch.cuda.reset_peak_memory_stats()
        views = peer_views(scene, "cuda")
        trained = train(views, scene, args.steps, args.seconds, args.appearance)
        results[str(data)] = score(scene, views, trained, args.appearance) | {
            "seconds": trained["seconds"],
            "steps": trained["steps"],
            "gaussians": int(trained["splats"]["means"].shape[0]),
            "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20,
        }
        print(data, json.dumps(results[str(data)]), flush=True)
        if args.out:
            sheet = args.out / f"{Path(data).resolve().parent.name}-{Path(data).name}.png"
            contact_sheet(scene, views, trained, args.appearance, sheet)
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
