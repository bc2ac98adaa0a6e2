"""Per-stage wall-clock timings of the solver, synchronised on CUDA so that each stage is charged its own kernels."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch


class StageClock:
    """Accumulates seconds per named stage when enabled; does nothing (and never synchronises) otherwise.

    Args:
        device: where the stages run; CUDA work is asynchronous, so each stage boundary synchronises it.
        enabled: measure, or only pass through.
    """

    def __init__(self, device: torch.device, enabled: bool) -> None:
        self.device = device
        self.enabled = enabled
        self.seconds: dict[str, float] = {}

    def _synchronise(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        self._synchronise()
        start = time.perf_counter()
        yield
        self._synchronise()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - start
