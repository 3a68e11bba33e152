"""The tone controller (docs/method.md, "Tone controller"): meter readings, fitting and choosing a
form, persistence with the model, and `render --tone auto|mean|view N`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hdrplenoxels.cli.main import main
from hdrplenoxels.cli.runs import EVAL_TONES
from hdrplenoxels.data.image_io import read_image
from hdrplenoxels.eval.evaluate import TONES, colour_corrected
from hdrplenoxels.tonemap.controller import (
    FORMS,
    ExposureTracker,
    ToneController,
    choose_form,
    fit,
    leave_one_out_error,
    meter,
)
from hdrplenoxels.train.model import MODEL_FILE, Model


def scene_image(seed: int, size=(24, 32)) -> torch.Tensor:
    """A linear image with a bright centre or a bright rim (so whole and centre-weighted meters differ),
    a random overall level over 6 stops and a random colour cast."""
    g = torch.Generator().manual_seed(seed)
    h, w = size
    rows = torch.linspace(-1, 1, h)[:, None]
    cols = torch.linspace(-1, 1, w)[None, :]
    r2 = rows**2 + cols**2
    shape = torch.exp(-r2) if seed % 2 else 0.2 + r2
    level = 2.0 ** (torch.rand(1, generator=g) * 6 - 3)
    cast = torch.exp(0.4 * torch.randn(3, generator=g))
    texture = 1.0 + 0.3 * torch.rand(h, w, 1, generator=g)
    return level * shape[..., None] * texture * cast


def auto_tone(img: torch.Tensor) -> np.ndarray:
    """A made-up phone camera: exposure brings the log-mean luminance to -2.5 stops; white balance removes
    70 % of the grey-world cast, with a blue bias."""
    r = meter(img)
    return (-2.5 - r.log2["meter"]) + (-0.7 * np.asarray(r.grey) + np.array([0.0, -0.05, 0.05]))


def test_meter_reads_a_flat_image_and_its_cast():
    flat = torch.full((10, 12, 3), 0.25)
    r = meter(flat)
    assert all(v == pytest.approx(-2.0, abs=1e-5) for v in r.log2.values())  # every mean of a flat image
    assert np.allclose(r.grey, 0.0, atol=1e-6)
    tinted = flat * torch.tensor([2.0, 1.0, 1.0])
    assert np.allclose(meter(tinted).grey, np.array([2, -1, -1]) / 3, atol=1e-5)
    bright_centre = flat.clone()
    bright_centre[3:7, 4:8] = 4.0
    lit = meter(bright_centre).log2
    assert lit["centre"] > lit["meter"] and lit["centre-average@1"] > lit["average@1"]  # centre-weighted
    assert lit["average@1"] > lit["meter"]  # an average counts the highlights fully, a geometric mean less


def test_the_controller_recovers_a_metering_rule_it_was_fitted_on():
    train = [scene_image(s) for s in range(12)]
    readings = [meter(x) for x in train]
    stops = np.stack([auto_tone(x) for x in train])
    form, errors = choose_form(readings, stops)
    assert form == "meter+grey" and errors["meter+grey"] < 0.01 < errors["mean"]
    controller = fit(form, readings, stops)
    for s in range(100, 106):  # unseen images
        img = scene_image(s)
        assert np.allclose(controller.predict_stops(meter(img)), auto_tone(img), atol=0.02)
        gains = controller.log_gains(img)  # natural log, for the response curve's input
        expected = torch.tensor(auto_tone(img) * math.log(2.0), dtype=torch.float32)
        assert torch.allclose(gains, expected, atol=0.02)


def test_a_tone_that_ignores_the_scene_is_best_predicted_by_the_mean():
    train = [scene_image(s) for s in range(10)]
    readings = [meter(x) for x in train]
    stops = np.tile([0.3, -0.1, 0.2], (10, 1)) + 0.01 * np.random.default_rng(0).standard_normal((10, 3))
    form, errors = choose_form(readings, stops)
    assert errors["mean"] <= min(errors.values()) + 0.005
    assert leave_one_out_error("mean", readings, stops) == pytest.approx(errors["mean"])
    assert choose_form(readings[:3], stops[:3]) == ("mean", {})  # too few views to fit a meter


def test_state_arrays_round_trip_and_bad_ones_are_refused():
    c = ToneController("centre+grey", (0.5, -0.9), (0.1, 0.0, -0.1, -0.6))
    assert ToneController.from_state_arrays(c.state_arrays()) == c
    bad = c.state_arrays() | {"form": np.array("spot")}
    with pytest.raises(ValueError, match="malformed"):
        ToneController.from_state_arrays(bad)


@pytest.fixture
def model(tonemapped_run) -> Model:
    return Model.load(tonemapped_run / MODEL_FILE)


def test_training_with_tone_mapping_fits_and_saves_a_controller(model):
    assert model.controller is not None and model.controller.form in FORMS


def test_auto_tone_exposes_a_dark_and_a_bright_view_alike(model):
    """With the controller of a camera that meters, a brighter radiance gets less exposure (16x: 4 stops
    less): the auto-exposed pictures match where the mean tone's differ."""
    model.controller = ToneController("meter", (-2.5, -1.0), (0.0, 0.0, 0.0, 0.0))
    radiance = model.render_camera(0)
    dark, bright = radiance * 0.25, radiance * 4.0
    auto = [model.to_ldr_controlled(r, tone=model.auto_tone()).mean() for r in (dark, bright)]
    mean = [model.to_ldr_controlled(r).mean() for r in (dark, bright)]
    assert abs(auto[1] - auto[0]) < 0.02 < mean[1] - mean[0]
    linear = model.hdr(radiance)  # the controller meters linear radiance
    gains = [model.controller.log_gains(linear * k) for k in (0.25, 4.0)]
    assert torch.allclose(gains[0] - gains[1], torch.full((3,), 4 * math.log(2.0)), atol=1e-3)


