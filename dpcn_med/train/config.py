"""Training configuration: one YAML file, read into dataclasses whose defaults are the only defaults.

Example (``training/configs/*.yaml`` hold complete ones)::

    output: runs/ct_mr
    model: {bandwidth: 32, modalities: [ct, mr]}
    data: {volumes: [mni, mni-pseudo-ct], validation_volumes: [../shared/data/seg3d/MR.nii.gz]}
    optimiser: {steps: 20000, batch_size: 32}
"""

from __future__ import annotations

import math
import os
import re
import types
import typing
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml

from dpcn_med.arguments import check_integer
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.models import ModelConfig
from dpcn_med.preprocess import Preprocessing
from dpcn_med.solver import LossWeights, SolverConfig
from dpcn_med.synth import PairConfig
from dpcn_med.train.folders import check_crop
from dpcn_med.train.pretrain import PretrainConfig


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

    def __post_init__(self) -> None:
        for name in ("volumes", "validation_volumes"):
            if not getattr(self, name):
                raise InputError(f"{name} is empty; list at least one volume (a path or {', '.join(BUILT_IN_VOLUMES)})")
        if self.validation_pairs < 1:
            raise InputError(f"validation_pairs is {self.validation_pairs}; expected at least 1")
        check_integer("validation_seed", self.validation_seed, minimum=0, maximum=MAX_SEED)
        if not 0 <= self.folder_fraction <= 1:
            raise InputError(f"folder_fraction is {self.folder_fraction}; expected a fraction of the steps in [0, 1]")
        check_crop(self.folder_crop, "folder_crop")


