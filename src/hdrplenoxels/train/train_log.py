"""What a run reports as it goes: its log, `train_log.jsonl` (every `log_every` steps one JSON line of
the mean MSE since the last line, its PSNR, the engine's own fields and the seconds since the run
(re)started, flushed so that a running job can be followed with `tail -f`), and the progress bar."""

from __future__ import annotations

import json
import math
import time
from typing import TextIO

import torch
from tqdm import tqdm


def mse_to_psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


class TrainLog:
    """Collects each step's MSE (a 0-d device tensor, read only when a line is written: reading it every
    step would make a CPU wait for the GPU), writes the lines and moves the bar (shown when `progress`)."""

    def __init__(self, file: TextIO, total: int, initial: int, progress: bool):
        self.file = file
        self.start = time.perf_counter()
        self.losses: list[torch.Tensor] = []
        self.bar = tqdm(
            total=total, initial=initial, disable=not progress, dynamic_ncols=True, mininterval=0.5
        )
        self.said: set[str] = set()

    def add(self, mse: torch.Tensor) -> None:
        self.losses.append(mse)
        self.bar.update(1)

    def write(self, step: int, engine_fields: dict) -> dict:
        """The line of `step`, written; the MSEs collected since the last line are its mean."""
        mse = float(torch.stack(self.losses).mean())
        self.losses.clear()
        entry = {"step": step, "mse": mse, "psnr": mse_to_psnr(mse), **engine_fields}
        entry["seconds"] = time.perf_counter() - self.start
        self.file.write(json.dumps(entry) + "\n")
        self.file.flush()
        shown = {k: f"{v:.3g}" if isinstance(v, float) else v for k, v in engine_fields.items()}
        self.bar.set_postfix(loss=f"{mse:.2e}", psnr=f"{entry['psnr']:.2f}", **shown)
        return entry

    def say(self, message: str, once: bool = False) -> None:
        """A line above the bar ('' says nothing); `once`: not again if it was said before."""
        if message and not (once and message in self.said):
            self.bar.write(message)
            self.said.add(message)

    def close(self) -> None:
        self.bar.close()