def test_render_tone_choices(tonemapped_run, tmp_path, capsys):
    """Each choice writes its own file names into one folder (none overwrites the views' own renders), and
    each picture is the one its tone gives; the flag's old name, --camera, still chooses."""
    run, out = str(tonemapped_run), tmp_path / "renders"
    for choice in (["--tone", "auto"], ["--camera", "mean"], ["--tone", "view 1"], ["--tone", "own"]):
        main(["render", run, *choice, "--out", str(out)])
    model = Model.load(tonemapped_run / MODEL_FILE)
    stems = [Path(model.names[i]).stem for i in model.test_ids]
    for suffix in ("", "_auto", "_ev+0", "_view1"):
        assert all((out / f"{s}{suffix}.png").is_file() for s in stems)
    assert len(list(out.glob("*.png"))) == 4 * len(stems)
    first = model.test_ids[0]
    radiance = model.render_camera(first)
    pictures = {
        "_view1": model.to_ldr(radiance, 1),
        "": model.to_ldr(radiance, first),
        "_ev+0": model.to_ldr_controlled(radiance),
        "_auto": model.to_ldr_controlled(radiance, tone=model.auto_tone()),
    }
    for suffix, picture in pictures.items():
        expected = (picture.numpy() * 255 + 0.5).astype(np.uint8)
        written = read_image(out / f"{stems[0]}{suffix}.png").astype(int)
        assert np.abs(written - expected).max() <= 1, suffix
    with pytest.raises(SystemExit):
        main(["render", run, "--tone", "sideways"])
    assert "use own, auto, mean or view N" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # eval's word: one vocabulary, each command saying which it takes
        main(["render", run, "--tone", "cc"])
    assert "render has no use for 'cc': use own, auto, mean or view N" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", run, "--tone", "view 1", "--crf-from", "2"])
    assert "whole tone" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", run, "--tone", "auto", "--camera", "mean"])
    assert "--camera is the old name of --tone" in capsys.readouterr().err


def test_a_model_without_a_controller_renders_with_the_mean_tone_only(tonemapped_run, tmp_path, capsys):
    old = tmp_path / "old"
    old.mkdir()
    model = Model.load(tonemapped_run / MODEL_FILE)
    model.controller = None
    model.save(old / MODEL_FILE)
    assert Model.load(old / MODEL_FILE).controller is None
    main(["render", str(old), "--tone", "mean", "--out", str(tmp_path / "mean")])
    assert list((tmp_path / "mean").glob("*_ev+0.png"))
    with pytest.raises(SystemExit) as stop:
        main(["render", str(old), "--tone", "auto"])
    assert stop.value.code == 2 and "no tone controller" in capsys.readouterr().err
    assert not (old / "renders").exists()  # refused before anything was written


def test_a_video_tone_settles_towards_the_controller_over_frames():
    """The tracker starts at the first frame's prediction and closes the same fraction of the gap each
    frame after a cut to a 16x brighter view (4 stops less exposure predicted)."""
    controller = ToneController("meter", (-2.5, -1.0), (0.0, 0.0, 0.0, 0.0))
    tracker = ExposureTracker(controller, fps=30.0, seconds=0.3)
    dim, bright = torch.full((8, 8, 3), 0.1), torch.full((8, 8, 3), 1.6)
    first = tracker(dim)
    assert torch.allclose(first, controller.log_gains(dim))
    gaps = [float((tracker(bright) - controller.log_gains(bright))[0]) for _ in range(30)]
    start = 4 * math.log(2.0)
    assert gaps[0] == pytest.approx(start * (1 - tracker.rate), rel=1e-4)
    assert all(b < a for a, b in zip(gaps, gaps[1:])) and gaps[-1] < 0.05 * start  # settled within 1 s
    assert ExposureTracker(controller, fps=30.0, seconds=0.0).rate == 1.0  # no settling: every frame its own


