"""Kill `train` at random moments and resume it, until it finishes; the model must equal an unbroken run's.

Run: python tests/kill_resume.py --kills 50 [--preset fast] [--seed 1]. The CI-sized version of this is
tests/test_crash_safety.py (6 kills of a tiny run); this one runs a whole preset on the procedural scene
through the command line, with checkpoints by time every `--checkpoint-seconds`, and prints a table.
"""

from __future__ import annotations

import argparse
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hdrplenoxels.synth.procedural import ProceduralSceneSpec, write_procedural_scene


def train(scene: Path, run: Path, args, extra: list[str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "hdrplenoxels", "train", str(scene), "--preset", args.preset]
    cmd += [
        "--out",
        str(run),
        "--device",
        "cpu",
        "--quiet",
        "--set",
        f"checkpoint_seconds={args.checkpoint_seconds}",
    ]
    cmd += extra
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def same_model(a: Path, b: Path) -> bool:
    x, y = dict(np.load(a)), dict(np.load(b))
    return x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x if k != "meta_json")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--kills", type=int, default=50)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--checkpoint-seconds", type=float, default=0.5)
    ap.add_argument("--max-wait", type=float, default=6.0, help="kill after 0.5..this many seconds")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    root = Path(tempfile.mkdtemp(prefix="kill_resume_"))
    scene = write_procedural_scene(root / "scene", ProceduralSceneSpec()).parent
    t0 = time.monotonic()
    unbroken = train(scene, root / "unbroken", args, [])
    assert unbroken.wait() == 0, unbroken.stderr.read()
    print(f"unbroken run: {time.monotonic() - t0:.1f} s")
    run, kills, resumes, steps = root / "killed", 0, 0, []
    while True:
        proc = train(scene, run, args, ["--resume"] if run.exists() else [])
        resumes += run.exists()
        wait = rng.uniform(0.5, args.max_wait) if kills < args.kills else None
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            kills += 1
            ckpts = sorted((run / "checkpoints").glob("step_*.npz")) if run.exists() else []
            steps.append(int(ckpts[-1].stem.split("_")[1]) if ckpts else 0)
            continue
        if proc.returncode != 0:
            sys.exit(f"a resumed run failed:\n{proc.stderr.read()[-2000:]}")
        break
    equal = same_model(root / "unbroken" / "model.npz", run / "model.npz")
    print(f"kills: {kills}, resumes: {resumes}, newest checkpoint at each kill: {steps}")
    print(f"final model equals the unbroken run's: {equal}")
    sys.exit(0 if equal else 1)


if __name__ == "__main__":
    main()
