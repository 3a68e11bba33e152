"""What the viewer shows for a rendered radiance image: the picture for each display mode and control
setting, the log-luminance histogram, and the false-colour legend. Pure functions, so the viewer's
pictures can be tested without a browser."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from hdrplenoxels.eval.video import frame_ldr
from hdrplenoxels.train.model import Model

DisplayMode = Literal["tone-mapped", "linear HDR", "false colour", "depth", "opacity"]
DISPLAY_MODES: tuple[str, ...] = ("tone-mapped", "linear HDR", "false colour", "depth", "opacity")
GEOMETRY_MODES = ("depth", "opacity")  # shown from depth_and_opacity, not from the radiance
LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709 / sRGB primaries


def srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function of linear values, clipped to [0, 1]."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=1e-12) ** (1 / 2.4) - 0.055)


def gamma22(x: torch.Tensor) -> torch.Tensor:
    return x.clamp(0.0, 1.0) ** (1 / 2.2)


def filmic(x: torch.Tensor) -> torch.Tensor:
    """An S-shaped curve with a soft shoulder (Hable's "Uncharted 2" operator, white point 11.2), encoded
    with gamma 2.2: highlights roll off instead of clipping."""

    def hable(v: torch.Tensor) -> torch.Tensor:
        a, b, c, d, e, f = 0.15, 0.50, 0.10, 0.20, 0.02, 0.30
        return ((v * (a * v + c * b) + d * e) / (v * (a * v + b) + d * f)) - e / f

    white = hable(torch.tensor(11.2))
    return gamma22(hable(x.clamp(min=0.0) * 2.0) / white)


def linear_clip(x: torch.Tensor) -> torch.Tensor:
    return x.clamp(0.0, 1.0)


STANDARD_RESPONSES: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "sRGB": srgb,
    "gamma 2.2": gamma22,
    "filmic": filmic,
    "linear clip": linear_clip,
}


@dataclass
class ViewState:
    """The viewer's controls. `response`: "reference", "view N" (a learned curve) or a standard curve's
    name. `adopted`: a training view whose whole learned tone is shown until a control moves. `auto`:
    EV and gains relative to the tone the model's controller predicts for the picture (auto exposure),
    not to the views' mean."""

    ev: float = 0.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    response: str = "reference"  # "as trained" for a model without tone mapping
    mode: str = "tone-mapped"
    adopted: int | None = None
    auto: bool = False
    false_colour_stops: tuple[float, float] = field(default=(-8.0, 4.0))


def display_modes(model: Model) -> tuple[str, ...]:
    """Depth and opacity come from the grid's march; other fields show their radiance only."""
    from hdrplenoxels.grid.sparse_grid import SparseGrid

    return DISPLAY_MODES if isinstance(model.field, SparseGrid) else DISPLAY_MODES[:3]


def response_choices(model: Model) -> list[str]:
    learned = (
        [] if model.tonemapper is None else ["reference", *(f"view {i}" for i in range(len(model.names)))]
    )
    return [*learned, *STANDARD_RESPONSES]


def linear_exposed(model: Model, radiance: torch.Tensor, state: ViewState) -> torch.Tensor:
    """Linear radiance through the neutral tone (the views' mean white balance, or the controller's
    tone for this picture with `state.auto`), the EV and the gains."""
    gains = torch.tensor(state.wb, dtype=torch.float32) * 2.0**state.ev
    if model.tonemapper is None:
        return radiance.float().cpu() * gains
    linear = model.hdr(radiance).float().cpu()
    log_basis = auto_tone(model, state)(linear) if state.auto else model.mean_log_wb()
    return linear * torch.exp(log_basis.detach().float().cpu()) * gains


def auto_tone(model: Model, state: ViewState) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The controller's tone when `state.auto` asks for it (None otherwise)."""
    return model.auto_tone() if state.auto and model.tonemapper is not None else None


def tone_mapped(model: Model, radiance: torch.Tensor, state: ViewState) -> torch.Tensor:
    """The picture through the adopted view's tone, a standard curve, or a learned response (a model
    trained without tone mapping renders its pictures' own encoding: "as trained" only clips it)."""
    if state.adopted is not None:
        return model.to_ldr(radiance, state.adopted).float().cpu()
    if state.response in STANDARD_RESPONSES:
        return STANDARD_RESPONSES[state.response](linear_exposed(model, radiance, state))
    view = state.response.removeprefix("view ")
    crf_from = int(view) if view.isdigit() else None  # "reference" (or "as trained": no tone mapper)
    tone = auto_tone(model, state)
    return frame_ldr(model, radiance, state.ev, state.wb, crf_from, tone).float().cpu()


def log2_luminance(linear: torch.Tensor) -> torch.Tensor:
    lum = (linear * torch.tensor(LUMINANCE, dtype=linear.dtype)).sum(-1)
    return torch.log2(lum.clamp(min=2.0**-20))


def turbo(t: np.ndarray) -> np.ndarray:
    """matplotlib's "turbo" colour map of values in [0, 1], as uint8 RGB."""
    from matplotlib import colormaps

    return (colormaps["turbo"](np.clip(t, 0.0, 1.0))[..., :3] * 255.0 + 0.5).astype(np.uint8)


def false_colour(linear: torch.Tensor, stops: tuple[float, float]) -> np.ndarray:
    """log2 luminance over [stops[0], stops[1]] through the turbo map (blue: dark, red: bright)."""
    lo, hi = stops
    return turbo(((log2_luminance(linear) - lo) / (hi - lo)).numpy())


def legend(stops: tuple[float, float], width: int = 256, height: int = 16) -> np.ndarray:
    """The false-colour bar, darkest stop at the left."""
    return np.repeat(turbo(np.linspace(0.0, 1.0, width))[None], height, axis=0)


def display_image(model: Model, radiance: torch.Tensor, state: ViewState) -> np.ndarray:
    """(H, W, 3) uint8 picture of a radiance image (H, W, 3) for the viewer's current controls."""
    if state.mode == "false colour":
        return false_colour(linear_exposed(model, radiance, state), state.false_colour_stops)
    if state.mode == "linear HDR":
        picture = srgb(linear_exposed(model, radiance, state))  # linear values, sRGB-encoded for the screen
    elif state.mode == "tone-mapped":
        picture = tone_mapped(model, radiance, state)
    else:
        raise ValueError(f"unknown display mode {state.mode!r}; choose one of {DISPLAY_MODES}")
    return (picture.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()


def histogram(linear: torch.Tensor, stops: tuple[float, float] = (-16.0, 8.0), bins: int = 96) -> np.ndarray:
    """A (64, bins * 2, 3) uint8 picture of the frame's log2-luminance histogram over `stops`, with a
    tick at every 4 stops; counts on a square-root scale so that small peaks stay visible."""
    lo, hi = stops
    counts, _ = np.histogram(log2_luminance(linear).numpy().ravel(), bins=bins, range=(lo, hi))
    heights = np.sqrt(counts / max(counts.max(), 1)) * 60
    image = np.full((64, bins * 2, 3), 24, dtype=np.uint8)
    for b, h in enumerate(heights):
        image[64 - int(math.ceil(h)) :, 2 * b : 2 * b + 2] = turbo(np.array([(b + 0.5) / bins]))[0]
    for stop in range(int(math.ceil(lo / 4) * 4), int(hi) + 1, 4):
        image[:4, max(0, int((stop - lo) / (hi - lo) * bins * 2) - 1)] = 200
    return image


@torch.no_grad()
def depth_opacity_view(
    model: Model, c2w: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth, opacity) images (H, W) of a camera in the grid's world frame (depth in the grid's units)."""
    from hdrplenoxels.geometry.cameras import pixel_grid
    from hdrplenoxels.render.auxiliary import depth_and_opacity

    w, h = size
    device = model.grid.device
    rows, cols = pixel_grid(h, w, device)
    pose = torch.as_tensor(c2w, dtype=torch.float32, device=device)
    k = torch.as_tensor(intrinsics, dtype=torch.float32, device=device)
    n = rows.shape[0]
    origins, dirs = model.geometry.rays(pose.expand(n, 4, 4), k.expand(n, 4), cols, rows)
    depth, opacity = depth_and_opacity(model.grid, origins, dirs, model.render_opt, origins.mean(0))
    return depth.reshape(h, w).cpu(), opacity.reshape(h, w).cpu()


def geometry_image(depth: torch.Tensor, opacity: torch.Tensor, mode: str) -> np.ndarray:
    """Opacity as grey; depth through turbo between its 2nd and 98th percentile where something is hit
    (near: blue, far: red), black where nothing is."""
    if mode == "opacity":
        grey = (opacity.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()
        return np.repeat(grey[..., None], 3, axis=-1)
    hit = opacity > 0.5
    picture = np.zeros((*depth.shape, 3), dtype=np.uint8)
    if hit.any():
        lo, hi = np.percentile(depth[hit].numpy(), [2, 98])
        picture[hit.numpy()] = turbo(((depth[hit] - lo) / max(hi - lo, 1e-6)).numpy())
    return picture
