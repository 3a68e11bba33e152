"""`benchmarks/device_kit.py` (what the GPU work carries to a device machine, and the calls that carry
it): the calls carry Warp's parts one a call and the rest with the last, within a call's 64 MiB and
2 000 characters, refuse what is not built or too large, and run commands the scripts accept today."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import device_kit  # noqa: E402
import gpu_check  # noqa: E402
import gpu_preset  # noqa: E402
import march_stages  # noqa: E402
import ncu_march  # noqa: E402
import prior_update  # noqa: E402

TESTS = Path(__file__).resolve().parent


@pytest.fixture
def built(tmp_path, monkeypatch) -> Path:
    """A stand-in `.gpu/` with every part present and small."""
    kit = tmp_path / ".gpu"
    for part in ("aa", "ab", "ac"):
        (kit / "parts").mkdir(parents=True, exist_ok=True)
        (kit / "parts" / f"warp.part.{part}").write_bytes(b"w" * 1024)
    (kit / "WHEEL_NAME").write_text("warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl\n")
    for folder in ("wheels", "demo", "capture/asclepius", "preset/kermit/x1", "peers/a", "peers/b"):
        (kit / folder).mkdir(parents=True)
        (kit / folder / "f").write_bytes(b"x" * 1024)
    monkeypatch.setattr(device_kit, "ROOT", tmp_path)
    monkeypatch.setattr(device_kit, "KIT", kit)
    monkeypatch.setattr(device_kit, "tree_mib", lambda: 5.6)
    return kit


def test_each_session_installs_first_then_carries_its_data_within_a_calls_limits(built):
    first, second, third = device_kit.sessions(svox2=False)
    for calls, data in ((first, 2), (second, 1), (third, 0)):
        assert [c.carry for c in calls[:2]] == [(".gpu/parts/warp.part.aa",), (".gpu/parts/warp.part.ab",)]
        assert calls[2].carry[:3] == (".gpu/parts/warp.part.ac", ".gpu/wheels", ".gpu/WHEEL_NAME")
        assert len(calls[2].carry) == 3 + data
        assert "pip install" in calls[2].command
        assert all("pip install" not in c.command for c in calls[3:])
        assert all(5.6 <= device_kit.check(c) < device_kit.CALL_MIB for c in calls)
    # the GPU issue's script first (at most 6 minutes), then its winners again (at most 3)
    assert "gpu_check.py" in first[2].command and ".gpu/capture" in first[2].carry
    assert first[2].timeout_s <= 420 and "cp $OUT/gpu_check.json /tmp/gpu_check.json" in first[2].command
    assert "graph_step.py --again /tmp/gpu_check.json" in first[3].command and first[3].timeout_s <= 180
    assert [c.carry[-1] for c in second[2:]] == [".gpu/demo", ".gpu/peers/a", ".gpu/peers/b"]
    assert len(third) == 4 and "ncu_march.py" in third[2].command
    assert "gpu_preset.py run" in third[3].command and third[3].carry == (".gpu/preset",)
    (built / "svox2").mkdir()
    fourth = device_kit.sessions(svox2=True)[3]
    assert "svox2_peer.py" in fourth[2].command and fourth[2].carry[-1] == ".gpu/svox2"
    for calls in (first, second, third, fourth):
        assert device_kit.session_s(calls) <= device_kit.SESSION_S


def test_a_call_that_carries_what_is_missing_or_too_much_is_refused(built):
    first, second, _ = device_kit.sessions(svox2=False)
    with open(built / "peers" / "b" / "big", "wb") as f:
        f.truncate(60 * 2**20)  # sparse: its size is what a call would carry
    with pytest.raises(ValueError, match="over 64"):
        device_kit.check(second[-1])
    (built / "demo" / "f").unlink()
    (built / "demo").rmdir()
    with pytest.raises(ValueError, match=r"\.gpu/demo, which is not built"):
        device_kit.check(first[2])


def test_the_calls_run_what_the_scripts_accept_today(built):
    """The printed calls would otherwise rot as the scripts change: each script's own parser takes them,
    every parity file exists, every candidate is defined."""
    first, _, third = device_kit.sessions(svox2=False)
    check = shlex.split(first[2].command.split(" && ")[-1].split("; ")[0])
    assert check[:2] == ["python3", "benchmarks/gpu_check.py"]
    args = gpu_check.parse_args([os.path.expandvars(a) for a in check[2:]])
    assert all((TESTS / f).exists() for f in args.parity_files)
    assert (
        args.sections[:3] == ["env", "parity", "step"] and "capture" in args.sections and args.deadline <= 360
    )
    again = shlex.split(first[3].command.split(" && ")[-1])
    assert again[:2] == ["python3", "benchmarks/graph_step.py"]
    preset = shlex.split(third[3].command.split(" && ")[-1])
    assert preset[:3] == ["python3", "benchmarks/gpu_preset.py", "run"]
    candidates = preset[preset.index("--candidates") + 1 : preset.index("--deadline")]
    assert candidates and set(candidates) <= set(gpu_preset.CANDIDATES)
    assert Path(preset[preset.index("--results") + 1]).name == "gpu_preset_results.json"
    assert (TESTS.parent / "benchmarks" / "gpu_preset_results.json").exists()
    *stages, prior, profile = (shlex.split(c) for c in third[2].command.split(" && ")[-1].split("; "))
    assert [s[:2] for s in stages] == [["python3", "benchmarks/march_stages.py"]] * 2
    assert prior[:2] == ["python3", "benchmarks/prior_update.py"]
    assert prior_update.parse_args([os.path.expandvars(a) for a in prior[2:]]).rows == 23_000_000
    assert [march_stages.parse_args(s[2:]).problem for s in stages] == ["spike", "paper"]
    assert profile[:2] == ["python3", "benchmarks/ncu_march.py"]
    assert ncu_march.parse_args([os.path.expandvars(a) for a in profile[2:]]).problem == "spike"
