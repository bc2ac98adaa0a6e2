"""Helpers of the training tests: a tiny config that trains in seconds on a CPU."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from dpcn_med.train import TrainConfig, load_config

TINY_YAML = """
output: run
seed: 3
device: cpu
model: {bandwidth: 8, channels: [4, 8, 16], residual_units: 0, modalities: [ct, mr]}
data:
  volumes: [mni]
  validation_volumes: [mni]
  validation_pairs: 4
  pair: {max_shift_fraction: 0.1}
optimiser: {steps: 4, batch_size: 4, learning_rate: 0.03, warmup_steps: 1, amp: false}
log_every: 1
validate_every: 2
checkpoint_every: 2
"""


def tiny_config(folder: Path, **changes) -> TrainConfig:
    path = folder / "tiny.yaml"
    path.write_text(TINY_YAML)
    return replace(load_config(path), **changes)
