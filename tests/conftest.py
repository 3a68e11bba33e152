"""The suite runs with the command line's process settings, as a library user applying them would, each
pytest-xdist worker on its share of the cores; and the small trained runs several test files look at."""

import os

from hdrplenoxels.core.process_settings import apply_process_settings, available_cores

apply_process_settings()
# Under pytest-xdist each worker gets its share of the cores (torch reads this when it loads, and our CPU
# kernels use torch's thread count): two workers each running two threads on two cores fight over them.
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, available_cores() // _workers)))

# isort: split
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_scene_path(tmp_path_factory) -> Path:
    """The suite's tiny procedural scene (`test_train.TINY`), written once per test process."""
    from test_train import TINY

    from hdrplenoxels.synth.procedural import write_procedural_scene

    return write_procedural_scene(tmp_path_factory.mktemp("scene"), TINY)


@pytest.fixture(scope="session")
def tiny_scene(tiny_scene_path):
    """The tiny scene loaded; tests derive variants with `dataclasses.replace`, never change it."""
    from hdrplenoxels.data import load_scene

    return load_scene(tiny_scene_path)


@pytest.fixture(scope="session")
def walled(tmp_path_factory):
    """The tiny walled room (`synth.procedural.TINY_WALLED`: a cascade's scene at a test's size), loaded
    once per test process; tests derive variants with `dataclasses.replace`, never change it."""
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.synth.procedural import TINY_WALLED, write_procedural_scene

    return load_scene(write_procedural_scene(tmp_path_factory.mktemp("walled"), TINY_WALLED))


@pytest.fixture(scope="session")
def tonemapped_run(tmp_path_factory, tiny_scene) -> Path:
    """A run folder: the tiny procedural scene, 30 steps with the tone mapper (videos, the viewer)."""
    from test_train import tiny_config

    from hdrplenoxels.train.trainer import Trainer

    cfg = tiny_config(30)
    cfg.tonemap.enabled = True
    folder = tmp_path_factory.mktemp("run")
    Trainer(tiny_scene, cfg, folder).run(progress=False)
    return folder


@pytest.fixture(autouse=True, scope="session")
def _every_learned_response_rises():
    """No learned response curve goes down anywhere: every run the suite trains is checked as it ends
    (a curve that decreases has no inverse, so its HDR would not be the light that made the photo)."""
    import torch

    from hdrplenoxels.train.trainer import Trainer

    original = Trainer.run

    def checked(self, progress: bool = True):
        model = original(self, progress)
        tm = model.tonemapper
        if tm is not None and tm.cfg.response == "monotonic":
            steps = torch.diff(tm.knots().detach(), dim=-1)
            down = float(steps.min())
            assert down >= 0.0, f"a learned response goes down ({down:.3g}) in {self.out_dir}"
        return model

    Trainer.run = checked
    yield
    Trainer.run = original
