"""`hdrplenoxels experiment` / `demo`: a tiny run writes the documented report, and a rerun reuses it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hdrplenoxels.cli.main import main
from hdrplenoxels.data.image_io import read_image
from hdrplenoxels.eval.metrics import lpips_available
from hdrplenoxels.experiments import EXPERIMENTS, median, table_s2
from hdrplenoxels.experiments.table_s1 import by_capture_ev
from hdrplenoxels.experiments.table_s2 import unclipped_fraction
from hdrplenoxels.train import runs
from hdrplenoxels.train.model import Model

TINY = ["--views", "8", "--resolution", "64x32", "--spp", "2", "--iters", "40"]


def test_list_names_every_experiment(capsys):
    main(["experiment", "--list"])
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == list(EXPERIMENTS)
    assert {"table-s1", "table-s2", "nerf-tonemap", "truth-recovery", "robustness", "crf-transfer"} <= set(
        listed
    )


def test_unknown_experiment_and_scene_are_refused(tmp_path, capsys):
    for args in (
        ["experiment", "nope", str(tmp_path)],
        ["experiment", "demo", str(tmp_path), "--scenes", "moon"],
    ):
        with pytest.raises(SystemExit) as e:
            main(args)
        assert e.value.code == 2
    assert "moon" in capsys.readouterr().err


def test_demo_writes_report_with_protocol_metrics_truth_and_images(tmp_path, capsys):
    out = tmp_path / "demo"
    main(["demo", "--out", str(out), *TINY])
    assert "report: " in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert "right half" in report["protocol"] and "exponent" in report["truth_protocol"]
    scene = report["scenes"]["demo"]
    keys = {"psnr", "ssim"} | ({"lpips_vgg", "lpips_alex"} if lpips_available() else set())
    for method in ("plenoxels_static", "plenoxels_varying", "ours_varying"):
        assert keys <= set(scene[method])
    assert {"crf_rmse", "ev_error_stops", "hdr_error_stops", "exponent_a"} <= set(
        scene["ours_varying"]["truth"]
    )
    md = (out / "report.md").read_text()
    # the EV sweep says which stops it steps in: the demo's PNGs have no EXIF, so the learned scale
    assert "EV in the learned scale (the photos have no EXIF exposure" in md and "true stops)." in md
    images = ("right_half_vs_truth.png", "ev_sweep.png", "test_view_radiance.exr", "demo_test_view.png")
    for image in (*images, "flythrough.mp4"):
        assert (out / "images" / image).stat().st_size > 0 and image in md
    assert (out / "runs/demo/ours_varying/tone_params.png").exists()
    for image in images[:2] + images[3:]:  # pictures a person can look at: at least 256 px
        assert max(read_image(out / "images" / image).shape[:2]) >= 256, image

    # A rerun reuses the finished runs instead of training again.
    model = out / "runs/demo/ours_varying/model.npz"
    stamp = model.stat().st_mtime_ns
    main(["demo", "--out", str(out), *TINY, "--no-lpips"])
    assert model.stat().st_mtime_ns == stamp

    # table-s1 on the same scene reuses those runs and adds its control: ours on the static captures,
    # scored on the same images as static Plenoxels (no truth block: its exposures never differ).
    main(["experiment", "table-s1", str(out), "--scenes", "demo", *TINY, "--no-lpips"])
    assert model.stat().st_mtime_ns == stamp
    scene = json.loads((out / "report.json").read_text())["scenes"]["demo"]
    assert "psnr" in scene["ours_static"] and "truth" not in scene["ours_static"]
    assert [v["index"] for v in scene["ours_static"]["views"]] == [
        v["index"] for v in scene["plenoxels_static"]["views"]
    ]
    control, static = (
        Model.load(out / "runs/demo" / key / "model.npz") for key in ("ours_static", "plenoxels_static")
    )
    assert control.tonemapper is not None and control.data_path == static.data_path
    assert "ours_static" in (out / "report.md").read_text()
    # Beside the protocol, the tones a new view would get (ours, tone-mapped): the own tone's score is
    # the protocol's, and colour correction can only bring the mean tone's picture closer.
    tones = scene["ours_varying"]["tones"]
    assert set(tones) == {"own", "auto", "mean", "cc"}
    assert tones["own"] == pytest.approx(scene["ours_varying"]["psnr"], abs=1e-4)
    assert tones["cc"] >= tones["mean"] - 1e-6
    assert "plenoxels_static" not in {row.split(" / ")[-1] for row in _tone_rows(out / "report.md")}
    # NeRF-A's column (NeRF-W protocol: test views' embeddings from their left halves).
    assert {"psnr", "ssim"} <= set(scene["nerf_a_varying"])
    nerf_a = json.loads((out / "runs/demo/nerf_a_varying/config.json").read_text())
    assert nerf_a["model"] == "nerf" and nerf_a["nerf"]["appearance"] and nerf_a["holdout"] == "right-half"


def _tone_rows(report: Path) -> list[str]:
    """The row labels of a report's tone table."""
    text = report.read_text()
    section = text.split("### Through the tones a new view would get", 1)[1].split("\n#", 1)[0]
    return [line.split("|")[1].strip() for line in section.splitlines() if line.startswith("| demo")]


