"""The suite runs with the command line's process settings, as a library user applying them would; and
the small trained runs several test files look at."""

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()

# isort: split
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tonemapped_run(tmp_path_factory) -> Path:
    """A run folder: the tiny procedural scene, 30 steps with the tone mapper (videos, the viewer)."""
    from test_train import TINY, tiny_config

    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import write_procedural_scene
    from hdrplenoxels.train.trainer import Trainer

    scene = load_scene(write_procedural_scene(tmp_path_factory.mktemp("scene"), TINY))
    cfg = tiny_config(30)
    cfg.tonemap.enabled = True
    folder = tmp_path_factory.mktemp("run")
    Trainer(scene, cfg, folder).run(progress=False)
    return folder
