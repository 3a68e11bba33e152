"""The run's log, `train_log.jsonl`: every `log_every` steps one JSON line of the mean MSE since the last
line, its PSNR, the engine's own fields and the seconds since the run (re)started, flushed so that a
running job can be followed (`tail -f`)."""

from __future__ import annotations

import json
import math
import time
from typing import TextIO

import torch


def mse_to_psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


class TrainLog:
    """Collects each step's MSE (a 0-d device tensor, read only when a line is written: reading it every
    step would make a CPU wait for the GPU) and writes the lines."""

    def __init__(self, file: TextIO):
        self.file = file
        self.start = time.perf_counter()
        self.losses: list[torch.Tensor] = []

    def add(self, mse: torch.Tensor) -> None:
        self.losses.append(mse)

    def write(self, step: int, engine_fields: dict) -> dict:
        """The line of `step`, written; the MSEs collected since the last line are its mean."""
        mse = float(torch.stack(self.losses).mean())
        self.losses.clear()
        entry = {"step": step, "mse": mse, "psnr": mse_to_psnr(mse), **engine_fields}
        entry["seconds"] = time.perf_counter() - self.start
        self.file.write(json.dumps(entry) + "\n")
        self.file.flush()
        return entry