@dataclass(frozen=True)
class OptimiserConfig:
    """AdamW with a linear warm-up and a cosine decay to ``final_fraction`` of the rate.

    Attributes:
        steps: optimiser steps in all.
        batch_size: pairs per step and device.
        learning_rate, weight_decay, warmup_steps, final_fraction: the schedule.
        gradient_clip: largest gradient norm (0: no clipping).
        amp: bfloat16 autocast of the feature extractors on CUDA (their features are cast back to float32 and
            the solver runs in float32: :meth:`dpcn_med.models.DPCN.forward`).

    Raises:
        InputError: a value out of its range (the message names it).
    """

    steps: int = 20000
    batch_size: int = 32
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 500
    final_fraction: float = 0.02
    gradient_clip: float = 1.0
    amp: bool = True

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} is {getattr(self, name)}; expected at least 1")
        if self.warmup_steps < 0:
            raise InputError(f"warmup_steps is {self.warmup_steps}; expected 0 (no warm-up) or more")
        if not 0 < self.learning_rate < math.inf:
            raise InputError(f"learning_rate is {self.learning_rate}; expected a finite number > 0")
        if not 0 <= self.weight_decay < math.inf:
            raise InputError(f"weight_decay is {self.weight_decay}; expected a finite number >= 0")
        if not 0 <= self.final_fraction <= 1:
            raise InputError(f"final_fraction is {self.final_fraction}; expected a fraction of the rate in [0, 1]")
        if not 0 <= self.gradient_clip < math.inf:
            raise InputError(f"gradient_clip is {self.gradient_clip}; expected a finite norm > 0, or 0 for no "
                             "clipping")


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        output: folder for the checkpoint, logs, plot and the final model (relative to the config file).
        model: the network (:class:`dpcn_med.models.ModelConfig`).
        data: the pairs.
        optimiser: the optimisation.
        loss: the weights and targets of the training terms (:class:`dpcn_med.solver.LossWeights`; the rotation
            width in radians).
        pretrain: dense pretraining of the rotation-stage networks over the first steps
            (:class:`dpcn_med.train.pretrain.PretrainConfig`; none by default).
        seed: of the pairs and the initial weights (each rank, and each resumed start, draws its own stream of
            synthetic pairs; rank ``r`` crops each folder's real pairs with a seed drawn from ``seed + r`` and the
            folder's place in the list).
        device: ``auto``, ``cpu``, ``cuda`` (under torchrun, each process takes ``cuda:LOCAL_RANK``).
        log_every, validate_every, checkpoint_every: in steps.
        resume: continue from ``output/checkpoint`` when it exists (which must have been made with this model, data
            and weight decay: :data:`dpcn_med.train.checkpoint.MUST_MATCH_ON_RESUME`).
    """

    output: str = "runs/dpcn"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optimiser: OptimiserConfig = field(default_factory=OptimiserConfig)
    loss: LossWeights = field(default_factory=LossWeights)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)
    seed: int = 0
    device: str = "auto"
    log_every: int = 10
    validate_every: int = 500
    checkpoint_every: int = 500
    resume: bool = True

    def __post_init__(self) -> None:
        if not self.output.strip():
            raise InputError("output is empty; name the folder the run writes into")
        check_integer("seed", self.seed, minimum=0, maximum=MAX_SEED)
        if not isinstance(self.device, str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device):
            # the names only: whether this machine has the GPU is for distributed.start
            raise InputError(f"device is {self.device!r}; expected auto, cpu, cuda or cuda:N")
        if self.pretrain.steps > self.optimiser.steps:
            raise InputError(f"pretrain.steps is {self.pretrain.steps}; expected at most optimiser.steps "
                             f"({self.optimiser.steps}), the run's steps in all")
        for name in ("log_every", "validate_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} is {getattr(self, name)}; expected a number of steps >= 1")

    def to_json(self) -> dict:
        return asdict(self)


MAX_SEED = 2 ** 32 - 1
"""Seeds are unsigned 32-bit integers: numpy's SeedSequence, which derives the run's other seeds from them
(:func:`dpcn_med.train.folders.derived_seed`), refuses negative ones."""

_SETTINGS_FIELDS = {(ModelConfig, "preprocessing"): Preprocessing, (ModelConfig, "solver"): SolverConfig}
"""Mapping fields whose entries are the fields of another dataclass, and are checked as such."""

_SCALARS = {bool: ("true or false", "true/false values"), int: ("an integer", "integers"),
            float: ("a number", "numbers"), str: ("a string", "strings")}


def _where(source: str, keys: tuple[str, ...]) -> str:
    """``tiny.yaml: optimiser.steps``: the file and the key path in it."""
    path = "".join(key if key.startswith("[") else f".{key}" for key in keys).lstrip(".")
    return f"{source}: {path}" if keys else source


def _expected(kind: Any, plural: bool = False) -> str:
    """How a type annotation reads in a message: ``a list of 2 numbers``."""
    args = typing.get_args(kind)
    if kind in _SCALARS:
        return _SCALARS[kind][plural]
    if kind is dict or is_dataclass(kind):
        return "mappings" if plural else "a mapping"
    if typing.get_origin(kind) is tuple:
        items = args[0] if args[1:] == (Ellipsis,) or len(set(args)) == 1 else None
        count = "" if args[1:] == (Ellipsis,) else f"{len(args)} "
        listed = f"{count}{_expected(items, True)}" if items is not None else \
            f"[{', '.join(_expected(a) for a in args)}]"
        return f"lists of {listed}" if plural else f"a list of {listed}"
    (other,) = (a for a in args if a is not type(None))  # ``X | None``, the only union the configs use
    return f"{_expected(other, plural)} or null"


def _checked(value: Any, kind: Any, source: str, keys: tuple[str, ...]) -> Any:
    """``value`` if it has the annotated type ``kind`` (lists become tuples, integers floats); else an error naming
    the key, the type expected and the value.

    YAML reads ``'false'`` (quoted) as a string, which ``bool`` would take for true, and ``mni`` where a list is meant
    as a string, which a loop would take character by character: both are refused, as are booleans for numbers.
    """
    expected = kind
    if typing.get_origin(kind) in (typing.Union, types.UnionType):  # ``X | None``, the only union the configs use
        if value is None:
            return None
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if is_dataclass(kind):
        return _build(kind, value, source, keys)
    if origin is tuple and isinstance(value, list):
        items = [args[0]] * len(value) if args[1:] == (Ellipsis,) else args
        if len(items) == len(value):
            return tuple(_checked(item, item_kind, source, (*keys, f"[{index}]"))
                         for index, (item, item_kind) in enumerate(zip(value, items)))
    elif kind is dict and isinstance(value, dict):
        return value
    elif kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    elif kind in _SCALARS and type(value) is kind:
        return value
    shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else repr(value)
    hint = ""
    if kind is float and isinstance(value, str) and re.fullmatch(r"[-+]?[\d.]+[eE][-+]?\d+", value):
        hint = " (YAML reads 1e-3 as a string: write 0.001 or 1.0e-3)"
    elif kind is bool and isinstance(value, str):
        hint = " (a quoted string: write true or false without quotes)"
    raise InputError(f"{_where(source, keys)}: expected {_expected(expected)}, got {shown}{hint}")


def _build(cls: type, values: Any, source: str, keys: tuple[str, ...] = ()) -> Any:
    """A (nested) dataclass from plain values, refusing unknown keys and values of the wrong type, and naming where
    they are."""
    where = _where(source, keys)
    if not isinstance(values, dict):
        raise InputError(f"{where}: expected a mapping, got {'null' if values is None else type(values).__name__}")
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(values) - set(known), key=str)
    if unknown:
        raise InputError(f"{where}: unknown keys {unknown}; known: {', '.join(known)}")
    hints = typing.get_type_hints(cls)
    built = {}
    for name, value in values.items():
        settings = _SETTINGS_FIELDS.get((cls, name))
        if settings is not None and isinstance(value, dict):  # checked entry by entry; the owner builds them
            hints_of = typing.get_type_hints(settings)
            built[name] = {key: _checked(v, hints_of[key], source, (*keys, name, key)) if key in hints_of else v
                           for key, v in value.items()}
        else:
            built[name] = _checked(value, hints[name], source, (*keys, name))
    try:
        return cls(**built)
    except (TypeError, ValueError) as error:
        # The dataclasses' own checks start with the field's name: "steps is 0; ..." becomes "optimiser.steps is 0".
        message = str(error)
        name = message.split(" ", 1)[0]
        raise InputError(f"{_where(source, (*keys, name))}{message[len(name):]}" if name in known else
                         f"{where}: {message}") from None


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (which would silently replace the first)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # ``<<: *anchor`` may be overridden, as YAML intends
                continue
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, typing.Hashable):
                continue  # the base class refuses it
            if key in first:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} appears twice (also at line {first[key].line + 1}); keep one",
                    key_node.start_mark)
            first[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Read a YAML training config; relative paths in it are taken from the file's folder, and ``~`` is the home
    folder.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: empty, not YAML, a key given twice, unknown keys, values of the wrong type or out of range (each
            message names the file and the key).
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give the YAML config file (training/configs/ has examples)")
    if not path.is_file():
        raise InputNotFoundError(f"{path}: not found (no such file); check the path")
    try:
        values = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark
        kind = "" if isinstance(error, yaml.constructor.ConstructorError) else "not a YAML file: "  # YAML, misused
        raise InputError(f"{path}: {kind}line {mark.line + 1}, column {mark.column + 1}: {error.problem}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not a YAML file ({' '.join(str(error).split())})") from None
    if values is None:  # an empty or truncated file, or the wrong one, must not start an hours-long default run
        raise InputError(f"{path}: holds no settings (empty, or comments only); write the run's settings, or '{{}}' "
                         "for every default")
    config = _build(TrainConfig, values, str(path))
    folder = path.resolve().parent

    def resolve(name: str) -> str:
        name = os.path.expanduser(name)
        return name if os.path.isabs(name) else os.path.normpath(folder / name)

    data = config.data
    data = DataConfig(**{**{f.name: getattr(data, f.name) for f in fields(DataConfig)},
                         **{key: tuple(v if v in BUILT_IN_VOLUMES else resolve(v) for v in getattr(data, key))
                            for key in ("volumes", "validation_volumes", "folders", "validation_folders")}})
    return TrainConfig(**{**{f.name: getattr(config, f.name) for f in fields(TrainConfig)}, "data": data,
                          "output": resolve(config.output)})


BUILT_IN_VOLUMES = ("mni", "mni-head", "mni-pseudo-ct")
"""Volumes that ship with dpcn_med (:mod:`dpcn_med.samples`), usable by name in ``data.volumes``."""
