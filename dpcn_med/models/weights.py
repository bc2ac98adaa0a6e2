"""Saving and loading models: tensors as safetensors, the :class:`ModelConfig` as JSON beside them.

Never pickle: ``torch.load`` of a downloaded file can run arbitrary code, so a model is two plain files,
``NAME.safetensors`` and ``NAME.json``, and a pickled checkpoint is refused (:func:`dpcn_med.io.read_tensors`).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from dpcn_med import io
from dpcn_med.arguments import shown
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.models.dpcn import DPCN, ModelConfig

FORMAT = "dpcn_med.model/1"
"""The JSON's ``format`` key: what wrote it and how."""


def model_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """``(weights, config)`` for ``NAME``, ``NAME.safetensors`` or ``NAME.json``.

    Raises:
        InputError: ``path`` is not a ``str`` or path, is empty, or names a folder (``"."``, ``"runs/"``).
    """
    expected = "expected a model file: NAME, NAME.safetensors or NAME.json"
    if not isinstance(path, (str, os.PathLike)) or isinstance(os.fspath(path), bytes):
        raise InputError(f"model path is {shown(path)}; {expected}")
    if not os.fspath(path):
        raise InputError(f"model path is empty; {expected}")
    if os.fspath(path).endswith(("/", os.sep)) or Path(path).name in ("", ".."):
        raise InputError(f"model path {os.fspath(path)!r} names a folder, not a file; {expected}")
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".safetensors", ".json") else path
    return stem.with_name(stem.name + ".safetensors"), stem.with_name(stem.name + ".json")


def unique_state(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The state dict with each tensor once: shared extractors would otherwise appear under two names."""
    tensors, seen = {}, set()
    for name, tensor in model.state_dict().items():
        if tensor.data_ptr() not in seen:
            seen.add(tensor.data_ptr())
            tensors[name] = tensor
    return tensors


def save_model(model: DPCN, path: str | os.PathLike, *, record: dict | None = None) -> tuple[Path, Path]:
    """Write ``NAME.safetensors`` and ``NAME.json`` (the config and an optional training ``record``), atomically.

    Returns:
        The two paths.
    """
    weights, config = model_paths(path)
    io.write_tensors(unique_state(model), weights, metadata={"format": FORMAT})
    io.write_json({"format": FORMAT, "config": model.config.to_json(), "record": record or {}}, config)
    return weights, config


def load_model(path: str | os.PathLike, *, device: str | torch.device = "cpu") -> DPCN:
    """A model saved by :func:`save_model`, in eval mode on ``device``.

    Raises:
        InputNotFoundError: either file is missing.
        InputError: not a model path (:func:`model_paths`), a pickled checkpoint, a config from something else or
            with unusable values, weights that do not fit the config, integer weights where floats belong, or
            weights holding NaN or Inf.
    """
    weights, config = model_paths(path)
    if os.fspath(path).lower().endswith(io.PICKLE_SUFFIXES):
        io.read_tensors(path)  # raises its message about pickles
    if not weights.exists() and not config.exists():  # the name is wrong, not one file of the pair lost
        raise InputNotFoundError(f"{os.fspath(path)}: no such model (neither {weights.name} nor {config.name} "
                                 f"exists in {weights.parent}); check the path")
    description = io.read_json(config)
    if not isinstance(description, dict) or description.get("format") != FORMAT:
        raise InputError(f"{config}: not a dpcn_med model config (format {FORMAT!r} expected)")
    if "config" not in description:
        raise InputError(f"{config}: lacks the 'config' key (the model's settings); save the model again")
    settings = description["config"]
    if not isinstance(settings, dict):
        raise InputError(f"{config}: 'config' is a {type(settings).__name__}, expected a mapping of the model's "
                         "settings")
    try:
        model = DPCN(ModelConfig.from_json(settings))
    except InputError as error:
        raise InputError(f"{config}: {error}") from None
    except (TypeError, ValueError, KeyError) as error:  # a value of the wrong type reaches arithmetic or MONAI
        raise InputError(f"{config}: unusable model config ({type(error).__name__}: {error})") from None
    tensors = io.read_tensors(weights)
    expected = unique_state(model)
    if set(tensors) != set(expected) or any(tensors[k].shape != v.shape for k, v in expected.items()):
        missing, unexpected = sorted(set(expected) - set(tensors)), sorted(set(tensors) - set(expected))
        raise InputError(f"{weights}: does not fit {config.name} (missing {missing[:3]}, unexpected {unexpected[:3]}"
                         ", or other shapes)")
    for name, reference in expected.items():
        # load_state_dict would cast integers silently and keep NaN: a model that registers wrongly, confidently.
        tensor = tensors[name]
        if reference.is_floating_point() and not tensor.is_floating_point():
            raise InputError(f"{weights}: tensor {name} is {str(tensor.dtype).removeprefix('torch.')}, expected "
                             "floating point")
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise InputError(f"{weights}: tensor {name} holds NaN or Inf values")
    model.load_state_dict({**model.state_dict(), **tensors})
    return model.to(device).eval()
