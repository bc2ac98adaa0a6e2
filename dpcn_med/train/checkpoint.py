"""A training run's checkpoint: ``checkpoint.safetensors`` (weights and optimiser moments) and ``checkpoint.json``
(the step, the optimiser's other state, the config and the log), saved together and resumed from only by a run of
the same model, data and weight decay. No pickle anywhere."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from dpcn_med import __version__, io
from dpcn_med.errors import InputError
from dpcn_med.models import DPCN
from dpcn_med.models.weights import unique_state
from dpcn_med.train.config import TrainConfig

MUST_MATCH_ON_RESUME = ("model", "data", "optimiser.weight_decay")
"""Config entries a checkpoint must share with the run that resumes it: the networks (but their ``version``), the
pairs (the data's paths as seen from the output folder, or as they were: a project folder moves whole, or only its
run), and the weight decay (restored with the optimiser's state). An entry only one side has (a checkpoint from a
dpcn_med before that setting) differs. The rest may change: ``steps`` (to train on), the rest of the schedule, the
batch size, the seed, the device, the intervals."""

CHECKPOINT_ENTRIES = {"step": int, "param_groups": list, "optimiser_scalars": dict, "config": dict, "rows": list}
"""What ``checkpoint.json`` holds, and the JSON type of each."""


def _checkpoint_paths(output: Path) -> tuple[Path, Path]:
    return output / "checkpoint.safetensors", output / "checkpoint.json"


def save_checkpoint(model: DPCN, optimiser: torch.optim.Optimizer, step: int, config: TrainConfig,
                    rows: list[dict]) -> None:
    """Weights and optimiser moments as safetensors, everything else as JSON (no pickle anywhere)."""
    tensors = {f"model.{name}": tensor for name, tensor in unique_state(model).items()}
    state = optimiser.state_dict()
    scalars = {}
    for index, values in state["state"].items():
        for name, value in values.items():
            if isinstance(value, Tensor):
                tensors[f"optimiser.{index}.{name}"] = value
            else:
                scalars[f"{index}.{name}"] = value
    weights, description = _checkpoint_paths(Path(config.output))
    with io.interrupts_deferred():  # each file is atomic; the pair must be too (load_checkpoint checks the step)
        io.write_tensors(tensors, weights, metadata={"step": str(step)})
        io.write_json({"step": step, "param_groups": state["param_groups"], "optimiser_scalars": scalars,
                       "config": config.to_json(), "rows": rows, "version": __version__}, description)


_ABSENT = object()
"""A config entry a checkpoint does not have."""


def _resume_settings(config: dict) -> dict:
    """The :data:`MUST_MATCH_ON_RESUME` entries of a config's JSON, nested as in the config."""
    settings: dict = {}
    for key in MUST_MATCH_ON_RESUME:
        section, _, name = key.partition(".")
        value = config.get(section, _ABSENT)
        if name:
            value = {name: value.get(name, _ABSENT) if isinstance(value, dict) else _ABSENT}
        elif section == "model" and isinstance(value, dict):
            value = {k: v for k, v in value.items() if k != "version"}  # which dpcn_med saved it; not a setting
        settings[section] = value
    return settings


def _seen_from(settings: dict, output: Any) -> dict:
    """``settings`` with the data's absolute paths made relative to the ``output`` folder."""
    data = settings.get("data")
    if not (isinstance(data, dict) and isinstance(output, str)):
        return settings
    relative = {key: [os.path.relpath(p, output) if isinstance(p, str) and os.path.isabs(p) else p for p in paths]
                for key in ("volumes", "validation_volumes", "folders", "validation_folders")
                if isinstance(paths := data.get(key), list)}
    return {**settings, "data": {**data, **relative}}


def _first_difference(saved: Any, current: Any, key: str = "") -> tuple[str, Any, Any] | None:
    """``(dotted key, saved value, current value)`` of the first entry where two JSON values differ, else ``None``."""
    if isinstance(saved, dict) and isinstance(current, dict):
        for name in [*current, *(k for k in saved if k not in current)]:
            found = _first_difference(saved.get(name, _ABSENT), current.get(name, _ABSENT),
                                      f"{key}.{name}" if key else name)
            if found is not None:
                return found
        return None
    return None if saved == current else (key, saved, current)


def _shown(value: Any) -> str:
    return "no such entry" if value is _ABSENT else json.dumps(value)


