"""A training step replayed from a CUDA graph (JOURNAL.md, "CUDA graph").

A step launches many small kernels (the ray draw, the march, the tone mapper and its autograd backward,
TV, the free-space prior, the optimisers: JOURNAL.md counts them); launched one by one from
Python, their launch cost outweighs their work on a GPU. A CUDA graph launches the recorded sequence in
one call. It replays the launches exactly as recorded: the same kernels, the same scalar arguments, the
same addresses, and none of the Python that made them. So what a step needs that changes from step to
step lives on the device: the step's count, which the step advances, and the learning rates looked up
at it there (`train/optim.StepRates`); what changes rarely (the view prior's weight, which the
schedule switches off once) is part of the key.

A capture is valid while the key it was made under holds (the grid's and the tone mapper's tensors, the
view prior's weight): a resample makes new tensors, so the next steps run eagerly again (`warmup` of
them, which build what is kept per grid) and the region is captured anew.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import torch

if TYPE_CHECKING:
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.engines.base import Engine

Outputs = Any  # what the region returns: tensors the replay overwrites in place


class Capture(Protocol):
    """Where a region runs: `eager` runs it now; `record` records it once, running nothing, and returns
    (replay, the recording's outputs), replay running the recorded work again into those outputs."""

    def eager(self, region: Callable[[], Outputs]) -> Outputs: ...

    def record(self, region: Callable[[], Outputs]) -> tuple[Callable[[], None], Outputs]: ...


class StepGraph:
    """Runs a step's region eagerly for `warmup` steps under a new key, then captures it and replays the
    capture while the key holds. If a capture fails, the region runs eagerly from then on and `failure`
    says why (a run must not end because its speed-up could not be had)."""

    def __init__(self, capture: Capture, warmup: int = 3):
        if warmup < 1:
            raise ValueError(f"warmup must be >= 1 (a first run builds what the region keeps), got {warmup}")
        self.capture = capture
        self.warmup = warmup
        self.failure: str | None = None
        self.captures = 0  # how many times the region was captured (a new key each)
        self._key: Hashable | None = None
        self._eager_left = warmup
        self._replay: Callable[[], None] | None = None
        self._outputs: Outputs = None

    def __call__(self, key: Hashable, region: Callable[[], Outputs]) -> Outputs:
        """The region's outputs for this step. A replay's outputs are the capture's own tensors, which
        the next replay overwrites: use them (or copy them) before the next call."""
        if self.failure is not None:
            return self.capture.eager(region)
        if key != self._key:
            self._drop()
            self._key, self._eager_left = key, self.warmup
        if self._replay is None and self._eager_left > 0:
            self._eager_left -= 1
            return self.capture.eager(region)
        if self._replay is None:
            try:
                self._replay, self._outputs = self.capture.record(region)
            except Exception as error:  # noqa: BLE001 -- any capture failure: fall back to eager steps
                self._drop()
                self.failure = f"{type(error).__name__}: {error}"
                return self.capture.eager(region)  # the recording ran nothing: the step is still to do
            self.captures += 1
        self._replay()
        return self._outputs

    def _drop(self) -> None:
        """Release the capture (its memory pool holds the region's temporaries)."""
        self._replay, self._outputs = None, None


def uses_step_graph(cfg: TrainConfig, device_type: str) -> bool:
    """Whether a run replays its steps from a CUDA graph: `cfg.cuda_graph` on CUDA with the Warp grid,
    whose step is the one made free of host reads (the NeRF and the PyTorch grid launch eagerly)."""
    return cfg.cuda_graph and device_type == "cuda" and (cfg.model, cfg.backend) == ("grid", "warp")


class CudaCapture:
    """A `Capture` on the generator's CUDA device. `torch.cuda.graph` records torch's work and Warp's
    launches together (they run on one stream: `core.warp_runtime.torch_stream`), Warp told of the capture
    so that it keeps the recorded kernels' modules loaded while the graph lives; `generator`'s draws
    advance at every replay. Eager runs use the recording's side stream too, as torch asks of the steps
    before a capture (what they set up lazily, such as a BLAS workspace, is then set up for that stream)."""

    def __init__(self, generator: torch.Generator):
        self.generator = generator
        self.device = generator.device
        self.side = torch.cuda.Stream(device=self.device)

    def eager(self, region: Callable[[], Outputs]) -> Outputs:
        with torch.cuda.device(self.device):
            main = torch.cuda.current_stream()
            self.side.wait_stream(main)
            with torch.cuda.stream(self.side):
                outputs = region()
            main.wait_stream(self.side)
        return outputs

    def record(self, region: Callable[[], Outputs]) -> tuple[Callable[[], None], Outputs]:
        """A failed recording raises the region's own error where it raised one (torch's then only says
        the capture was invalidated), with torch's current stream put back."""
        import warp as wp

        from hdrplenoxels.core.warp_runtime import torch_stream

        with torch.cuda.device(self.device):
            main = torch.cuda.current_stream()
            graph = torch.cuda.CUDAGraph()
            graph.register_generator_state(self.generator)
            self.side.wait_stream(main)
            raised: list[Exception] = []

            def watched() -> Outputs:
                try:
                    return region()
                except Exception as error:
                    raised.append(error)
                    raise

            mode = wp.CaptureMode.GLOBAL  # torch's mode for the capture it opens
            try:
                with torch.cuda.graph(graph, stream=self.side):
                    warp_capture = wp.ScopedCapture(stream=torch_stream(), external=True, capture_mode=mode)
                    with warp_capture:
                        outputs = watched()
            except Exception as error:
                torch.cuda.set_stream(main)  # torch leaves the side stream current when its end fails
                if raised and raised[0] is not error:
                    raise raised[0] from error
                raise

        return _Replay(graph, warp_capture, self.device), outputs


@dataclass
class _Replay:
    """A recorded graph's replay on its device."""

    graph: torch.cuda.CUDAGraph
    warp_capture: object
    """Warp's record of the modules the graph launches: kept as long as the graph."""
    device: torch.device

    def __call__(self) -> None:
        with torch.cuda.device(self.device):
            self.graph.replay()


def held_key(engine: Engine, view_prior_weight: float, tone_tensors: list[torch.Tensor]) -> tuple:
    """The key of a training step's capture: what it holds the addresses of, which a resample or a resume
    replaces (the grid's and the background's tensors, the tone parameters and the tone mapper's
    buffers: its reference, sizes and curve groups, given in `tone_tensors`), and the view prior's
    weight, a constant of the recorded work that the schedule switches off once."""
    field, background = engine.field, engine.background
    held = [field.links, field.density, field.sh]
    if background is not None:
        held += [background.density, background.color]
    held += tone_tensors
    return (engine.graph_key(), view_prior_weight, *(t.data_ptr() for t in held))
