"""What the end of a training run costs: from its last step to `Trainer.run` returning (the final
checkpoint, the tones' gauge and controller, the model, the tone plot), and the megabytes of the final
checkpoint and the model; with the writes behind the work (`core/writer_thread.py`, the package's way)
against the same writes made in turn, in the same process.

Each run trains the preset on DATA with tone mapping (its steps shortened with `--steps`: the grid still
reaches every level of the schedule), the two ways alternating. The end's seconds are the run's minus the
log's seconds to its last step.

Usage: python benchmarks/run_end.py DATA [--preset balanced] [--steps 300] [--repeats 2]
       [--device auto] [--json F]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from concurrent.futures import Future
from pathlib import Path

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()  # before torch loads, as the command line does

# isort: split
import torch  # noqa: E402

import hdrplenoxels.train.trainer as trainer_module  # noqa: E402
from hdrplenoxels.core.writer_thread import WriterThread  # noqa: E402
from hdrplenoxels.data import load_scene  # noqa: E402
from hdrplenoxels.train.model import MODEL_FILE  # noqa: E402
from hdrplenoxels.train.presets import preset  # noqa: E402
from hdrplenoxels.train.run_folder import LOG_FILE, checkpoints  # noqa: E402


class InlineWriter(WriterThread):
    """The reference: every write made when it is handed over, on the caller's thread."""

    def submit(self, write, *args) -> Future:
        future: Future = Future()
        try:
            future.set_result(write(*args))
        except Exception as e:  # noqa: BLE001 - kept for `wait`, as the thread's would be
            future.set_exception(e)
        self._pending.append(future)
        return future


def end_seconds(scene, preset_name: str, steps: int, device: str, inline: bool) -> dict[str, float]:
    cfg = preset(preset_name)
    cfg.tonemap.enabled = True
    cfg.device = device
    if steps:
        cfg.optim.n_iters = steps
        cfg.grid.upsample_every = max(1, steps // len(cfg.grid.reso_schedule))
    trainer_module.WriterThread = InlineWriter if inline else WriterThread
    try:
        with tempfile.TemporaryDirectory(prefix="hdrplenoxels-run-end-") as tmp:
            run = Path(tmp) / "run"
            t = time.perf_counter()
            trainer_module.Trainer(scene, cfg, run, overwrite=True).run(progress=False)
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            whole = time.perf_counter() - t
            last = json.loads((run / LOG_FILE).read_text().splitlines()[-1])["seconds"]
            final = checkpoints(run)[-1]
            written = (final.stat().st_size + (run / MODEL_FILE).stat().st_size) / 1e6
    finally:
        trainer_module.WriterThread = WriterThread
    return {"run_seconds": whole, "end_seconds": whole - last, "end_mb": written}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="balanced")
    ap.add_argument("--steps", type=int, default=300, help="steps a run trains (0: the preset's)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    scene = load_scene(args.data)
    rows: dict[str, list[float]] = {"in turn": [], "behind": []}
    for _ in range(args.repeats):
        for name in rows:
            r = end_seconds(scene, args.preset, args.steps, device, inline=name == "in turn")
            rows[name].append(r["end_seconds"])
            line = f"{name:8s} end of run {r['end_seconds']:.2f} s, {r['end_mb']:.0f} MB written (whole run "
            line += f"{r['run_seconds']:.1f} s)"
            print(line, flush=True)
    before, after = statistics.median(rows["in turn"]), statistics.median(rows["behind"])
    print(f"median end of run: in turn {before:.2f} s, behind the work {after:.2f} s (x{after / before:.2f})")
    if args.json:
        summary = {"preset": args.preset, "steps": args.steps, "device": device, **rows}
        args.json.write_text(json.dumps(summary))


if __name__ == "__main__":
    main()