def test_render_video_with_the_auto_tone(tonemapped_run, tmp_path):
    """`render --video --tone auto`: an orbit whose frames are exposed by the tracker; a view's tone
    renders its frames through that view's gains."""
    import av

    args = ["--frames", "3", "--resolution", "48x40", "--fps", "8"]
    for tone in ("auto", "view 1", "mean"):
        out = tmp_path / f"{tone.replace(' ', '')}.mp4"
        main(["render", str(tonemapped_run), "--video", str(out), *args, "--tone", tone])
        with av.open(str(out)) as container:
            assert len(list(container.decode(video=0))) == 3


def test_colour_correction_leaves_a_matching_render_and_undoes_an_affine_cast():
    g = torch.Generator().manual_seed(3)
    photo = torch.rand(12, 10, 3, generator=g) * 0.8 + 0.1
    assert torch.allclose(colour_corrected(photo, photo), photo, atol=1e-5)  # cc PSNR = plain PSNR
    matrix = torch.tensor([[0.7, 0.1, 0.0], [0.05, 0.9, 0.1], [0.0, 0.2, 0.6]])
    cast = (photo.reshape(-1, 3) @ matrix.T + torch.tensor([0.05, -0.02, 0.03])).reshape(photo.shape)
    assert torch.allclose(colour_corrected(cast, photo), photo, atol=1e-4)


def test_eval_scores_test_views_through_each_tone(tonemapped_run, tmp_path, capsys):
    """`eval --tone own|auto|mean|cc --json`: psnr/ssim at the top, the tone named (--camera, the flag's
    old name, still chooses); correcting the mean tone's colours can only bring the picture closer to
    the photo."""
    results = {}
    for tone, flag in (("own", "--tone"), ("auto", "--tone"), ("mean", "--tone"), ("cc", "--camera")):
        path = tmp_path / f"{tone}.json"
        main(["eval", str(tonemapped_run), flag, tone, "--no-lpips", "--json", str(path)])
        results[tone] = json.loads(path.read_text())
        assert results[tone]["tone"] == tone and {"psnr", "ssim"} <= results[tone].keys()
    assert results["cc"]["psnr"] >= results["mean"]["psnr"]
    assert "colour-corrected" in results["cc"]["tone_protocol"]
    assert tuple(TONES) == EVAL_TONES  # the command line offers every tone `evaluate` knows, no other
    with pytest.raises(SystemExit):
        main(["eval", str(tonemapped_run), "--tone", "view 1", "--no-lpips"])
    assert "eval has no use for 'view N': use own, auto, mean or cc" in capsys.readouterr().err


def test_the_viewers_auto_exposure_follows_the_controller(model):
    """The viewer's `auto` control: pictures exposed by the controller's tone, EV relative to it."""
    from hdrplenoxels.viewer.display import ViewState, display_image, linear_exposed

    model.controller = ToneController("meter", (-2.5, -1.0), (0.0, 0.0, 0.0, 0.0))
    radiance = model.render_camera(0)
    dark, bright = radiance * 0.25, radiance * 4.0
    auto = [display_image(model, r, ViewState(auto=True)).mean() for r in (dark, bright)]
    plain = [display_image(model, r, ViewState()).mean() for r in (dark, bright)]
    assert abs(auto[1] - auto[0]) < 3 < plain[1] - plain[0]  # 8-bit pictures
    up = linear_exposed(model, dark, ViewState(auto=True, ev=1.0))
    assert torch.allclose(up, 2 * linear_exposed(model, dark, ViewState(auto=True)), rtol=1e-5)


def test_an_average_meter_in_another_gauge_is_found_by_its_power():
    """A camera that averages the luminance of radiance which the model holds to the power 1/1.4 (a gauge
    it cannot know): the power mean with g = 1.4 is the form left-out views choose."""
    train = [scene_image(s) for s in range(12)]
    truth = []
    for img in train:
        lum = (img * torch.tensor([0.2126, 0.7152, 0.0722])).sum(-1) ** 1.4  # the camera's linear light
        truth.append(np.full(3, -2.5 - math.log2(float(lum.mean())) / 1.4))
    form, errors = choose_form([meter(x) for x in train], np.stack(truth))
    assert form == "average@1.4" and errors[form] < 0.005 < errors["meter"] / 5


def test_the_mean_tone_of_a_full_holdout_run_is_the_trained_views_mean(model):
    """With --holdout full the test views never trained their tones: the mean tone leaves them out."""
    learned = model.tonemapper.linear_log_wb()
    model.tonemapper.log_wb.data[model.test_ids] += 3.0  # untrained tones, far off
    assert torch.allclose(model.mean_log_wb(), model.tonemapper.linear_log_wb().mean(0))
    model.config["holdout"] = "full"
    assert torch.allclose(model.mean_log_wb(), learned[model.train_ids].mean(0), atol=1e-6)