def test_unclipped_fraction_counts_lit_pixels_with_no_clipped_channel():
    black, lit, clipped_red = [0, 1, 2], [10, 200, 90], [255, 40, 40]
    image = np.array([[black, lit], [clipped_red, lit]], dtype=np.uint8)
    assert unclipped_fraction([image]) == pytest.approx(2 / 3)  # the black pixel is background
    assert unclipped_fraction([image, np.full((2, 2, 3), 255, np.uint8)]) == pytest.approx(2 / 7)


def test_validation_compares_variants_on_its_own_renders(tmp_path, capsys):
    out = tmp_path / "val"
    args = ["experiment", "validation", str(out), "--scenes", "demo", "--no-lpips", *TINY]
    main([*args, "--variant", "defaults", "--variant", "lambda_crf_loglog=0.01,lambda_sh_view=0"])
    report = json.loads((out / "report.json").read_text())
    assert "seed 7" in report["protocol"] and "right half" in report["protocol"]
    scene = report["scenes"]["demo"]
    assert "psnr" in scene["plenoxels_static"]
    variants = scene["variants"]
    assert list(variants) == ["defaults", "lambda_crf_loglog=0.01,lambda_sh_view=0"]
    for v in variants.values():
        assert {"psnr", "median_psnr", "truth", "minus_static_at_0ev"} <= set(v) and "ev_error_stops" in v[
            "truth"
        ]
        assert sum(g["views"] for g in v["by_capture_ev"].values()) == len(scene["plenoxels_static"]["views"])
    config = json.loads((out / "runs" / "demo" / "variant1" / "varying" / "config.json").read_text())
    assert config["tonemap"]["lambda_crf_loglog"] == 0.01 and config["tonemap"]["lambda_sh_view"] == 0
    median = json.loads((out / "runs" / "demo" / "variant0" / "median" / "config.json").read_text())
    # The median experiment's own settings for a sparse bracket, while the -3/0/+3 EV run keeps the defaults.
    assert median["tonemap"]["lambda_crf_loglog"] == 0.01 and median["tonemap"]["saturation_weighting"]
    plain = json.loads((out / "runs" / "demo" / "variant0" / "varying" / "config.json").read_text())
    assert plain["tonemap"]["lambda_crf_loglog"] == 0.0
    # Its renders are not the experiments' (other views, other capture seed).
    (root,) = (out / "data").glob("demo_validation_*_seed7")
    assert len(json.loads((root / "varying" / "camera_truth.json").read_text())["views"]) == 8


