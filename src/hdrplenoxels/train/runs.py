"""One training as a value (`RunSpec`): what to train, where, with which configuration. Experiments list
their runs as specs so an executor can train them anywhere (docs/design.md, "Executors"), and every
executor trains a spec through `train_spec`, so a run is the same wherever it was trained."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrplenoxels.core.devices import pick_device
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.exposures import load_exposures
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.run_folder import LOG_FILE, resumable_checkpoints
from hdrplenoxels.train.trainer import Trainer

CONFIG_FILE = "config.json"


@dataclass
class RunSpec:
    """A dataset trained into a run folder with `config`; `known_exposure`: the views' true EVs are read
    from the dataset's camera_truth.json (synthetic captures)."""

    data: Path
    run: Path
    config: TrainConfig
    known_exposure: bool = False

    def load_scene(self) -> SceneData:
        scene = load_scene(self.data, self.config.data.downscale)
        if self.known_exposure:
            scene.exposures = load_exposures(self.data / "camera_truth.json", scene.names)
        return scene

    def same_config(self) -> bool:
        """Whether the run folder was started with exactly this configuration."""
        path = self.run / CONFIG_FILE
        try:
            saved = json.loads(path.read_text())
        except (OSError, ValueError):
            return False
        return saved == json.loads(json.dumps(self.config.to_dict()))

    def finished(self) -> bool:
        """Whether the run holds its final model for this configuration (read from the model file's
        metadata only, without loading the scene or the grid)."""
        if not (self.run / MODEL_FILE).exists() or not self.same_config():
            return False
        try:
            with np.load(self.run / MODEL_FILE) as z:
                meta = json.loads(str(z["meta_json"]))
        except (OSError, ValueError, KeyError):
            return False
        return int(meta.get("step", -1)) == self.config.optim.n_iters


def train_seconds(run: Path) -> float | None:
    """Wall seconds of a run's training as its log's last line says (None: no log yet)."""
    log = Path(run) / LOG_FILE
    lines = log.read_text().splitlines() if log.is_file() else []
    return float(json.loads(lines[-1])["seconds"]) if lines else None


def train_spec(spec: RunSpec, resume: bool = False, progress: bool = False) -> tuple[Model, SceneData]:
    """The run's model: loaded when it finished with the same configuration and data, else trained.
    `resume`: continue from the run's newest checkpoint when it was started with this very configuration
    (a retried task whose worker died); otherwise any old run in the folder is replaced."""
    cfg = spec.config
    scene = spec.load_scene()
    if spec.finished():
        model = Model.load(spec.run / MODEL_FILE, device=str(pick_device(cfg.device)))
        if model.data_path == str(scene.source) and model.step == cfg.optim.n_iters:
            return model, scene
    found = resumable_checkpoints(spec.run) if resume and spec.same_config() else []
    if found:
        print(f"resuming {spec.run} from {found[-1].name}", flush=True)
    resume = bool(found)
    return Trainer(scene, cfg, spec.run, resume=resume, overwrite=not resume).run(progress=progress), scene
