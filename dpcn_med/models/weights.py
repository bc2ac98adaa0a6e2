"""Saving and loading models: tensors as safetensors, the :class:`ModelConfig` as JSON beside them.

Never pickle: ``torch.load`` of a downloaded file can run arbitrary code, so a model is two plain files,
``NAME.safetensors`` and ``NAME.json``, and a pickled checkpoint is refused (:func:`dpcn_med.io.read_tensors`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import torch

from dpcn_med import io
from dpcn_med.arguments import shown
from dpcn_med.devices import resolve_device
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.models.dpcn import DPCN, ModelConfig

FORMAT = "dpcn_med.model/1"
"""The JSON's ``format`` key and the weights' ``format`` metadata: what wrote them and how."""
CONFIG_HASH = "config_sha256"
"""The weights' metadata key holding :func:`config_hash` of the config they were saved with (absent in files written
before it existed, which load as before)."""


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


def config_hash(settings: dict) -> str:
    """SHA-256 of the model's settings (the JSON's ``config``) in a canonical JSON text (sorted keys, no spaces):
    the same for the saved dict and for the one read back, whatever the file's layout."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


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
    settings = model.config.to_json()
    io.write_tensors(unique_state(model), weights, metadata={"format": FORMAT, CONFIG_HASH: config_hash(settings)})
    io.write_json({"format": FORMAT, "config": settings, "record": record or {}}, config)
    return weights, config


def load_model(path: str | os.PathLike, *, device: str | torch.device = "cpu") -> DPCN:
    """A model saved by :func:`save_model`, in eval mode on ``device`` (``auto``, ``cpu``, ``cuda`` or ``cuda:N``, as
    :func:`dpcn_med.devices.resolve_device` reads it).

    Raises:
        InputNotFoundError: either file is missing.
        InputError: an unusable ``device`` (refused before the files are read), not a model path (:func:`model_paths`)
            or one the file system refuses (a name too long), a pickled checkpoint, a config from something else,
            lacking a key that defines the model or with unusable values, weights of another format or saved with
            another config, weights that do not fit the config, integer weights where floats belong, weights holding
            NaN or Inf (as stored or as float32), or learned temperatures that are not finite and positive.
    """
    device = resolve_device(device)
    weights, config = _existing_model_paths(path)
    settings, model_config = _read_config(config)
    metadata, shapes = io.read_tensor_header(weights)
    if metadata.get("format", FORMAT) != FORMAT:
        raise InputError(f"{weights}: weights of format {metadata['format']!r}; this version of dpcn_med reads "
                         f"{FORMAT!r}")
    model = _checked_model(weights, config, model_config, shapes)
    if CONFIG_HASH in metadata and metadata[CONFIG_HASH] != config_hash(settings):  # same shapes, another training
        raise InputError(f"{weights}: saved with another config than {config} (its {CONFIG_HASH} differs): the two "
                         "files come from different models or trainings; keep the pair save_model wrote together")
    tensors = io.read_tensors(weights)
    _check_tensors(weights, model, tensors)
    model.load_state_dict({**model.state_dict(), **tensors})
    _check_temperatures(weights, model)
    return model.to(device).eval()


def _existing_model_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """:func:`model_paths` of a model that exists (at least one of its files).

    Raises:
        InputNotFoundError: neither file exists.
        InputError: as :func:`model_paths`, a pickled checkpoint, or a path the file system refuses.
    """
    weights, config = model_paths(path)
    if os.fspath(path).lower().endswith(io.PICKLE_SUFFIXES):
        io.read_tensors(path)  # raises its message about pickles
    try:
        neither = not weights.exists() and not config.exists()
    except OSError as error:  # Path.exists raises for a name too long (ENAMETOOLONG), on Python 3.11 at least
        raise InputError(f"{os.fspath(path)}: not a usable model path ({error.strerror or error})") from None
    if neither:  # the name is wrong, not one file of the pair lost
        raise InputNotFoundError(f"{os.fspath(path)}: no such model (neither {weights.name} nor {config.name} "
                                 f"exists in {weights.parent}); check the path")
    return weights, config