@pytest.mark.parametrize(
    "args, problem",
    [
        (["validation", "--variant", "no_such_setting=1"], "no_such_setting"),
        (["validation", "--variant", "lambda_crf_loglog=big"], "number"),
        (["table-s1", "--variant", "lambda_crf_loglog=1"], "validation"),
        (["table-s2", "--nerf-preset", "fast"], "not a nerf preset"),
        (["nerf-tonemap", "--preset", "nerf-cpu"], "not a grid preset"),
        (["table-s1", "--set", "model=nerf"], "model"),
        (["table-s1", "--set", "nerf.appearance=true"], "nerf.appearance"),
    ],
)
def test_bad_variants_are_refused(args, problem, tmp_path, capsys):
    name, *rest = args
    with pytest.raises(SystemExit) as e:
        main(["experiment", name, str(tmp_path / "out"), *rest])
    assert e.value.code == 2
    assert problem in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_table_s1_groups_ours_and_static_by_the_exposure_of_the_scored_capture(tmp_path):
    (tmp_path / "varying").mkdir()
    views = [
        {"ev": ev, "wb_gains": [1.0, 1.0, 1.0], "crf_curve": [0.0, 1.0], "hdr": f"hdr/{i}.exr"}
        for i, ev in enumerate((-3.0, 0.0, 3.0, -3.0, 3.0))
    ]
    (tmp_path / "varying" / "camera_truth.json").write_text(json.dumps({"views": views}))
    result = {
        "ours_varying": {"views": [{"index": i, "psnr": p} for i, p in ((0, 40.0), (3, 42.0), (2, 30.0))]},
        "plenoxels_static": {"views": [{"index": i, "psnr": 38.0} for i in (0, 3, 2)]},
    }
    groups = by_capture_ev(tmp_path, result)
    assert list(groups) == ["-3", "+3"]  # only the scored (test) views' exposures
    assert groups["-3"] == {"views": 2, "ours": 41.0, "static": 38.0, "difference": 3.0}
    assert groups["+3"]["difference"] == -8.0


# The NeRF experiments' runs: TINY with 20 steps of tiny batches, so that their NeRF runs take seconds.
TINY_NERF = [*TINY[:-1], "20", "--no-lpips", "--set", "optim.batch_size=256"]


@pytest.fixture(scope="module")
def nerf_data(tmp_path_factory):
    """Rendered truth shared by the NeRF experiments' tests (`--data`)."""
    return tmp_path_factory.mktemp("nerf-data")


@pytest.fixture(scope="module")
def table_s2_run(tmp_path_factory, nerf_data):
    """`experiment table-s2` on the tiny demo scene, recording every dataset and HDR truth file read while
    NeRF-A's interpolation weight is being chosen."""
    out = tmp_path_factory.mktemp("s2") / "out"
    reads, choosing = [], []
    real_weight = table_s2.validated_weight

    def spy_weight(*args, **kwargs):
        choosing.append(True)
        try:
            return real_weight(*args, **kwargs)
        finally:
            choosing.pop()

    def recording(fn):
        def wrapped(path, *args, **kwargs):
            if choosing:
                reads.append(Path(path))
            return fn(path, *args, **kwargs)

        return wrapped

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(table_s2, "validated_weight", spy_weight)
        mp.setattr(runs, "load_scene", recording(runs.load_scene))
        mp.setattr(median, "read_exr", recording(median.read_exr))
        mp.setattr(median.SynthTruth, "load", recording(median.SynthTruth.load))
        main(["experiment", "table-s2", str(out), "--scenes", "demo", "--data", str(nerf_data), *TINY_NERF])
    return out, reads


def test_table_s2_scores_ours_plenoxels_nerf_a_and_nerf_tone_at_the_median_exposure(table_s2_run):
    out, _ = table_s2_run
    report = json.loads((out / "report.json").read_text())
    assert report["experiment"] == "table-s2" and "right half" in report["protocol"]
    assert "validation captures" in report["protocol"]
    scene = report["scenes"]["demo"]
    for key in ("ours_median", "plenoxels_median", "nerf_a_median", "nerf_tone_median", table_s2.CEILING):
        assert {"psnr", "ssim"} <= set(scene[key]), key
    assert {"ours_minus_nerf_a_mean_db", "met_nerf_a", "min_psnr"} <= set(report["targets"])
    md = (out / "report.md").read_text()
    assert "nerf_a_median" in md and "NeRF-A's interpolation weight" in md
    assert (out / "images" / "demo_median.png").stat().st_size > 0 and "images/demo_median.png" in md
    for key, appearance, tonemap in (("nerf_a_median", True, False), ("nerf_tone_median", False, True)):
        config = json.loads((out / "runs/demo" / key / "config.json").read_text())
        assert config["model"] == "nerf" and config["preset"] == "nerf-cpu"
        assert config["nerf"]["appearance"] is appearance and config["tonemap"]["enabled"] is tonemap