def load_checkpoint(model: DPCN, optimiser: torch.optim.Optimizer, config: TrainConfig) -> tuple[int, list[dict]]:
    """Restore a checkpoint into ``model`` and ``optimiser``: ``(step, log rows)``; ``(0, [])`` without one.

    Raises:
        InputError: the checkpoint is malformed, was made with other :data:`MUST_MATCH_ON_RESUME` settings, or is past
            ``config.optimiser.steps``; the message names the file and the way out.
    """
    weights, description = _checkpoint_paths(Path(config.output))
    afresh = "train into another output folder, or start afresh over this one with --restart (resume: false)"
    if not config.resume or not (weights.exists() or description.exists()):
        return 0, []
    for missing, present in ((weights, description), (description, weights)):
        if not missing.exists():  # starting afresh would overwrite the other half at the first checkpoint
            raise InputError(f"{missing}: missing beside {present.name} (a checkpoint is the two files); {afresh}")
    saved = io.read_json(description)
    wrong = [key for key, kind in CHECKPOINT_ENTRIES.items()
             if not (isinstance(saved, dict) and isinstance(saved.get(key), kind))
             or (key == "step" and (isinstance(saved[key], bool) or saved[key] < 0))]
    if wrong:
        raise InputError(f"{description}: not a dpcn_med checkpoint (no valid {', '.join(wrong)}); {afresh}")
    settings = _resume_settings(saved["config"]), _resume_settings(json.loads(json.dumps(config.to_json())))
    difference = _first_difference(*settings)
    if difference is not None and _first_difference(_seen_from(settings[0], saved["config"].get("output")),
                                                    _seen_from(settings[1], config.output)) is not None:
        key, before, now = difference
        raise InputError(f"{description}: was made with {key} {_shown(before)}, this config has {_shown(now)}; "
                         f"{afresh}")
    if saved["step"] > config.optimiser.steps:
        raise InputError(f"{description}: is at step {saved['step']}, past this config's optimiser.steps "
                         f"{config.optimiser.steps}; ask for more steps, or {afresh}")
    try:
        tensors, step = io.read_tensors(weights), io.read_tensor_header(weights)[0].get("step")
    except InputError as error:
        raise InputError(f"{error}; {afresh}") from None
    if step != str(saved["step"]):
        raise InputError(f"{weights}: holds step {step}, {description.name} step {saved['step']}: the two files are "
                         f"from different saves (one cut short?); {afresh}")
    _restore_model(model, tensors, weights, afresh)
    _restore_optimiser(optimiser, tensors, saved, description, afresh)
    return saved["step"], saved["rows"]


def _restore_model(model: DPCN, tensors: dict[str, Tensor], weights: Path, afresh: str) -> None:
    """Load a checkpoint's ``model.*`` tensors into ``model``.

    Raises:
        InputError: tensors missing, unexpected or of another shape than ``model``'s.
    """
    model_state = {name[len("model."):]: t for name, t in tensors.items() if name.startswith("model.")}
    shapes = {name: tensor.shape for name, tensor in unique_state(model).items()}
    misfits = sorted(set(shapes) ^ set(model_state)) + sorted(
        name for name in set(shapes) & set(model_state) if model_state[name].shape != shapes[name])
    if misfits:
        raise InputError(f"{weights}: does not fit this model ({len(misfits)} tensors missing, unexpected or of "
                         f"another shape, such as {misfits[0]}); {afresh}")
    model.load_state_dict({**model.state_dict(), **model_state})


def _restore_optimiser(optimiser: torch.optim.Optimizer, tensors: dict[str, Tensor], saved: dict, description: Path,
                       afresh: str) -> None:
    """Load a checkpoint's ``optimiser.*`` tensors and the JSON's scalars and parameter groups into ``optimiser``.

    Raises:
        InputError: a state that does not fit the optimiser's parameters.
    """
    state: dict = {"state": {}, "param_groups": saved["param_groups"]}
    try:
        for name, tensor in tensors.items():
            if name.startswith("optimiser."):
                _, index, key = name.split(".", 2)
                state["state"].setdefault(int(index), {})[key] = tensor
        for name, value in saved["optimiser_scalars"].items():
            index, key = name.split(".", 1)
            state["state"].setdefault(int(index), {})[key] = value
        optimiser.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise InputError(f"{description}: its optimiser state does not fit this model ({' '.join(str(error).split())})"
                         f"; {afresh}") from None
