"""What one training step launches: torch operators (those doing arithmetic apart from views and other
metadata) and Warp launches, averaged over steady-state steps of a real trainer, by where in the step
they come from (JOURNAL.md, "CUDA graph"). Each is a launch the host pays for unless the step is
replayed from a CUDA graph.

The fused kernels that replace runs of operators on CUDA (the tone mapper's loss, the ray draw, the tone
parameters' RMSProp, the MSI's dense TV) are counted as a CUDA step takes them
(`kernels.dispatch.KERNELS_ON_CPU`); `--cpu-paths` counts a CPU step's.

Usage: python benchmarks/studies/step/step_launches.py DATA [--preset balanced] [--tonemap] [--steps 5]
       [--cpu-paths]
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import traceback
from pathlib import Path

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import warp as wp  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

# Operators that only make views or read metadata: no kernel on a GPU.
METADATA = ("view", "detach", "slice", "select", "unsqueeze", "expand", "permute", "unbind", "alias",
            "transpose", "squeeze", "reshape", "_unsafe_view", "split", "t.default")  # fmt: skip
PACKAGE = "/hdrplenoxels/"


def _origin() -> str:
    """The innermost package function on the stack (the autograd backward runs under the trainer's)."""
    frames = [f for f in traceback.extract_stack() if PACKAGE in f.filename]
    if not frames:
        return "outside the package"
    f = frames[-1]
    return f"{f.filename.split(PACKAGE)[-1]}:{f.name}"


class Counter(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.arithmetic: collections.Counter = collections.Counter()
        self.metadata = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if any(m in str(func) for m in METADATA):
            self.metadata += 1
        else:
            self.arithmetic[_origin()] += 1
        return func(*args, **(kwargs or {}))


def main() -> None:
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.kernels import dispatch
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import Trainer

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="balanced")
    ap.add_argument("--tonemap", action="store_true", help="train with the tone mapper")
    ap.add_argument("--steps", type=int, default=5, help="steps counted (after 3 that build what is kept)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--cpu-paths", action="store_true", help="PyTorch's operators where a CPU uses them")
    args = ap.parse_args()
    dispatch.KERNELS_ON_CPU = not args.cpu_paths
    cfg = preset(args.preset)
    cfg.tonemap.enabled = args.tonemap
    cfg.device = args.device
    launches: collections.Counter = collections.Counter()
    launch = wp.launch

    def counted(kernel, *a, **k):
        launches[kernel.key] += 1
        return launch(kernel, *a, **k)

    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(load_scene(args.data), cfg, Path(tmp))
        for _ in range(3):
            trainer.train_step()
        wp.launch = counted
        try:
            with Counter() as ops:
                for _ in range(args.steps):
                    trainer.train_step()
        finally:
            wp.launch = launch
    n = args.steps
    paths = "a CPU's" if args.cpu_paths else "CUDA's"
    print(f"{args.preset}, tone mapper {'on' if args.tonemap else 'off'}, on {trainer.device} ({paths} "
          "paths); per step:")  # fmt: skip
    print(f"  torch operators: {sum(ops.arithmetic.values()) / n:.0f} doing arithmetic, "
          f"{ops.metadata / n:.0f} views and metadata")  # fmt: skip
    for origin, count in ops.arithmetic.most_common():
        print(f"    {count / n:5.1f}  {origin}")
    print(f"  Warp launches: {sum(launches.values()) / n:.0f} (on a CPU one per thread's part of a launch)")
    for key, count in launches.most_common():
        print(f"    {count / n:5.1f}  {key}")


if __name__ == "__main__":
    main()
