"""End to end: on a tiny varying-exposure scene, learned tone mapping beats plain Plenoxels by >= 5 dB."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from hdrplenoxels.cli.main import main
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.image_io import read_exr, read_image
from hdrplenoxels.eval.evaluate import evaluate
from hdrplenoxels.eval.metrics import psnr
from hdrplenoxels.experiments.reexposure import camera_settings, reexposure, reexposure_target
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.synth.pipeline import PipelineConfig
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer


@pytest.fixture(scope="module")
def varying_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny360")
    opts = SynthOptions(n_views=32, width=48, height=48, spp=16)
    synthesize("objects360", out, opts, PipelineConfig(seed=1))
    return load_scene(out / "varying")


@pytest.fixture(scope="module")
def tonemapped(varying_scene, tmp_path_factory) -> Path:
    """Ours (`fast`, the tone mapper) trained on the varying scene: its run folder."""
    cfg = preset("fast")
    cfg.tonemap.enabled = True
    run = tmp_path_factory.mktemp("ours")
    Trainer(varying_scene, cfg, run).run(progress=False)
    return run


def test_tone_mapping_beats_plain_plenoxels_on_varying_cameras(varying_scene, tonemapped, tmp_path):
    cfg = preset("fast")
    cfg.tonemap.enabled = False
    plain = Trainer(varying_scene, cfg, tmp_path / "plain").run(progress=False)
    psnr = {}
    for tonemap, model in ((False, plain), (True, Model.load(tonemapped / "model.npz"))):
        result = evaluate(model, varying_scene, lpips=False)
        assert result["holdout"] == "right-half"
        psnr[tonemap] = result["psnr"]
    assert psnr[True] >= psnr[False] + 5.0, psnr

    # The learned tones are exported, and `render` shows each view through its own tone.
    run = tonemapped
    params = json.loads((run / "tone_params.json").read_text())
    assert len(params["white_balance"]) == len(varying_scene.names) and params["names"] == varying_scene.names
    with Image.open(run / "tone_params.png") as plot:
        assert plot.format == "PNG" and plot.size[0] > 600
    main(["render", str(run), "--out", str(tmp_path / "r")])
    view = Path(varying_scene.names[varying_scene.test_ids[1]]).stem
    png = read_image(tmp_path / "r" / f"{view}.png").astype(np.float64) / 255
    radiance = read_exr(tmp_path / "r" / f"{view}.exr")
    model = Model.load(run / "model.npz")
    learned = model.tonemapper.learned_radiance(torch.from_numpy(radiance))  # the EXR is linearised
    expected = model.to_ldr(learned, varying_scene.test_ids[1]).numpy()
    assert np.abs(png - expected).max() <= 1 / 255 + 1e-6
    assert np.abs(png - np.clip(radiance, 0, 1)).max() > 0.1  # not just the clipped radiance

    # User controls: +2 EV is brighter than -2 EV; a curve can come from another view or run.
    for ev in ("-2", "2"):
        main(
            [
                "render",
                str(run),
                "--out",
                str(tmp_path / "c"),
                "--ev",
                ev,
                "--crf-from",
                "3",
                "--crf-run",
                str(run),
            ]
        )
    dark = read_image(tmp_path / "c" / f"{view}_ev-2.png").astype(float).mean()
    bright = read_image(tmp_path / "c" / f"{view}_ev+2.png").astype(float).mean()
    assert bright > dark + 20
    # The same curve from the exported tone_params.json gives the same render.
    main(["render", str(run), "--out", str(tmp_path / "j"), "--ev", "2", "--crf-from", "3",
          "--crf-run", str(run / "tone_params.json")])  # fmt: skip
    from_json = read_image(tmp_path / "j" / f"{view}_ev+2.png").astype(int)
    assert np.abs(from_json - read_image(tmp_path / "c" / f"{view}_ev+2.png").astype(int)).max() <= 1
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"white_balance": [[1.0, 1.0, 1.0]]}))
    with pytest.raises(SystemExit) as bad_json:
        main(["render", str(run), "--out", str(tmp_path / "y"), "--ev", "1", "--crf-run", str(broken)])
    assert bad_json.value.code == 2 and not (tmp_path / "y").exists()
    with pytest.raises(SystemExit) as plain_run:  # a run without learned tones cannot be controlled
        main(["render", str(tmp_path / "False"), "--out", str(tmp_path / "x"), "--ev", "1"])
    assert plain_run.value.code == 2


def test_a_view_seen_through_another_views_tone_is_what_that_camera_would_have_taken(
    varying_scene, tonemapped
):
    """Re-exposure (`experiments.reexposure`): training views rendered through the learned tone of views
    exposed 6 stops apart match the truth through those views' true cameras nearly as well as through
    their own, where ignoring the tone (a view's own picture against the other camera's) is far off."""
    data = varying_scene.source.parent if varying_scene.source.is_file() else varying_scene.source
    model = Model.load(tonemapped / "model.npz")
    cameras = camera_settings(data)
    train = list(varying_scene.train_ids)[:8]
    pairs = [(i, j) for i in train for j in train if abs(cameras[i].ev - cameras[j].ev) == 6.0]
    assert pairs
    own = np.mean([r.psnr for r in reexposure(model, data, [(i, i) for i, _ in pairs])])
    across = reexposure(model, data, pairs)
    assert all(abs(r.stops) == 6.0 for r in across)
    mean = float(np.mean([r.psnr for r in across]))
    assert mean > 28.0 and mean > own - 9.0, (mean, own)
    i, j = pairs[0]
    target = reexposure_target(data, i, cameras[j])
    ignored = float(psnr(model.to_ldr(model.render_camera(i), i), target))  # its own tone, not j's
    assert ignored < mean - 10.0, (ignored, mean)


def test_known_exposures_linearise_the_model(varying_scene, tmp_path, capsys):
    """With the generator's EVs given, the fitted exponent turns learned exposures into true stops, and
    the run says how far its EVs ended from the given ones."""
    from hdrplenoxels.eval.truth import SynthTruth, truth_report

    truth_file = varying_scene.source.parent / "camera_truth.json"
    with pytest.raises(SystemExit) as no_tonemap:
        main(
            [
                "train",
                str(varying_scene.source),
                "--out",
                str(tmp_path / "x"),
                "--known-exposure",
                str(truth_file),
                "--no-tonemap",  # known exposures act through the tone mapper: refused without it
            ]
        )
    assert no_tonemap.value.code == 2
    # without --tonemap: known exposures turn the tone mapper on
    main(["train", str(varying_scene.source), "--out", str(tmp_path / "k"), "--quiet",
          "--iters", "200", "--known-exposure", str(truth_file)])  # fmt: skip
    model = Model.load(tmp_path / "k" / "model.npz")
    assert model.tonemapper.cfg.known_exposure and 0.2 < float(model.tonemapper.exponent) < 0.95
    views = json.loads(truth_file.read_text())["views"]
    true_ev = np.array([views[int(Path(n).stem.split("_")[1])]["ev"] for n in model.names])
    learned = (model.tonemapper.linear_log_wb().mean(1) / np.log(2.0)).numpy()
    error = (learned - learned.mean()) - (true_ev - true_ev.mean())
    said = re.search(
        r"fitted to the known exposures \(a = [0-9.]+;[^)]* the learned EVs ([0-9.]+) stop RMS",
        capsys.readouterr().out,
    )
    assert said and abs(float(said.group(1)) - np.sqrt(np.mean(error**2))) < 0.006
    report = truth_report(model, SynthTruth.load(varying_scene.source))
    assert report["exponent_a"] == pytest.approx(1.0, abs=0.02)  # learned EVs are true stops again
