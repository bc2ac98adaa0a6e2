"""The torch device named by a user: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``, checked against this machine."""

from __future__ import annotations

import torch

from dpcn_med.arguments import shown
from dpcn_med.errors import InputError


def resolve_device(device: str | torch.device) -> torch.device:
    """``"auto"`` (CUDA when available, else CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (or a ``torch.device``).

    Raises:
        InputError: not a string or ``torch.device``, an unknown device, or a CUDA GPU this machine does not have.
    """
    if not isinstance(device, (str, torch.device)):
        raise InputError(f"device is {shown(device)}; expected auto, cpu, cuda or cuda:N (or a torch.device)")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as error:
        raise InputError(f"device {device!r} is not valid; use auto, cpu, cuda or cuda:N") from error
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {device!r} asked for, but this torch build sees no CUDA GPU; use --device cpu")
    if resolved.type not in ("cpu", "cuda"):
        raise InputError(f"device {device!r} is not supported; use auto, cpu, cuda or cuda:N")
    if resolved.type == "cuda" and resolved.index is not None and resolved.index >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise InputError(f"device {device!r} asked for, but this machine has {count} CUDA GPU"
                         f"{'s' if count > 1 else ''}; use cuda:0{f' to cuda:{count - 1}' if count > 1 else ''}")
    return resolved