def _read_config(config: Path) -> tuple[dict, ModelConfig]:
    """The model's settings (the JSON's ``config``) and the :class:`ModelConfig` they make.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: a config from something else (a training checkpoint's is named as such), lacking its settings,
            or with unusable values.
    """
    description = io.read_json(config)
    if not isinstance(description, dict) or description.get("format") != FORMAT:
        # A training checkpoint (checkpoint.json: step, optimiser state) sits beside the model a run writes.
        hint = (f": a training checkpoint; the trained model is {config.with_name('model.safetensors')}"
                if isinstance(description, dict) and {"step", "param_groups"} <= description.keys() else "")
        raise InputError(f"{config}: not a dpcn_med model config (format {FORMAT!r} expected){hint}")
    if "config" not in description:
        raise InputError(f"{config}: lacks the 'config' key (the model's settings); save the model again")
    settings = description["config"]
    if not isinstance(settings, dict):
        raise InputError(f"{config}: 'config' is a {type(settings).__name__}, expected a mapping of the model's "
                         "settings")
    try:
        return settings, ModelConfig.from_json(settings)
    except InputError as error:
        raise InputError(f"{config}: {error}") from None
    except (TypeError, ValueError, KeyError) as error:  # a value of the wrong type reaches arithmetic or MONAI
        raise InputError(f"{config}: unusable model config ({type(error).__name__}: {error})") from None


def _check_tensors(weights: Path, model: DPCN, tensors: dict[str, torch.Tensor]) -> None:
    """Refuse integer tensors where ``model`` has floats, and tensors holding NaN or Inf as stored or in ``model``'s
    dtype.

    Raises:
        InputError: naming the tensor.
    """
    for name, reference in unique_state(model).items():
        # load_state_dict would cast integers silently and keep NaN, and cast 1e300 in float64 to Inf: a model that
        # registers wrongly, confidently.
        tensor = tensors[name]
        if reference.is_floating_point() and not tensor.is_floating_point():
            raise InputError(f"{weights}: tensor {name} is {str(tensor.dtype).removeprefix('torch.')}, expected "
                             "floating point")
        if tensor.is_floating_point() and not torch.isfinite(tensor.to(reference.dtype)).all():
            raise InputError(f"{weights}: tensor {name} holds NaN or Inf values"
                             + (f" (as {str(reference.dtype).removeprefix('torch.')})"
                                if tensor.dtype != reference.dtype else ""))


def _check_temperatures(weights: Path, model: DPCN) -> None:
    """Refuse learned temperatures that are not finite and positive.

    Raises:
        InputError: naming the stage.
    """
    for stage, temperature in vars(model.temperatures()).items():
        # softplus(-200) is 0 in float32: a softmax dividing by it gives a NaN pose.
        value = float(temperature.detach())
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{weights}: the learned {stage} temperature is {value!r} (softplus of "
                             f"temperatures.raw.{stage}); expected a finite number > 0")


def _checked_model(weights: Path, config: Path, model_config: ModelConfig, shapes: dict[str, tuple[int, ...]]
                   ) -> DPCN:
    """The network of ``model_config`` once the names and ``shapes`` in the weights' header fit it: the network is first
    built on the meta device (no memory), so that weights of another model are refused before it is allocated."""
    with torch.device("meta"):
        skeleton = DPCN(model_config)
    names = set(skeleton.state_dict())
    # named_parameters and named_buffers list a shared extractor once, under its first name, as unique_state does.
    expected = {name: tuple(tensor.shape) for name, tensor in [*skeleton.named_parameters(),
                                                               *skeleton.named_buffers()] if name in names}
    if shapes != expected:
        missing, unexpected = sorted(set(expected) - set(shapes)), sorted(set(shapes) - set(expected))
        raise InputError(f"{weights}: does not fit {config.name} (missing {missing[:3]}, unexpected {unexpected[:3]}"
                         ", or other shapes)")
    return DPCN(model_config)
