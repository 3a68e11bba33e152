"""`benchmarks/peers_table.py` (ours and gsplat on the same capture kits): what holds without a GPU.
The runs come in the order that decides the issue's targets first, gsplat at ours' time is timed from
ours' seconds and its own default run, a session continues the last one's results (ours' rows of another
configuration run again) and starts nothing past its deadline, and ours' run trains and scores a kit."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import peers_table  # noqa: E402

TINY_OURS = ["--preset", "fast", "--set", "optim.n_iters=4", "--set", "grid.upsample_every=1000"]  # one level


@pytest.fixture
def kits(tmp_path, tiny_scene_path):
    for capture, photos in (("asclepius", "varying"), ("kermit", "photos"), ("asclepius", "static")):
        shutil.copytree(tiny_scene_path.parent, tmp_path / "kits" / capture / photos)
    return tmp_path / "kits"


def test_the_fixed_and_the_varying_camera_come_first():
    assert peers_table.ORDER[:3] == [("kermit", "photos"), ("asclepius", "static"), ("brickstamp", "static")]
    assert len(peers_table.ORDER) == len(set(peers_table.ORDER)) == 12


def test_gsplat_at_ours_time_makes_the_steps_its_default_run_made_in_that_time():
    assert peers_table.same_time_scaler({"seconds": 60.0}, {"steps": 30_000, "seconds": 600.0}) == 0.1
    assert peers_table.same_time_scaler({"seconds": 900.0}, {"steps": 30_000, "seconds": 600.0}) == 1.0


def test_a_session_continues_the_last_and_stops_at_its_deadline(kits, tmp_path, monkeypatch):
    calls = []

    def ours(kit, cfg, work, sheet, lpips):
        calls.append((kit.parent.name, kit.name, "ours"))
        return {"psnr": 20.0, "ssim": 0.5, "seconds": 30.0, "steps": 3000}

    def gsplat(kit, scaler, seconds, appearance, sheet):
        calls.append((kit.parent.name, kit.name, scaler, seconds, appearance))
        return {"psnr": 19.0, "ssim": 0.5, "seconds": 300.0, "steps": 30_000}

    monkeypatch.setattr(peers_table, "run_ours", ours)
    monkeypatch.setattr(peers_table, "run_gsplat", gsplat)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "GPU")
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: None)
    out = tmp_path / "out"
    assert peers_table.main(["--kits", str(kits), "--out", str(out), "--sets", "photos", "static"]) == 0
    assert calls == [
        ("kermit", "photos", "ours"),
        ("kermit", "photos", 1.0, None, False),
        ("kermit", "photos", 0.1, 30.0, False),  # 30 s of ours at gsplat's 100 steps a second
        ("asclepius", "static", "ours"),
        ("asclepius", "static", 1.0, None, False),
        ("asclepius", "static", 0.1, 30.0, False),
    ]
    first = json.loads((out / "results.json").read_text())
    assert (
        len(first["rows"]) == 6
        and "| kermit | photos | gsplat-same-time | 19.00 |" in (out / "results.md").read_text()
    )
    calls.clear()  # the next session: the varying kit is new, and ours is trained with another setting
    argv = ["--kits", str(kits), "--out", str(tmp_path / "next"), "--results", str(out / "results.json")]
    assert peers_table.main([*argv, "--set", "optim.n_iters=2000"]) == 0
    assert calls[:2] == [
        ("kermit", "photos", "ours"),
        ("kermit", "photos", 0.1, 30.0, False),
    ]  # gsplat's own kept
    assert ("asclepius", "varying", 1.0, None, True) in calls  # the exposure compensation on varying photos
    assert len(json.loads((tmp_path / "next" / "results.json").read_text())["rows"]) == 9
    calls.clear()
    assert peers_table.main([*argv, "--deadline", "-1"]) == 0
    assert calls == []


def test_ours_trains_and_scores_a_kit_and_draws_its_sheet(kits, tmp_path):
    out = tmp_path / "out"
    argv = ["--kits", str(kits), "--out", str(out), "--work", str(tmp_path / "work"), "--sets", "photos"]
    assert peers_table.main([*argv, *TINY_OURS, "--device", "cpu", "--no-lpips"]) == 0  # halves too small
    (row,) = json.loads((out / "results.json").read_text())["rows"]
    assert row["method"] == "ours" and row["steps"] == 4 and row["test_views"] == 2
    assert 0 < row["psnr"] < 60 and row["seconds"] >= row["steps_seconds"] > 0
    assert (out / "sheets" / "kermit-photos-ours.png").stat().st_size > 0
