"""benchmarks/graph_step.py, the spike step per kernel variant that `make gpu-check` times from the CUDA
graph: on a CPU its steps run eagerly, so here each variant trains and renders what the default does (to
the bit), the switches it sets are put back, and a variant that fails is reported, not fatal."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import graph_step  # noqa: E402


def test_each_variant_steps_and_renders_as_the_default_and_puts_its_switches_back(monkeypatch):
    from hdrplenoxels.kernels import march_kernel
    from hdrplenoxels.train.engines import warp_grid

    before = (march_kernel.CUDA_LANES, warp_grid.render_forward, warp_grid.accumulate_backward)
    monkeypatch.setitem(graph_step.VARIANTS, "broken", ({"touched_update": "sideways"}, None, {}))
    names = [*graph_step.VARIANTS]  # every variant the GPU check times, and "broken" last
    kept = []  # what a section stopped at its time limit would keep: each finished variant as it ends
    out = graph_step.graph_steps(
        [96], names, 12, 1, "cpu", on_run=lambda so_far: kept.append(len(so_far["runs"]))
    )
    assert names[-1] == "broken" and kept == list(range(1, len(names)))  # a failure is no result to keep
    assert out["graph"] is False
    for name in names[:-1]:
        run = out["runs"][f"{name}@96"]
        assert run["ms"] > 0 and run["max_image_difference"] == 0.0
    assert "error" in out["runs"]["broken@96"]
    assert (march_kernel.CUDA_LANES, warp_grid.render_forward, warp_grid.accumulate_backward) == before


def test_a_variant_changes_what_runs():
    """The switches reach the engine: the kernel variant a step compiles is the variant's."""
    from hdrplenoxels.train.engines import warp_grid

    with graph_step.variant_kernels(16, {"specialise": True, "max_registers": 96}):
        assert warp_grid.render_forward.keywords == {"specialise": True, "max_registers": 96}
        from hdrplenoxels.kernels import march_kernel

        assert march_kernel.CUDA_LANES == 16


def test_the_winners_are_the_variants_faster_than_the_default_that_render_the_same():
    runs = {
        "default@5000": {"ms": 2.0, "max_image_difference": 0.0},
        "default@100000": {"ms": 20.0, "max_image_difference": 0.0},
        "lanes-16@5000": {"ms": 1.5, "max_image_difference": 1e-6},  # faster at 5 000 rays
        "lanes-16@100000": {"ms": 25.0, "max_image_difference": 1e-6},
        "threads@100000": {"ms": 10.0, "max_image_difference": 0.5},  # faster, but renders otherwise
        "specialised@5000": {"ms": 2.5, "max_image_difference": 0.0},  # slower
        "rays-4x8@5000": {"error": "RuntimeError"},
    }
    report = {"sections": {"step": {"result": {"runs": runs}}}}
    assert graph_step.winners(report) == ["default", "lanes-16"]
