"""A vanilla NeRF radiance field (docs/method.md, "NeRF engine"): positional encoding, an MLP with a skip
connection and a view-dependent colour branch, stratified coarse samples plus importance-sampled fine
samples, and linear colour with no upper bound (softplus) so that it can hold HDR radiance.

NeRF-A (NeRF-W's appearance embeddings without transients) is an option: a learned vector per image fed
into the colour branch only, so that geometry is shared and only colour follows the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import nn
from torch.nn import functional as F

from hdrplenoxels.core.settings import setting


@dataclass
class NerfConfig:
    """Architecture and sampling: what a saved NeRF needs to render (its Adam settings are training's:
    `train/config.py`'s `NerfSettings`). The defaults are CPU-sized, small enough to train a 64x64,
    50-view scene in minutes on two cores (JOURNAL.md); `paper()` has vanilla NeRF's sizes."""

    width: int = setting(64, at_least=1)
    """Hidden width of the density trunk."""
    depth: int = setting(4, at_least=1)
    """Layers of the density trunk."""
    skip: int = setting(2, at_least=0)
    """The encoded position is fed again after this many layers."""
    view_width: int = setting(32, at_least=1)
    """Hidden width of the colour branch."""
    pos_freqs: int = setting(6, at_least=0)
    """Octaves of the position encoding."""
    dir_freqs: int = setting(2, at_least=0)
    """Octaves of the view-direction encoding."""
    n_coarse: int = setting(32, at_least=1)
    """Stratified samples per ray."""
    n_fine: int = setting(32, at_least=0)
    """Importance samples per ray (added to the coarse ones for the fine network)."""
    appearance: bool = False
    """NeRF-A: a learned embedding per image into the colour branch."""
    appearance_dim: int = setting(48, at_least=1)
    """Length of each image's appearance embedding."""

    @staticmethod
    def among(values: dict) -> NerfConfig:
        """The network settings among `values`, which may hold others (a `NerfSettings`' Adam rates)."""
        if not isinstance(values, dict):
            raise TypeError(f"NeRF settings must be a mapping, got {type(values).__name__}")
        known = {f.name for f in fields(NerfConfig)}
        return NerfConfig(**{k: v for k, v in values.items() if k in known})

    @classmethod
    def paper(cls) -> NerfConfig:
        """Vanilla NeRF's network (Mildenhall et al. 2020): 8 x 256 with a skip at 4, 10 and 4 octaves,
        64 + 128 samples."""
        return cls(
            width=256,
            depth=8,
            skip=4,
            view_width=128,
            pos_freqs=10,
            dir_freqs=4,
            n_coarse=64,
            n_fine=128,
        )


@dataclass
class Appearance:
    """Which image's embedding a NeRF-A render uses: `first`'s, or a blend `(1 - weight) first + weight
    second` of two images' embeddings. A tuple of images stands for the mean of their embeddings (a
    group's appearance, e.g. all darker views')."""

    first: int | tuple[int, ...]
    second: int | tuple[int, ...] | None = None
    weight: float = 0.0


def encode(x: torch.Tensor, octaves: int) -> torch.Tensor:
    """[x, sin(2^k pi x), cos(2^k pi x)] for k < octaves, (N, D) -> (N, D (1 + 2 octaves))."""
    freqs = math.pi * 2.0 ** torch.arange(octaves, dtype=x.dtype, device=x.device)
    angles = (x[..., None, :] * freqs[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class RadianceMLP(nn.Module):
    """Density from the encoded position; colour from a feature, the encoded direction and (NeRF-A) the
    appearance code."""

    def __init__(self, cfg: NerfConfig):
        super().__init__()
        pos_dim = 3 * (1 + 2 * cfg.pos_freqs)
        dir_dim = 3 * (1 + 2 * cfg.dir_freqs)
        code_dim = cfg.appearance_dim if cfg.appearance else 0
        self.skip = cfg.skip
        layers = []
        for i in range(cfg.depth):
            fan_in = pos_dim if i == 0 else cfg.width + (pos_dim if i == cfg.skip else 0)
            layers.append(nn.Linear(fan_in, cfg.width))
        self.trunk = nn.ModuleList(layers)
        self.sigma = nn.Linear(cfg.width, 1)
        self.feature = nn.Linear(cfg.width, cfg.width)
        self.view = nn.Linear(cfg.width + dir_dim + code_dim, cfg.view_width)
        self.rgb = nn.Linear(cfg.view_width, 3)

    def forward(
        self, pos: torch.Tensor, dirs: torch.Tensor, code: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Density (M,) and linear radiance (M, 3) of encoded positions and directions (M, .)."""
        h = pos
        for i, layer in enumerate(self.trunk):
            if i == self.skip:
                h = torch.cat([h, pos], dim=-1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.sigma(h)[:, 0])
        parts = [self.feature(h), dirs] + ([] if code is None else [code])
        return sigma, F.softplus(self.rgb(F.relu(self.view(torch.cat(parts, dim=-1)))))


def box_near_far(
    origins: torch.Tensor, dirs: torch.Tensor, center: torch.Tensor, radius: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where rays enter and leave the axis-aligned box center +- radius (the grid's box), (N,) each;
    rays that miss it get near == far (no samples contribute)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (center - radius - origins) * inv
    t1 = (center + radius - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, torch.maximum(far, near)


def stratified(
    near: torch.Tensor, far: torch.Tensor, n: int, generator: torch.Generator | None
) -> torch.Tensor:
    """n depths per ray, one uniform draw in each of n equal bins of [near, far] (bin centres without
    `generator`), (N, n) and increasing."""
    u = torch.full((near.shape[0], n), 0.5, device=near.device)
    if generator is not None:
        u = torch.rand(u.shape, generator=generator, device=near.device)
    steps = (torch.arange(n, device=near.device) + u) / n
    return near[:, None] + (far - near)[:, None] * steps


def importance(
    t: torch.Tensor, weights: torch.Tensor, n: int, generator: torch.Generator | None
) -> torch.Tensor:
    """n depths drawn from the piecewise-constant density of `weights` over the bins between the
    midpoints of `t` (NeRF's inverse-CDF sampling; evenly spaced quantiles without `generator`)."""
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    w = weights[:, 1:-1].detach() + 1e-5
    cdf = torch.cumsum(w / w.sum(-1, keepdim=True), -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)
    if generator is None:
        u = torch.linspace(0.0, 1.0, n + 2, device=t.device)[1:-1].expand(t.shape[0], n)
    else:
        u = torch.rand((t.shape[0], n), generator=generator, device=t.device)
    u = u.contiguous()
    hi = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    lo = hi - 1
    c0, c1 = cdf.gather(1, lo), cdf.gather(1, hi)
    b0, b1 = mids.gather(1, lo), mids.gather(1, hi)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-8)).clamp(0.0, 1.0)
    return b0 + frac * (b1 - b0)


def composite(
    sigma: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor, far: torch.Tensor, background_brightness: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Radiance (N, 3) and weights (N, S) of samples at increasing depths `t` (unit directions): each
    sample covers up to the next, the last up to `far`; what is left shows the background."""
    deltas = torch.cat([t[:, 1:] - t[:, :-1], (far[:, None] - t[:, -1:]).clamp_min(0.0)], -1)
    alpha = 1.0 - torch.exp(-sigma * deltas)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1), -1)
    weights = alpha * trans[:, :-1]
    colour = (weights[..., None] * rgb).sum(1) + (1.0 - weights.sum(1, keepdim=True)) * background_brightness
    return colour, weights


class NerfField(nn.Module):
    """Coarse and fine networks inside the scene's box (world or NDC coordinates), and per-image
    appearance codes for NeRF-A."""

    def __init__(self, cfg: NerfConfig, center, radius, n_images: int):
        super().__init__()
        self.cfg = cfg
        self.n_images = n_images
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32))
        self.register_buffer("radius", torch.tensor(radius, dtype=torch.float32))
        self.coarse = RadianceMLP(cfg)
        self.fine = RadianceMLP(cfg)
        self.codes = nn.Embedding(n_images, cfg.appearance_dim) if cfg.appearance else None
        if self.codes is not None:
            nn.init.normal_(self.codes.weight, std=0.01)

    @property
    def device(self) -> torch.device:
        return self.center.device

    def appearance_codes(self, n: int, image_ids: torch.Tensor | None, appearance: Appearance | None):
        """(n, dim) codes of the rays' images, or of `appearance` for all of them; None without NeRF-A."""
        if self.codes is None:
            return None
        if appearance is None:
            if image_ids is None:
                raise ValueError("a NeRF-A render needs the rays' image ids or an Appearance")
            return self.codes(image_ids)
        code = self._code(appearance.first)
        if appearance.second is not None:
            code = torch.lerp(code, self._code(appearance.second), appearance.weight)
        return code.expand(n, -1)

    def _code(self, images: int | tuple[int, ...]) -> torch.Tensor:
        """One image's embedding, or the mean of a group's."""
        group = (images,) if isinstance(images, int) else tuple(images)
        if not group:
            raise ValueError("appearance of an empty group of images")
        for i in group:
            if not 0 <= i < self.n_images:
                raise ValueError(f"appearance of image {i}: the model has images 0..{self.n_images - 1}")
        if isinstance(images, int):
            return self.codes.weight[images]
        return self.codes.weight[list(group)].mean(0)

    def _shade(self, net: RadianceMLP, origins, dirs, t, far, code, background_brightness: float):
        n, s = t.shape
        pts = origins[:, None] + t[..., None] * dirs[:, None]
        pos = encode(((pts - self.center) / self.radius).reshape(-1, 3), self.cfg.pos_freqs)
        view = encode(dirs, self.cfg.dir_freqs).repeat_interleave(s, 0)
        sample_code = None if code is None else code.repeat_interleave(s, 0)
        sigma, rgb = net(pos, view, sample_code)
        return composite(sigma.view(n, s), rgb.view(n, s, 3), t, far, background_brightness)

    def forward(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        background_brightness: float,
        image_ids: torch.Tensor | None = None,
        appearance: Appearance | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Coarse and fine radiance (N, 3) each of rays with unit directions; `generator` draws the
        training jitter (without it, deterministic bin centres and quantiles)."""
        near, far = box_near_far(origins, dirs, self.center, self.radius)
        code = self.appearance_codes(origins.shape[0], image_ids, appearance)
        t_coarse = stratified(near, far, self.cfg.n_coarse, generator)
        rgb_coarse, weights = self._shade(
            self.coarse, origins, dirs, t_coarse, far, code, background_brightness
        )
        t_fine = importance(t_coarse, weights, self.cfg.n_fine, generator)
        t_all, _ = torch.sort(torch.cat([t_coarse, t_fine], -1), -1)
        rgb_fine, _ = self._shade(self.fine, origins, dirs, t_all, far, code, background_brightness)
        return rgb_coarse, rgb_fine

    @torch.no_grad()
    def render(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        background_brightness: float,
        appearance: Appearance | None = None,
        chunk: int = 4096,
    ) -> torch.Tensor:
        """Fine radiance (N, 3), deterministic, in chunks of rays (bounded memory)."""
        out = [
            self(origins[i : i + chunk], dirs[i : i + chunk], background_brightness, appearance=appearance)[1]
            for i in range(0, origins.shape[0], chunk)
        ]
        return torch.cat(out) if out else origins.new_zeros((0, 3))
