"""A trained model: the radiance field (a grid or a NeRF) plus everything needed to render it without the
training data."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.geometry.cameras import Cameras, pixel_grid
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import Backend, RenderOptions
from hdrplenoxels.render.fields import Field, render_field
from hdrplenoxels.render.nerf import Appearance
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.controller import ToneController
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.tonemap.response import controlled_ldr
from hdrplenoxels.train.field_io import load_field_with_background, save_field

MODEL_FILE = "model.npz"


def render_options(saved: dict) -> RenderOptions:
    """A model's saved render options ("background": the old name of `background_brightness`)."""
    saved = dict(saved)
    if "background" in saved:
        saved["background_brightness"] = saved.pop("background")
    return RenderOptions(**saved)


@dataclass
class Model:
    field: Field
    geometry: SceneGeometry
    render_opt: RenderOptions
    cameras: Cameras  # every view of the training scene, in the grid's world frame
    names: list[str]
    train_ids: list[int]
    test_ids: list[int]
    data_path: str
    config: dict = dataclasses.field(default_factory=dict)
    step: int = 0
    tonemapper: ToneMapper | None = None  # the learned tones; None for a plain Plenoxels run
    background: MSIBackground | None = None  # the MSI behind a grid's box; None: the constant background
    controller: ToneController | None = None  # a new view's tone from its radiance (with a tone mapper)

    def meta(self) -> dict:
        o = self.render_opt
        return {
            "kind": "model",
            "geometry": self.geometry.to_dict(),
            "render": {
                "step_size": o.step_size,
                "sigma_thresh": o.sigma_thresh,
                "stop_thresh": o.stop_thresh,
                "background_brightness": o.background_brightness,
            },
            "names": self.names,
            "train_ids": self.train_ids,
            "test_ids": self.test_ids,
            "data_path": self.data_path,
            "config": self.config,
            "step": self.step,
        }

    def extra_arrays(self) -> dict[str, np.ndarray]:
        arrays = {
            "cameras/c2w": self.cameras.c2w,
            "cameras/intrinsics": self.cameras.intrinsics,
            "cameras/sizes": self.cameras.sizes,
        }
        if self.tonemapper is not None:
            arrays.update({f"tonemap/{k}": v for k, v in self.tonemapper.state_arrays().items()})
        if self.controller is not None:
            arrays.update({f"controller/{k}": v for k, v in self.controller.state_arrays().items()})
        return arrays

    def save(self, path: Path) -> None:
        save_field(
            path, self.field, meta=self.meta(), extra_arrays=self.extra_arrays(), background=self.background
        )

    @classmethod
    def load(cls, path: Path, device: torch.device | str = "cpu") -> Model:
        field, background, meta, extra = load_field_with_background(path, device=device)
        if meta.get("kind") != "model" or "cameras/c2w" not in extra:
            raise InputError(path, "this grid file holds no trained model (no cameras or scene geometry)")
        cams = Cameras(extra["cameras/c2w"], extra["cameras/intrinsics"], extra["cameras/sizes"])
        tonemapper = None
        tone_arrays = {k.removeprefix("tonemap/"): v for k, v in extra.items() if k.startswith("tonemap/")}
        if tone_arrays:
            cfg = ToneMapConfig(**meta.get("config", {}).get("tonemap", {}))
            tonemapper = ToneMapper(len(cams), cams.sizes, cfg).to(device)
            tonemapper.load_state_arrays(tone_arrays)
        controller = None
        ctl = {k.removeprefix("controller/"): v for k, v in extra.items() if k.startswith("controller/")}
        if ctl:
            try:
                controller = ToneController.from_state_arrays(ctl)
            except (KeyError, ValueError) as e:
                raise InputError(path, f"its tone controller is unreadable ({e})") from e
        return cls(
            field=field,
            geometry=SceneGeometry.from_dict(meta["geometry"]),
            render_opt=render_options(meta["render"]),
            cameras=cams,
            names=list(meta["names"]),
            train_ids=list(meta["train_ids"]),
            test_ids=list(meta["test_ids"]),
            data_path=meta["data_path"],
            config=meta.get("config", {}),
            step=int(meta.get("step", 0)),
            tonemapper=tonemapper,
            background=background,
            controller=controller,
        )

    @property
    def grid(self) -> SparseGrid:
        """The field of a grid model (NeRF models have none)."""
        if not isinstance(self.field, SparseGrid):
            raise ValueError("this model is a NeRF, not a voxel grid")
        return self.field

    def default_appearance(self, image_id: int | None = None) -> Appearance:
        """The appearance a NeRF-A render uses unless told: image `image_id`'s own, else the first
        training view's (other fields ignore it)."""
        return Appearance(image_id if image_id is not None else (self.train_ids or [0])[0])

    @torch.no_grad()
    def render_view(
        self,
        c2w: np.ndarray,
        intrinsics: np.ndarray,
        size: tuple[int, int],
        backend: Backend = "warp",
        appearance: Appearance | None = None,
        chunk: int | None = None,
    ) -> torch.Tensor:
        """Linear radiance (H, W, 3) of a camera given in the field's world frame (OpenCV c2w), the MSI
        background (if any) composited behind the field; `appearance` picks a NeRF-A's (default:
        `default_appearance()`); `chunk` rays at a time (default: a CUDA grid's whole view, which its
        renderer then marches a thread per ray, see `kernels.march_kernel.lanes_for`; else 32 768)."""
        w, h = size
        device = torch.device(self.field.device)
        if chunk is None:
            chunk = 1 << 20 if isinstance(self.field, SparseGrid) and device.type == "cuda" else 1 << 15
        rows, cols = pixel_grid(h, w, device)
        pose = torch.as_tensor(c2w, dtype=torch.float32, device=device)
        k = torch.as_tensor(intrinsics, dtype=torch.float32, device=device)
        appearance = appearance or self.default_appearance()
        out = []
        for i in range(0, rows.shape[0], chunk):
            r, c = rows[i : i + chunk], cols[i : i + chunk]
            n = r.shape[0]
            o, d = self.geometry.rays(pose.expand(n, 4, 4), k.expand(n, 4), c, r)
            out.append(render_field(self.field, o, d, self.render_opt, backend, appearance, self.background))
        return torch.cat(out).reshape(h, w, 3)

    def render_camera(
        self, i: int, backend: Backend = "warp", appearance: Appearance | None = None
    ) -> torch.Tensor:
        """View `i` (with its own NeRF-A appearance unless `appearance` says otherwise)."""
        cams = self.cameras
        return self.render_view(
            cams.c2w[i], cams.intrinsics[i], cams.size(i), backend, appearance or self.default_appearance(i)
        )

    @torch.no_grad()
    def to_ldr(self, radiance: torch.Tensor, image_id: int) -> torch.Tensor:
        """Image `image_id`'s learned tone applied to a radiance image (H, W, 3), clipped to [0, 1].

        Without a tone mapper the radiance is the prediction of the LDR image itself (plain Plenoxels).
        """
        if self.tonemapper is None:
            return radiance.clamp(0.0, 1.0)
        h, w = radiance.shape[:2]
        dev = self.tonemapper.log_wb.device
        rows, cols = pixel_grid(h, w, dev)
        ids = torch.full((h * w,), image_id, dtype=torch.long, device=dev)
        flat = self.tonemapper(radiance.reshape(-1, 3).to(dev), ids, rows, cols, training=False)
        return flat.reshape(h, w, 3).clamp(0.0, 1.0)

    @torch.no_grad()
    def to_ldr_controlled(
        self,
        radiance: torch.Tensor,
        ev: float = 0.0,
        wb: tuple[float, float, float] = (1.0, 1.0, 1.0),
        crf_from: int | None = None,
        crf_source: ToneMapper | None = None,
        tone: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """A user-controlled tone: exposure `ev` stops and per-channel gains `wb` relative to the mean of
        all views' white balance, or to `tone(linear radiance)`'s natural-log gains (3,) (the tone
        controller's prediction, say); with the response of view `crf_from` (of `crf_source`, the tones
        of another trained run or of a tone_params.json, when given; default: this model's reference)."""
        if self.tonemapper is None:
            raise ValueError("this model has no learned tones (trained without --tonemap)")
        source = crf_source or self.tonemapper
        view = int(source.reference) if crf_from is None else crf_from
        dev = self.tonemapper.log_wb.device
        linear = self.tonemapper.linear_radiance(radiance.to(dev))
        basis = tone(linear) if tone is not None else self.mean_log_wb()
        log_gains = basis + ev * math.log(2.0) + torch.log(torch.tensor(wb, device=dev))
        return controlled_ldr(linear, log_gains, source.curve(view))

    def mean_log_wb(self) -> torch.Tensor:
        """The mean learned tone (3,): over every view that trained its tone (all of them, unless
        `--holdout full` kept the test views out, whose tones then stay at their initial value)."""
        full = self.config.get("holdout") == "full"
        return self.tonemapper.basis_log_wb(list(self.train_ids) if full else None)

    def auto_tone(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The tone controller's prediction, for `to_ldr_controlled(tone=...)`."""
        if self.controller is None:
            raise ValueError("this model has no tone controller (a checkpoint, or a run from before them)")
        return self.controller.log_gains

    @torch.no_grad()
    def hdr(self, radiance: torch.Tensor) -> torch.Tensor:
        """What to save as HDR: the rendered radiance, linearised when known exposures fixed the exponent."""
        return radiance if self.tonemapper is None else self.tonemapper.linear_radiance(radiance)


def load_model(path: str | Path, device: torch.device | str = "cpu") -> Model:
    """The trained model of a run folder (its model.npz) or of a model file; an `InputError` naming the
    file when there is none or it is damaged."""
    path = Path(path)
    if path.is_dir():
        path = path / MODEL_FILE
    if not path.exists():
        raise InputError(path, "no trained model here (train first, or pass the model .npz)")
    try:
        return Model.load(path, device=device)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError) as e:
        # load_grid has checked the arrays; this is the model's own part (meta, cameras, tone mapper)
        reason = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise InputError(path, f"damaged model file ({type(e).__name__}: {reason})") from None