def test_table_s2_chooses_nerf_a_weight_on_validation_captures_only(table_s2_run, nerf_data):
    out, reads = table_s2_run
    weight = json.loads((out / "report.json").read_text())["scenes"]["demo"]["nerf_a_weight"]
    psnr = weight["validation_psnr"]
    assert list(psnr) == [f"{w:g}" for w in median.WEIGHTS]
    assert psnr[f"{weight['chosen']:g}"] == max(psnr.values())
    # Everything read while choosing (datasets, camera truth, HDR truth) is validation data.
    (validation,) = nerf_data.glob("demo_validation_*_seed7")
    assert any(p.suffix == ".exr" for p in reads) and any(p.name == "varying" for p in reads)
    for path in reads:
        assert path.is_relative_to(validation), path


def test_nerf_tonemap_writes_table_targets_and_image_grid(tmp_path, nerf_data):
    out = tmp_path / "fig-s8"
    main(["experiment", "nerf-tonemap", str(out), "--scenes", "demo", "--data", str(nerf_data), *TINY_NERF])
    report = json.loads((out / "report.json").read_text())
    assert report["experiment"] == "nerf-tonemap" and "right half" in report["protocol"]
    scene = report["scenes"]["demo"]
    assert list(scene) == ["nerf_static", "nerf_varying", "nerf_tone_varying"]
    for values in scene.values():
        assert {"psnr", "ssim"} <= set(values)
    targets = report["targets"]
    assert targets["tone_minus_varying_mean_db"] == pytest.approx(
        scene["nerf_tone_varying"]["psnr"] - scene["nerf_varying"]["psnr"]
    )
    md = (out / "report.md").read_text()
    assert "images/nerf_tonemap.png" in md and "NeRF + tone − NeRF static" in md
    figure = read_image(out / "images" / "nerf_tonemap.png")
    # One row of five right halves (64x32 views: 32 px wide each, 2 px gaps).
    assert figure.shape[:2] == (32, 5 * 32 + 4 * 2)
    for key in scene:
        assert json.loads((out / "runs/demo" / key / "config.json").read_text())["model"] == "nerf"


def test_novel_views_scores_unseen_views_through_each_camera(tmp_path):
    """`experiment novel-views` on a tiny auto-exposure capture: the right-half run and the full-holdout
    run, whose unseen test views are scored through auto, mean, cc and their true tone."""
    out = tmp_path / "novel"
    main(["experiment", "novel-views", str(out), "--scenes", "demo", *TINY])
    report = json.loads((out / "report.json").read_text())
    assert report["experiment"] == "novel-views" and "held out entirely" in report["protocol"]
    scene = report["scenes"]["demo"]
    assert {"right_half", "auto", "mean", "cc", "true", "controller"} <= set(scene)
    assert scene["cc"] >= scene["mean"]  # correcting the mean tone's colours only brings it closer
    (truth_file,) = (out / "data").glob("demo_*/captures/auto/auto/camera_truth.json")
    assert json.loads(truth_file.read_text())["variant"] == "auto"
    configs = [
        json.loads((out / "runs/demo" / f"ours_{h}" / "config.json").read_text())
        for h in ("right-half", "full")
    ]
    assert [c["holdout"] for c in configs] == ["right-half", "full"]
    assert (out / "images" / "demo_novel.png").is_file()
    assert "EV error auto" in (out / "report.md").read_text()
