"""MSI or contracted grid behind the box? The measurement the choice rests on (JOURNAL.md,
"Background: MSI or contracted grid").

Trains ours (the tone mapper, `balanced` by default) on a synthetic scene's validation capture twice, in
one loop that differs only in the background model behind the grid's box:

- `msi`: the shipped multi-sphere background (Warp kernels, `grid/background.py`);
- `contracted`: a prototype of mip-NeRF 360's contraction, written here in PyTorch only. Box-normalised
  points x (the box is [-1, 1]^3) map to x when |x|_inf <= 1, else to (2 - 1/|x|_inf) x / |x|_inf, so
  the box keeps its place and everything beyond it fills the shell out to [-2, 2]^3. One dense grid of
  `--contracted-size`^3 cells over [-2, 2]^3 holds raw density and linear RGB, trilinear and ReLU'd as
  the MSI's. A ray takes `--contracted-samples` samples from where it leaves the box (or its origin,
  when it misses the box) to infinity at t = t_start + r0 (1 / (1 - u) - 1), u uniform in (0, 1), so
  that they are near-uniform in the contracted coordinate; each adds optical depth sigma x (L - 1) /
  samples, so that a ray's total optical length is the MSI's (its spl (L - 1) samples add sigma / spl
  each). Its TV and sparsity are the MSI's (forward differences over the three axes, mean over the
  shell's cells: the ones inside the box are sampled by nothing), with the same weights, learning rates
  and RMSProp.

The default size matches the MSI's texel count (`balanced`: 16 x 128 x 256 = 524 288, and 84^3 x 7/8
shell cells), with two samples per cell of the shell's thickness. The
prototype is not a shipped component: it has no Warp kernel, so its wall time is printed but not
compared. Scores are PSNR / SSIM on the validation views' right halves (their left halves train their
tone parameters); every model is the final step of its schedule. Validation captures only: the choice
is never made on test views.

Example: python benchmarks/studies/background/background_choice.py --scene courtyard
         --out /tmp/background_choice
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from hdrplenoxels.experiments.common import ExperimentSettings, config_for, scores, validation_root
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.march_reference import composite_weights
from hdrplenoxels.kernels.options import RenderOptions
from hdrplenoxels.render.autograd import render_warp
from hdrplenoxels.synth.scenes import SCENES
from hdrplenoxels.train.engines.warp_grid import WarpGridEngine
from hdrplenoxels.train.runs import RunSpec
from hdrplenoxels.train.trainer import Trainer

TV_EPS = 1e-9


@dataclass
class ContractedGrid:
    """Raw density (G, G, G) and colour (G, G, G, 3) over contracted [-2, 2]^3, indexed [z, y, x]."""

    density: torch.Tensor
    color: torch.Tensor
    center: torch.Tensor  # (3,) world: the box's centre
    half: torch.Tensor  # (3,) world: the box's half extents
    r0: float  # world: half the box diagonal, the scale of the sample spacing
    samples: int
    depth_per_sample: float  # optical depth of a sample is sigma times this

    @property
    def device(self) -> torch.device:
        return self.density.device

    @classmethod
    def create(
        cls, grid: SparseGrid, size: int, samples: int, optical_length: float, density: float, color: float
    ):
        device = grid.device
        half = torch.tensor([float(r) for r in grid.radius], device=device)
        return cls(
            density=torch.full((size, size, size), float(density), device=device),
            color=torch.full((size, size, size, 3), float(color), device=device),
            center=torch.tensor([float(c) for c in grid.center], device=device),
            half=half,
            r0=float(half.norm()),
            samples=samples,
            depth_per_sample=optical_length / samples,
        )


def contracted_radiance(
    bg: ContractedGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions,
    density: torch.Tensor | None = None,
    color: torch.Tensor | None = None,
) -> torch.Tensor:
    """Radiance (N, 3) behind the box along world rays (unit directions); autograd-able w.r.t. `density`
    and `color` (default: the grid's own)."""
    density = bg.density if density is None else density
    color = bg.color if color is None else color
    x = (origins - bg.center) / bg.half
    v = dirs / bg.half
    inv = 1.0 / torch.where(v.abs() > 1e-9, v, torch.full_like(v, 1e-9))
    t1, t2 = (-1.0 - x) * inv, (1.0 - x) * inv
    t_near = torch.minimum(t1, t2).amax(-1)
    t_far = torch.maximum(t1, t2).amin(-1)
    hits = (t_near <= t_far) & (t_far > 0.0)
    t_start = torch.where(hits, t_far, torch.zeros_like(t_far)).clamp(min=0.0)
    k = torch.arange(bg.samples, device=origins.device, dtype=origins.dtype)
    u = (k + 0.5) / bg.samples
    t = t_start[:, None] + bg.r0 * (1.0 / (1.0 - u) - 1.0)[None, :]
    p = x[:, None, :] + t[..., None] * v[:, None, :]
    n = p.abs().amax(-1, keepdim=True).clamp(min=1e-6)
    q = torch.where(n > 1.0, (2.0 - 1.0 / n) * p / n, p) / 2.0  # in [-1, 1] for grid_sample
    values = torch.cat([density[None], color.permute(3, 0, 1, 2)])[None]  # (1, 4, G, G, G)
    out = F.grid_sample(values, q[None, :, :, None, :], mode="bilinear", align_corners=True)
    out = out[0, :, :, :, 0]  # (4, N, K)
    sigma = torch.relu(out[0])
    rgb = torch.relu(out[1:]).permute(1, 2, 0)  # (N, K, 3)
    delta = torch.full_like(sigma, bg.depth_per_sample)
    weights, t_end = composite_weights(sigma, torch.ones_like(sigma, dtype=torch.bool), delta, opt)
    return (weights[..., None] * rgb).sum(1) + (t_end * opt.background_brightness)[:, None]


def _shell(size: int, device: torch.device) -> torch.Tensor:
    """(G, G, G) bool: the cells whose centre lies beyond the box (|c|_inf >= 1 in contracted units)."""
    centre = torch.linspace(-2.0, 2.0, size, device=device).abs()
    return (
        torch.maximum(torch.maximum(centre[:, None, None], centre[None, :, None]), centre[None, None, :])
        >= 1.0
    )


def _tv(values: torch.Tensor, shell: torch.Tensor) -> torch.Tensor:
    """`values` (G, G, G, C): mean over the `shell`'s cells of sqrt(sum of squared forward differences),
    summed over channels."""
    diffs = []
    for axis in range(3):
        d = torch.zeros_like(values)
        n = values.shape[axis]
        d.narrow(axis, 0, n - 1).copy_(values.narrow(axis, 1, n - 1) - values.narrow(axis, 0, n - 1))
        diffs.append(d**2)
    return torch.sqrt(sum(diffs) + TV_EPS)[shell].mean(0).sum()


def contracted_engine(size: int, samples: int) -> type:
    """The Warp grid engine with the contracted grid behind its box in place of the MSI."""

    class ContractedGridEngine(WarpGridEngine):
        @staticmethod
        def new_background(cfg, geometry, field):
            if not cfg.background.enabled:
                return None
            b = cfg.background
            return ContractedGrid.create(field, size, samples, b.layers - 1, b.init_sigma, b.init_color)

        def _background_parts(self) -> int:
            return 1

        def _background_forward(self, batch):
            bg = self.background
            leaves = (bg.density.detach().requires_grad_(True), bg.color.detach().requires_grad_(True))
            behind = contracted_radiance(bg, batch.origins, batch.dirs, self.render_opt, *leaves)
            self._graph = (behind, leaves)  # for its backward
            return behind.detach()

        def _background_backward(self, batch, behind, grad_behind):
            graph, leaves = self._graph
            d_density, d_color = torch.autograd.grad(graph, list(leaves), grad_behind)
            grads = self.background_gradients()
            grads.density[0].add_(d_density)
            grads.color[0].add_(d_color)

        def _regularise_background(self, generator):
            bg, w = self.background, self.bg_weights
            density = bg.density.detach().requires_grad_(True)
            color = bg.color.detach().requires_grad_(True)
            shell = _shell(density.shape[0], density.device)
            loss = w.lambda_tv_sigma * _tv(density[..., None], shell)
            loss = loss + w.lambda_tv_color * _tv(color, shell)
            loss = loss + w.lambda_sparsity * torch.log1p(2.0 * density[shell] ** 2).mean()
            d_density, d_color = torch.autograd.grad(loss, [density, color])
            grads = self.background_gradients()
            grads.density[0].add_(d_density)
            grads.color[0].add_(d_color)

        @torch.no_grad()
        def render(self, origins, dirs):
            behind = contracted_radiance(self.background, origins, dirs, self.render_opt)
            return render_warp(self.field, origins, dirs, self.render_opt, behind=behind)

    return ContractedGridEngine


def _render_field_with_contracted(original):
    """`render_field` that also composites a `ContractedGrid` (the Model renders through it)."""

    def render_field(field, origins, dirs, opt, backend="warp", appearance=None, background=None):
        if isinstance(background, ContractedGrid):
            with torch.no_grad():
                behind = contracted_radiance(background, origins, dirs, opt)
                return render_warp(field, origins, dirs, opt, behind=behind)
        return original(field, origins, dirs, opt, backend, appearance, background)

    return render_field


def train_and_score(model_name: str, spec: RunSpec, s: ExperimentSettings, size: int, samples: int) -> dict:
    """Runs in its own process: the schedule's steps (as `Trainer.run`, without checkpoints), then the
    validation scores, the training time and this process's peak RSS."""
    import hdrplenoxels.train.engines as engines_module
    import hdrplenoxels.train.model as model_module

    if model_name == "contracted":
        engine = contracted_engine(size, samples)
        engines_module.engine_class = lambda key: engine
        model_module.render_field = _render_field_with_contracted(model_module.render_field)
    scene = spec.load_scene()
    trainer = Trainer(scene, spec.config, spec.run, overwrite=True)
    t0 = time.perf_counter()
    while trainer.step < spec.config.optim.n_iters:
        trainer.train_step()
        trainer.upsample()
    seconds = time.perf_counter() - t0
    trainer.lock.release()
    tone = spec.config.tonemap
    if trainer.tonemapper is not None and tone.output_prior_gamma and not tone.known_exposure:
        trainer.tonemapper.fit_exponent_to_response_prior(tone.output_prior_gamma)
    result = scores(trainer.model(), scene, s)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    return {"seconds": seconds, "peak_gb": peak_gb, "psnr": result["psnr"], "ssim": result["ssim"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="courtyard")
    parser.add_argument("--preset", default="balanced")
    parser.add_argument("--models", nargs="+", default=["msi", "contracted"], choices=("msi", "contracted"))
    parser.add_argument("--contracted-size", type=int, help="cells per side (default: the MSI's texels)")
    parser.add_argument("--contracted-samples", type=int, help="samples per ray (default: size / 2)")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides for both runs (key=value)")
    parser.add_argument("--long-side", type=int, default=400)
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--out", type=Path, default=Path("background_choice"))
    args = parser.parse_args()
    spec = SCENES[args.scene]
    scale = args.long_side / max(spec.width, spec.height)
    s = ExperimentSettings(
        resolution=(round(spec.width * scale), round(spec.height * scale)),
        spp=args.spp,
        lpips=False,
        data_root=args.out / "data",
        preset=args.preset,
        overrides=tuple(args.set),
    )
    root = validation_root(args.scene, s, args.out)
    cfg = config_for(s, tonemap=True)
    b = cfg.background
    size = args.contracted_size or round((b.layers * b.height * b.width * 8 / 7) ** (1 / 3))
    samples = args.contracted_samples or size // 2
    context = multiprocessing.get_context("spawn")
    results = {}
    for name in args.models:
        label = name if name == "msi" else f"contracted{size}x{samples}"
        spec = RunSpec(root / "varying", args.out / "runs" / "background_choice" / args.scene / label, cfg)
        with context.Pool(1) as pool:
            r = pool.apply(train_and_score, (name, spec, s, size, samples))
        results[label] = r
        print(
            f"{args.scene:10s} {label:18s} {r['seconds']:7.1f} s  peak {r['peak_gb']:5.2f} GB  "
            f"PSNR {r['psnr']:6.2f}  SSIM {r['ssim']:.3f}",
            flush=True,
        )
    out = args.out / f"background_choice_{args.scene}.json"
    out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
