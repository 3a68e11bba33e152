"""A trained model: the grid plus everything needed to render it without the training data."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.cameras import Cameras
from hdrplenoxels.errors import InputError
from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.grid_io import load_grid, save_grid
from hdrplenoxels.render import Backend, RenderOptions, render_rays
from hdrplenoxels.scene_setup import SceneGeometry

MODEL_FILE = "model.npz"


@dataclass
class Model:
    grid: SparseGrid
    geometry: SceneGeometry
    render_opt: RenderOptions
    cameras: Cameras  # every view of the training scene, in the grid's world frame
    names: list[str]
    train_ids: list[int]
    test_ids: list[int]
    data_path: str
    config: dict = field(default_factory=dict)
    step: int = 0

    def meta(self) -> dict:
        o = self.render_opt
        return {
            "kind": "model",
            "geometry": self.geometry.to_dict(),
            "render": {
                "step_size": o.step_size,
                "sigma_thresh": o.sigma_thresh,
                "stop_thresh": o.stop_thresh,
                "background": o.background,
            },
            "names": self.names,
            "train_ids": self.train_ids,
            "test_ids": self.test_ids,
            "data_path": self.data_path,
            "config": self.config,
            "step": self.step,
        }

    def extra_arrays(self) -> dict[str, np.ndarray]:
        return {
            "cameras/c2w": self.cameras.c2w,
            "cameras/intrinsics": self.cameras.intrinsics,
            "cameras/sizes": self.cameras.sizes,
        }

    def save(self, path: Path) -> None:
        save_grid(path, self.grid, meta=self.meta(), extra_arrays=self.extra_arrays())

    @classmethod
    def load(cls, path: Path, device: torch.device | str = "cpu") -> Model:
        grid, meta, extra = load_grid(path, device=device)
        if meta.get("kind") != "model" or "cameras/c2w" not in extra:
            raise InputError(path, "this grid file holds no trained model (no cameras or scene geometry)")
        cams = Cameras(extra["cameras/c2w"], extra["cameras/intrinsics"], extra["cameras/sizes"])
        return cls(
            grid=grid,
            geometry=SceneGeometry.from_dict(meta["geometry"]),
            render_opt=RenderOptions(**meta["render"]),
            cameras=cams,
            names=list(meta["names"]),
            train_ids=list(meta["train_ids"]),
            test_ids=list(meta["test_ids"]),
            data_path=meta["data_path"],
            config=meta.get("config", {}),
            step=int(meta.get("step", 0)),
        )

    @torch.no_grad()
    def render_view(
        self,
        c2w: np.ndarray,
        intrinsics: np.ndarray,
        size: tuple[int, int],
        backend: Backend = "warp",
        chunk: int = 1 << 15,
    ) -> torch.Tensor:
        """Linear radiance (H, W, 3) of a camera given in the grid's world frame (OpenCV c2w)."""
        w, h = size
        rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        rows, cols = rows.reshape(-1).to(self.grid.device), cols.reshape(-1).to(self.grid.device)
        pose = torch.as_tensor(c2w, dtype=torch.float32, device=self.grid.device)
        k = torch.as_tensor(intrinsics, dtype=torch.float32, device=self.grid.device)
        out = []
        for i in range(0, rows.shape[0], chunk):
            r, c = rows[i : i + chunk], cols[i : i + chunk]
            n = r.shape[0]
            o, d = self.geometry.rays(pose.expand(n, 4, 4), k.expand(n, 4), c, r)
            out.append(render_rays(self.grid, o, d, self.render_opt, backend))
        return torch.cat(out).reshape(h, w, 3)

    def render_camera(self, i: int, backend: Backend = "warp") -> torch.Tensor:
        return self.render_view(
            self.cameras.c2w[i], self.cameras.intrinsics[i], self.cameras.size(i), backend
        )
