"""A registration's options resolved before any work: mode, bandwidth, device and the feature model.

A batch checks them once with :func:`check_options`; :func:`load_feature_model` keeps the model last loaded, so the
registrations that use it read its files once.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from dpcn_med import io
from dpcn_med.arguments import check_integer, shown
from dpcn_med.devices import resolve_device
from dpcn_med.errors import InputError
from dpcn_med.preprocess import MODALITIES
from dpcn_med.solver.config import DEFAULT_BANDWIDTH
from dpcn_med.solver.validation import check_grid_bandwidth, check_mode

if TYPE_CHECKING:
    from dpcn_med.models import DPCN


def check_options(*, mode: str, model: str | os.PathLike | None, bandwidth: int | None, device: str | torch.device,
                  fixed_modality: str, moving_modality: str
                  ) -> tuple[str, int, torch.device, DPCN | None]:
    """:func:`dpcn_med.register`'s options checked before any work (a batch checks them once, not at every pair).

    Returns:
        ``(mode, bandwidth, device, network)``: the bandwidth and device resolved (``None``: the model's, else
        :data:`DEFAULT_BANDWIDTH`), the model loaded (``None``: learning-free).

    Raises:
        InputError: an unknown mode, modality or device, a bandwidth out of range (the grids will be ``(2B)^3``), or
            a model that cannot be used at this bandwidth.
    """
    mode = check_mode(mode)
    if bandwidth is not None:
        bandwidth = check_grid_bandwidth(check_integer("bandwidth", bandwidth))
    for name, value in (("fixed_modality", fixed_modality), ("moving_modality", moving_modality)):
        if value not in MODALITIES:
            raise InputError(f"{name} {value!r} is not supported; use one of {', '.join(MODALITIES)}")
    torch_device = resolve_device(device)
    network = load_feature_model(model, bandwidth, torch_device)
    if bandwidth is None:
        bandwidth = DEFAULT_BANDWIDTH if network is None else network.config.bandwidth
    return mode, bandwidth, torch_device, network


LEARNING_FREE = ("none", "learning-free")
"""Names of the learning-free solver for ``model`` (as is ``None``)."""


def load_feature_model(model: str | os.PathLike | None, bandwidth: int | None, device: torch.device):
    """The learned model named by ``model`` (a path to ``NAME.safetensors`` / ``NAME.json`` / ``NAME``) on
    ``device``, or ``None`` for the learning-free solver.

    Raises:
        InputNotFoundError: the model's files are missing.
        InputError: not a path (or ``None``), an empty one, not a dpcn_med model, or trained at another bandwidth
            than ``bandwidth`` (any when ``None``).
    """
    if model is None:
        return None
    if not isinstance(model, (str, os.PathLike)) or Path(model).name in ("", ".."):
        raise InputError(f"model is {shown(model)}; expected the path of a model (NAME.safetensors, NAME.json or "
                         f"NAME), or None or 'none' for the learning-free solver")
    if os.fspath(model).lower() in LEARNING_FREE:
        return None
    network = _loaded_model(model, device)
    if bandwidth is not None and network.config.bandwidth != bandwidth:
        raise InputError(f"{model}: this model was trained at bandwidth {network.config.bandwidth}; register with "
                         f"bandwidth={network.config.bandwidth} (--bandwidth {network.config.bandwidth})")
    return network


_LOADED: dict[tuple, DPCN] = {}
"""The model last loaded, by its files' SHA-256 and its device: the registrations of a batch (or of a Dask worker)
load it once. A model is only ever evaluated here, so one instance serves every registration."""


def _loaded_model(model: str | os.PathLike, device: torch.device) -> DPCN:
    from dpcn_med.models import load_model
    from dpcn_med.models.weights import model_paths

    try:
        key = (*(io.file_sha256(path) for path in model_paths(model)), str(device))
    except (OSError, InputError):  # missing or unreadable files: load_model says what is wrong
        return load_model(model, device=device)
    if key not in _LOADED:
        _LOADED.clear()  # one model at a time: a cohort uses one
        _LOADED[key] = load_model(model, device=device)
    return _LOADED[key]
