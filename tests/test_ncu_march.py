"""benchmarks/ncu_march.py reads ncu's CSV pages: the parsers held to pages in ncu's layout, so a device
call's profile is summarised rather than lost to a misread column (ncu itself runs only there)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import ncu_march  # noqa: E402

HEAD = (
    '"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size"'
)
DETAILS = "\n".join(
    [
        "==PROF== Disconnected from process 4242",
        HEAD + ',"Section Name","Metric Name","Metric Unit","Metric Value"',
        '"0","4242","python3","h","render_forward_lanes_1a2b3c4d_cuda_kernel_forward","1","7","(32, 1, 1)",'
        '"(5000, 1, 1)","GPU Speed Of Light Throughput","Duration","msecond","1.25"',
        '"0","4242","python3","h","render_forward_lanes_1a2b3c4d_cuda_kernel_forward","1","7","(32, 1, 1)",'
        '"(5000, 1, 1)","Launch Statistics","Registers Per Thread","register/thread","120"',
        '"0","4242","python3","h","render_forward_lanes_1a2b3c4d_cuda_kernel_forward","1","7","(32, 1, 1)",'
        '"(5000, 1, 1)","Occupancy","Achieved Occupancy","%","21.5"',
        '"0","4242","python3","h","render_forward_lanes_1a2b3c4d_cuda_kernel_forward","1","7","(32, 1, 1)",'
        '"(5000, 1, 1)","Occupancy","Block Limit Registers","block","17"',
        '"1","4242","python3","h","void at::native::vectorized_elementwise_kernel<4>(int, T1, T2)","1","7",'
        '"(128, 1, 1)","(9, 1, 1)","GPU Speed Of Light Throughput","Duration","nsecond","3,200"',
    ]
)
RAW = "\n".join(
    [
        HEAD + ',"smsp__average_warps_issue_stalled_long_scoreboard_per_issue_active.ratio",'
        '"smsp__average_warps_issue_stalled_barrier_per_issue_active.ratio",'
        '"smsp__average_warps_issue_stalled_wait_per_issue_active.ratio","sm__warps_active.avg.pct_of_peak",'
        '"smsp__average_warps_issue_stalled_selected_per_issue_active.ratio"',
        '"","","","","","","","","","inst","inst","inst","%","inst"',
        '"0","4242","python3","h","render_forward_lanes_1a2b3c4d_cuda_kernel_forward","1","7","(32, 1, 1)",'
        '"(5000, 1, 1)","12.5","30.25","0","21.5","100"',
        '"1","4242","python3","h","void at::native::vectorized_elementwise_kernel<4>(int, T1, T2)","1","7",'
        '"(128, 1, 1)","(9, 1, 1)","0.5","n/a","1.5","80","1"',
    ]
)


def test_the_summary_keeps_each_launch_its_duration_in_microseconds_and_its_costliest_stalls():
    launches = {k["id"]: k for k in ncu_march.summarise(DETAILS, RAW)}
    march, torch_op = launches["0"], launches["1"]
    assert march["kernel"] == "render_forward_lanes"
    assert march["duration"] == pytest.approx(1250.0)
    assert march["registers"] == 120 and march["achieved_occupancy"] == 21.5
    assert "Block Limit Registers" not in march and len(march) == 6  # kernel, id, stalls and 3 kept
    assert list(march["stalls"]) == ["barrier", "long_scoreboard"]  # ranked; a zero and `selected` out
    assert march["stalls"]["barrier"] == 30.25
    assert torch_op["kernel"] == "void at::native::vectorized_elementwise_kernel<4>"
    assert torch_op["duration"] == pytest.approx(3.2)
    assert torch_op["stalls"] == {"wait": 1.5, "long_scoreboard": 0.5}  # "n/a" skipped


def test_a_details_page_without_its_columns_is_refused():
    with pytest.raises(ValueError, match="Metric Value"):
        ncu_march.parse_details(HEAD + ',"Section Name","Metric Name","Metric Unit"\n"0","1"')
