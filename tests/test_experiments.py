"""`hdrplenoxels experiment` / `demo`: a tiny run writes the documented report, and a rerun reuses it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrplenoxels.cli.main import main
from hdrplenoxels.eval.metrics import lpips_available
from hdrplenoxels.experiments import EXPERIMENTS
from hdrplenoxels.experiments.median_exposure import unclipped_fraction
from hdrplenoxels.experiments.table_s1 import by_capture_ev
from hdrplenoxels.train.model import Model

TINY = ["--views", "8", "--resolution", "64x32", "--spp", "2", "--iters", "40"]


def test_list_names_every_experiment(capsys):
    main(["experiment", "--list"])
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == list(EXPERIMENTS)
    assert {"table-s1", "median-exposure", "truth-recovery", "robustness", "crf-transfer"} <= set(listed)


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
    images = ("right_half_vs_truth.png", "ev_sweep.png", "test_view_radiance.exr", "demo_test_view.png")
    for image in (*images, "flythrough.mp4"):
        assert (out / "images" / image).stat().st_size > 0 and image in md
    assert (out / "runs/demo/ours_varying/camera_params.png").exists()

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
    assert not plain["tonemap"]["saturation_weighting"]
    # Its renders are not the experiments' (other views, other capture seed).
    (root,) = (out / "data").glob("demo_validation_*_seed7")
    assert len(json.loads((root / "varying" / "camera_truth.json").read_text())["views"]) == 8


@pytest.mark.parametrize(
    "args, problem",
    [
        (["validation", "--variant", "no_such_setting=1"], "no_such_setting"),
        (["validation", "--variant", "lambda_crf_loglog=big"], "number"),
        (["table-s1", "--variant", "lambda_crf_loglog=1"], "validation"),
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
