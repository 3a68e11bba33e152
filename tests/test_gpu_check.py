"""`make gpu-check` (benchmarks/gpu_check.py): a clear no-op without CUDA, and its driver's summary."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "gpu_check.py"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_without_cuda_it_says_so_and_exits_0(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "no CUDA device" in proc.stdout
    assert not out.exists()  # nothing measured, nothing written


def test_sections_run_in_their_own_processes_and_are_summarised(tmp_path):
    """The plumbing on the CPU: four sections, both summaries written, their figures in the markdown."""
    out = tmp_path / "out"
    args = ["--out", str(out), "--device", "cpu", "--demo-data", str(tmp_path), "--sections", "env",
            "lanes", "kernels", "fused", "--lanes", "0", "--spike-rays", "64", "--render-rays", "32", "96",
            "--repeats", "1", "--limit-scale", "5"]  # fmt: skip
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((out / "gpu_check.json").read_text())
    assert [report["sections"][s]["status"] for s in ("env", "lanes")] == ["ok", "ok"]
    assert report["sections"]["env"]["result"]["torch"] == torch.__version__
    assert report["sections"]["env"]["result"]["disk_write_mb_per_s"] > 0
    assert report["sections"]["lanes"]["result"]["lanes_0_train_rays_per_s"] > 0
    summary = (out / "gpu_check.md").read_text()
    assert "Lanes per ray (spike, 64 rays" in summary and "| lanes | ok |" in summary
    assert "96 rays" in summary and report["sections"]["lanes"]["result"]["render_96_lanes_32_rays_per_s"] > 0
    kernels = report["sections"]["kernels"]["result"]
    assert kernels["specialised_train_rays_per_s"] > 0 and kernels["registers_64_render_rays_per_s"] > 0
    assert "Kernel variants (spike; rays/s of 64-ray forward + backward and of a 96-ray forward" in summary
    fused = report["sections"]["fused"]["result"]
    assert fused["tone_loss_torch_64_ms"] > 0 and fused["ray_draw_kernel_100000_ms"] > 0
    assert "Fused kernels against PyTorch's operators" in summary
    assert "- tone_loss, 100000 rays, launched: torch" in summary and "- ray_draw, 64 rays" in summary


def test_a_section_past_its_limit_is_stopped_and_reported(tmp_path):
    out = tmp_path / "out"
    args = ["--out", str(out), "--device", "cpu", "--demo-data", str(tmp_path), "--sections", "lanes",
            "--limit-scale", "0.005"]  # fmt: skip
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True)
    assert proc.returncode == 1  # not every section ok
    report = json.loads((out / "gpu_check.json").read_text())
    assert report["sections"]["lanes"]["status"] == "timeout"
    assert "| lanes | timeout |" in (out / "gpu_check.md").read_text()


def _gpu_check_module():
    spec = importlib.util.spec_from_file_location("gpu_check", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_parity_results_and_the_headline_figures_are_read_from_their_files(tmp_path):
    gc = _gpu_check_module()
    xml = tmp_path / "parity.xml"
    xml.write_text(
        '<testsuites><testsuite tests="3" failures="1" errors="0" skipped="1" time="2.5">'
        '<testcase classname="t" name="a"/>'
        '<testcase classname="t" name="b"><failure message="boom&#10;more"/></testcase>'
        '<testcase classname="t" name="c"><skipped/></testcase></testsuite></testsuites>'
    )
    parity = gc.parse_junit(xml)
    assert parity["tests"] == 3 and parity["failures"] == 1 and parity["failed"] == ["t::b: boom"]
    rates = {"train_rays_per_s": 2e6, "step_rays_per_s": 1e6, "render_rays_per_s": 4e6}
    report = {
        "sections": {
            "parity": {"result": parity},
            "bench": {"result": {"results": {"spike": {"warp": rates}}, "training_runs": {}}},
            "reference": {"result": {"results": {"spike": {"torch": {"train_rays_per_s": 2e4}}}}},
            "viewer": {"result": {"size": [800, 800], "frame_ms": 25.0, "fps": 40.0}},
            "balanced": {"result": {"seconds": 20.0, "psnr_right_halves": 30.0}},
            "graph": {"result": {"seconds": 7.5, "psnr_right_halves": 30.1, "graph_captures": 3}},
            "capture": {
                "result": {
                    "seconds": 12.5,
                    "steps_seconds": 9.0,
                    "psnr_right_halves": 23.4,
                    "capture": "asclepius",
                }
            },
        }
    }
    rows = {figure: (measured, target) for figure, measured, target in gc.headline(report)}
    assert rows["parity tests on CUDA"] == ("1 passed, 1 failed, 1 skipped", "all pass")
    assert rows["spike 128³ train rays/s, 5000 rays"][0] == "2.00 M (100x the reference)"
    assert rows["viewer frame 800x800"] == ("25.0 ms (40.0 fps)", "≥ 30 fps")
    assert rows["`balanced` on the demo scene (tone mapping), each kernel launched (`cuda_graph=false`)"] == (
        "20.0 s, 30.00 dB right halves",
        "",
    )
    graph = rows["the same from a CUDA graph (`cuda_graph`, the default)"]
    assert graph == ("7.5 s, 30.10 dB right halves; 3 captures", "≤ 8 s")
    capture = rows["`balanced` on asclepius (a real capture, tone mapping, from the graph)"]
    assert capture == ("12.5 s (9.0 s of steps), 23.40 dB right halves", "≤ 15 s")
    report["sections"]["graph"]["result"]["graph_failure"] = "RuntimeError: no"
    rows = {figure: measured for figure, measured, _ in gc.headline(report)}
    assert rows["the same from a CUDA graph (`cuda_graph`, the default)"].endswith(
        "capture failed: RuntimeError: no"
    )


def test_the_levels_profile_is_summarised_per_run():
    gc = _gpu_check_module()
    top = [{"name": "render_forward_lanes_cuda_kernel_forward", "ms": 0.75, "calls": 1.0}]
    level = {"level": 0, "reso": [8, 8, 8], "voxels": 512, "wall_ms": 1.5, "kernel_ms": 1.0, "top": top}
    level |= {"view_prior": True}
    run = {"device": "NVIDIA H200", "graph": False, "graph_failure": None, "steps": 6, "levels": [level]}
    run |= {"view_prior_update": "auto"}
    sections = {
        "levels": {
            "status": "ok",
            "seconds": 1.0,
            "result": {"launched": run, "graph-dense": run | {"graph": True, "view_prior_update": "dense"}},
        }
    }
    summary = gc.markdown({"date": "d", "command": "c", "seconds": 1.0, "sections": sections})
    assert "steps launched from the host" in summary and "steps from a CUDA graph" in summary
    assert summary.count("level 0 (8x8x8, 512 voxels, view prior on): 1.50 ms a step, kernels 1.00 ms") == 2
    assert "the view prior's pull dense" in summary and "the view prior's pull auto" in summary
    assert "0.750    1.0x  render_forward_lanes_cuda_kernel_forward" in summary


def test_the_step_variants_and_ncu_counters_are_summarised():
    gc = _gpu_check_module()
    runs = {
        "default@5000": {
            "ms": 1.25,
            "train_rays_per_s": 4.0e6,
            "first_steps_s": 3.0,
            "max_image_difference": 0.0,
        },
        "rays-4x8@5000": {"error": "RuntimeError: no"},
    }
    launch = {
        "kernel": "render_backward_lanes",
        "duration": 1234.5,
        "registers": 168,
        "achieved_occupancy": 17.2,
    }
    launch |= {"stalls": {"long_scoreboard": 3.1, "barrier": 2.0, "wait": 1.0, "math": 0.5}}
    sections = {
        "step": {"status": "timeout", "seconds": 150.0, "result": {"reso": 128, "graph": True, "runs": runs}},
        "ncu": {
            "status": "ok",
            "seconds": 80.0,
            "result": {"problem": "spike", "rays": 5000, "launches": [launch]},
        },
    }
    summary = gc.markdown({"date": "d", "command": "c", "seconds": 1.0, "sections": sections})
    assert "The spike step (128³) from the CUDA graph" in summary  # kept though the section timed out
    assert "| default@5000 | 1.250 | 4.00 M | 0.0e+00 |" in summary
    assert "| rays-4x8@5000 | failed: RuntimeError: no | | |" in summary
    assert (
        "| render_backward_lanes | 1234.5 | 168 | 17 % | long_scoreboard 3.1, barrier 2.0, wait 1.0 |"
        in summary
    )


def test_the_capture_section_runs_only_with_its_data(tmp_path):
    gc = _gpu_check_module()
    assert "capture" not in gc.parse_args(["--out", str(tmp_path)]).sections  # the default, without data
    kit = tmp_path / "asclepius"
    args = gc.parse_args(["--out", str(tmp_path), "--capture-data", str(kit)])
    assert "capture" in args.sections and args.argv[-2:] == ["--capture-data", str(kit.resolve())]
    with pytest.raises(SystemExit) as exit_:
        gc.parse_args(["--out", str(tmp_path), "--sections", "capture"])
    assert exit_.value.code == 2


def test_the_viewer_shows_the_demo_trained_from_the_graph_or_else_the_launched_one(tmp_path):
    """The GPU call runs `graph` without `balanced`: the viewer section must find that run's model."""
    from hdrplenoxels.train.model import MODEL_FILE

    gc = _gpu_check_module()
    with pytest.raises(FileNotFoundError, match="no trained demo"):
        gc.demo_model(tmp_path)
    for run in (gc.BALANCED_RUN, gc.GRAPH_RUN):
        (tmp_path / run).mkdir()
        (tmp_path / run / MODEL_FILE).write_bytes(b"")
        assert gc.demo_model(tmp_path) == tmp_path / run / MODEL_FILE  # the graph's once it is there
