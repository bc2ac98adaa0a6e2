"""Named tensors in ``.safetensors`` files; pickled checkpoints are refused."""

from __future__ import annotations

import os
from typing import Any

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.io.atomic import _umask, atomic_output

PICKLE_SUFFIXES = (".pt", ".pth", ".ckpt", ".pkl", ".pickle", ".bin")
"""Suffixes of pickled tensors, which are refused: unpickling a file can run arbitrary code."""


def write_tensors(tensors: dict[str, Any], path: str | os.PathLike, *, metadata: dict[str, str] | None = None
                  ) -> None:
    """Write named tensors as one ``.safetensors`` file, atomically (CPU copies; shared storage written once each).

    Raises:
        InputError: ``path`` does not end in ``.safetensors``, or its folder does not exist.
    """
    from safetensors.torch import save_file

    if not os.fspath(path).endswith(".safetensors"):
        raise InputError(f"{path}: tensors are written as .safetensors")
    plain = {name: tensor.detach().cpu().contiguous().clone() for name, tensor in tensors.items()}
    with atomic_output(path) as staged:
        save_file(plain, str(staged), metadata=metadata)
        os.chmod(staged, 0o666 & ~_umask())  # safetensors creates its files 0600, whatever the umask


def read_tensors(path: str | os.PathLike) -> dict[str, Any]:
    """Named CPU tensors from a ``.safetensors`` file.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: a pickled file (refused), or not readable as safetensors.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    name = os.fspath(path)
    if name.lower().endswith(PICKLE_SUFFIXES):
        raise InputError(f"{name}: a pickled file; dpcn_med only reads .safetensors (unpickling a file can run "
                         "arbitrary code)")
    if not os.path.isfile(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    try:
        return load_file(name)
    except (SafetensorError, OSError, ValueError) as error:
        raise InputError(f"{name}: not a readable .safetensors file ({error})") from None


def read_tensor_header(path: str | os.PathLike) -> tuple[dict[str, str], dict[str, tuple[int, ...]]]:
    """The header of a ``.safetensors`` file: its string metadata (empty if none) and each tensor's shape (no tensor
    is read).

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not readable as safetensors.
    """
    from safetensors import SafetensorError, safe_open

    name = os.fspath(path)
    if not os.path.isfile(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    try:
        with safe_open(name, framework="pt") as handle:
            return (dict(handle.metadata() or {}),
                    {key: tuple(handle.get_slice(key).get_shape()) for key in handle.keys()})
    except (SafetensorError, OSError, ValueError) as error:
        raise InputError(f"{name}: not a readable .safetensors file ({error})") from None
