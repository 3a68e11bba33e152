"""The library API: the example in docs/api.md runs as written (on a tiny scene), and the package's
exports resolve without importing anything until used."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import hdrplenoxels as hp

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"
PRESET_LINE = 'hp.preset("fast")'  # the example's preset; a 20-step tiny config here


def example_code() -> str:
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) == 1, "docs/api.md should hold one Python example"
    return blocks[0]


def test_every_export_resolves_and_is_documented():
    text = DOC.read_text()
    assert sorted(hp.__all__) == sorted(hp._EXPORTS)
    for name in hp.__all__:
        assert getattr(hp, name) is not None
        assert f"`{name}" in text, f"{name} is exported but not in docs/api.md's table"
    with pytest.raises(AttributeError):
        hp.no_such_name  # noqa: B018


def test_importing_the_package_imports_no_torch():
    code = "import sys, hdrplenoxels; print('torch' in sys.modules, 'warp' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_the_documented_example_trains_scores_and_renders(tmp_path, monkeypatch):
    from test_train import TINY, tiny_config

    from hdrplenoxels.synth.procedural import write_procedural_scene

    code = example_code()
    assert PRESET_LINE in code and 'data, run = "demo_data/varying", "runs/demo"' in code
    write_procedural_scene(tmp_path / "demo_data" / "varying", TINY)
    monkeypatch.chdir(tmp_path)
    namespace = {"tiny": tiny_config(20)}
    exec(compile(code.replace(PRESET_LINE, "tiny"), str(DOC), "exec"), namespace)

    assert (tmp_path / "runs" / "demo" / "model.npz").exists()
    assert np.isfinite(namespace["scores"]["psnr"]) and "right" in namespace["scores"]["protocol"]
    picture = namespace["picture"]
    h, w = TINY.height, TINY.width
    assert picture.hdr.shape == (h, w, 3) and picture.ldr.shape == (h, w, 3)
    assert float(picture.ldr.min()) >= 0.0 and float(picture.ldr.max()) <= 1.0
    assert (tmp_path / "view.exr").stat().st_size > 0 and (tmp_path / "view.png").stat().st_size > 0
    # one stop brighter than the predicted tone: its picture is brighter than auto at EV 0
    model, pose = namespace["model"], namespace["pose"]
    plain = hp.render_pose(model, pose, tone="auto", convention="opencv")
    assert float(picture.ldr.mean()) > float(plain.ldr.mean())
    assert np.allclose(plain.hdr.numpy(), picture.hdr.numpy())


def test_render_pose_checks_its_tone(tonemapped_run):
    model = hp.load_model(tonemapped_run)
    pose = model.geometry.poses_to_data(model.cameras.c2w[model.test_ids[0]])
    own = hp.render_pose(model, pose, tone=model.test_ids[0], convention="opencv")
    assert own.ldr.shape[-1] == 3
    # one convention, OpenGL by default, for the API as for `render --pose`
    from hdrplenoxels.geometry.cameras import opencv_to_opengl

    given = hp.render_pose(model, opencv_to_opengl(pose), tone=model.test_ids[0])
    assert torch.equal(given.hdr, own.hdr)
    assert not torch.equal(hp.render_pose(model, pose, tone=model.test_ids[0]).hdr, own.hdr)
    with pytest.raises(ValueError, match="use 'opengl' or 'opencv'"):
        hp.render_pose(model, pose, convention="colmap")
    with pytest.raises(ValueError, match="whole tone"):
        hp.render_pose(model, pose, tone=0, ev=1.0)
    with pytest.raises(ValueError, match="use 'auto'"):
        hp.render_pose(model, pose, tone="brightest")


def test_load_model_names_a_folder_without_one(tmp_path):
    from hdrplenoxels.core.errors import InputError

    with pytest.raises(InputError, match="no trained model"):
        hp.load_model(tmp_path)
