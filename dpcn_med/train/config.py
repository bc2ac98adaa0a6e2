"""Training configuration: one YAML file, read into dataclasses whose defaults are the only defaults.

Example (``training/configs/*.yaml`` hold complete ones)::

    output: runs/ct_mr
    model: {bandwidth: 32, modalities: [ct, mr]}
    data: {volumes: [mni, mni-pseudo-ct], validation_volumes: [../shared/data/seg3d/MR.nii.gz]}
    optimiser: {steps: 20000, batch_size: 32}
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from dpcn_med.errors import InputError
from dpcn_med.models import ModelConfig
from dpcn_med.synth import PairConfig


@dataclass(frozen=True)
class DataConfig:
    """Where training pairs come from.

    Attributes:
        volumes: base volumes of the synthetic pairs: image paths (relative to the config file) or built-in names
            (``mni``, ``mni-head``, ``mni-pseudo-ct``).
        validation_volumes: volumes held out for validation, same kinds.
        pair: poses, crops, and the simulated modality of each side (:class:`dpcn_med.synth.PairConfig`).
        validation_pairs: size of the fixed validation set.
        validation_seed: its seed (the same pairs at every validation).
        folders: folders of real registered pairs (:mod:`dpcn_med.train.folders`) mixed into training.
        folder_fraction: share of the steps whose batch comes from ``folders`` (when there are any).
        folder_crop: ``(low, high)`` fraction of the fixed foreground a real pair keeps after a random slab crop,
            or ``None`` for whole pairs.
        validation_folders: folders of real held-out pairs, scored at every validation beside the synthetic set.
    """

    volumes: tuple[str, ...] = ("mni",)
    validation_volumes: tuple[str, ...] = ("mni-pseudo-ct",)
    pair: PairConfig = field(default_factory=PairConfig)
    validation_pairs: int = 64
    validation_seed: int = 1234
    folders: tuple[str, ...] = ()
    folder_fraction: float = 0.5
    folder_crop: tuple[float, float] | None = (0.6, 1.0)
    validation_folders: tuple[str, ...] = ()


@dataclass(frozen=True)
class OptimiserConfig:
    """AdamW with a linear warm-up and a cosine decay to ``final_fraction`` of the rate.

    Attributes:
        steps: optimiser steps in all.
        batch_size: pairs per step and device.
        learning_rate, weight_decay, warmup_steps, final_fraction: the schedule.
        gradient_clip: largest gradient norm (0: no clipping).
        amp: bfloat16 autocast of the networks on CUDA (the solver's FFTs stay in float32).
    """

    steps: int = 20000
    batch_size: int = 32
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 500
    final_fraction: float = 0.02
    gradient_clip: float = 1.0
    amp: bool = True


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        output: folder for the checkpoint, logs, plot and the final model (relative to the config file).
        model: the network (:class:`dpcn_med.models.ModelConfig`).
        data: the pairs.
        optimiser: the optimisation.
        seed: of the pairs and the initial weights (rank ``r`` draws pairs with ``seed + r``).
        device: ``auto``, ``cpu``, ``cuda`` (under torchrun, each process takes ``cuda:LOCAL_RANK``).
        log_every, validate_every, checkpoint_every: in steps.
        resume: continue from ``output/checkpoint`` when it exists.
    """

    output: str = "runs/dpcn"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optimiser: OptimiserConfig = field(default_factory=OptimiserConfig)
    seed: int = 0
    device: str = "auto"
    log_every: int = 10
    validate_every: int = 500
    checkpoint_every: int = 500
    resume: bool = True

    def to_json(self) -> dict:
        return asdict(self)


def _build(cls: type, values: Any, where: str) -> Any:
    """A (nested) dataclass from plain values, refusing unknown keys and naming where they are."""
    if not isinstance(values, dict):
        raise InputError(f"{where}: expected a mapping, got {type(values).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise InputError(f"{where}: unknown keys {unknown}; known: {', '.join(known)}")
    built = {}
    defaults = cls()
    for name, value in values.items():
        default = getattr(defaults, name)
        if is_dataclass(default):
            if isinstance(default, ModelConfig):
                value = ModelConfig.from_json({**default.to_json(), **value}) if isinstance(value, dict) else value
            else:
                value = _build(type(default), value, f"{where}.{name}")
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        built[name] = value
    try:
        return cls(**built)
    except (TypeError, ValueError) as error:
        raise InputError(f"{where}: {error}") from None


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Read a YAML training config; relative paths in it are taken from the file's folder.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not YAML, unknown keys (with where they are), or values out of range.
    """
    import yaml

    from dpcn_med.errors import InputNotFoundError

    path = Path(path)
    if not path.is_file():
        raise InputNotFoundError(f"{path}: not found (no such file); check the path")
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not a YAML file ({error})") from None
    config = _build(TrainConfig, values, str(path))
    folder = path.resolve().parent

    def resolve(name: str) -> str:
        return name if name in BUILT_IN_VOLUMES or os.path.isabs(name) else os.path.normpath(folder / name)

    data = config.data
    data = DataConfig(**{**{f.name: getattr(data, f.name) for f in fields(DataConfig)},
                         **{key: tuple(resolve(v) for v in getattr(data, key))
                            for key in ("volumes", "validation_volumes", "folders", "validation_folders")}})
    output = config.output if os.path.isabs(config.output) else os.path.normpath(folder / config.output)
    return TrainConfig(**{**{f.name: getattr(config, f.name) for f in fields(TrainConfig)}, "data": data,
                          "output": output})


BUILT_IN_VOLUMES = ("mni", "mni-head", "mni-pseudo-ct")
"""Volumes that ship with dpcn_med (:mod:`dpcn_med.samples`), usable by name in ``data.volumes``."""
