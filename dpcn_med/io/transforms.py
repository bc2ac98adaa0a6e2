"""ITK transform files (.tfm, .txt, .h5): read with the checks ITK lacks, written atomically."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.io._common import _sitk_reason
from dpcn_med.io.atomic import _check_same_transform, _check_write_suffix, _check_written, atomic_output

TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")
"""ITK transform files (text or HDF5), readable by SimpleITK, ITK and Slicer."""


def read_transform(path: str | os.PathLike) -> sitk.Transform:
    """A 3-D ITK transform (.tfm, .txt, .h5), as its concrete SimpleITK class (e.g. ``Similarity3DTransform``).

    Raises:
        InputNotFoundError: the path does not exist.
        InputError: the file is not a readable transform, not 3-D, of a class SimpleITK cannot read back, holds
            non-finite parameters, or (a text file) a parameter that is not a number or a linear transform with
            another number of parameters than its class.
    """
    name = os.fspath(path)
    if not os.path.exists(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    if os.path.isdir(name):
        raise InputError(f"{name}: is a folder; expected a transform file ({', '.join(TRANSFORM_SUFFIXES)})")
    _check_transform_text(name)
    try:
        transform = sitk.ReadTransform(name)
    except RuntimeError as error:
        raise InputError(f"{name}: not a readable transform ({_sitk_reason(error)}); expected an ITK transform file "
                         f"({', '.join(TRANSFORM_SUFFIXES)}) as SimpleITK, ITK or Slicer write it") from None
    except KeyError:  # SimpleITK's ReadTransform cannot downcast a few classes it writes (measured, 2.5)
        raise InputError(f"{name}: holds a transform class SimpleITK cannot read back (ComposeScaleSkewVersor3D is "
                         "one); write it as an AffineTransform") from None
    if transform.GetDimension() != 3:
        raise InputError(f"{name}: is a {transform.GetDimension()}-D transform; expected a 3-D one")
    if not _finite_parameters(transform):
        raise InputError(f"{name}: holds NaN or infinite parameters; compute and write the transform again")
    return transform.Downcast()


def write_transform(transform: sitk.Transform, path: str | os.PathLike) -> None:
    """Write ``transform`` atomically as .tfm or .txt (text) or .h5 / .hdf5 (HDF5); Slicer and ITK read all.

    Raises:
        InputError: another suffix, or the folder does not exist.
        OSError: the file came out short (a full disk, a file-size limit); ``path`` is left as it was.
    """
    target = Path(path)
    _check_write_suffix(target, TRANSFORM_SUFFIXES, "a transform")
    if not _finite_parameters(transform):
        raise InputError(f"{target}: the transform holds NaN or infinite parameters; nothing written")
    with atomic_output(target) as temporary:
        sitk.WriteTransform(transform, str(temporary))
        if target.suffix.lower() in (".tfm", ".txt"):  # the HDF5 writer raises on a short write itself
            _check_written(target, lambda: _check_same_transform(temporary, transform))


def _check_transform_text(name: str) -> None:
    """Refuse an ITK text transform file whose parameters ITK would misread, before it reads them: a ``Parameters``
    or ``FixedParameters`` value that is not a finite number, or a linear transform with another number of
    ``Parameters`` than its class takes. HDF5 files pass.

    Raises:
        InputError: such a file, or one that cannot be opened.

    See docs/design_notes/io.md.
    """
    try:
        with open(name, "rb") as file:
            if file.read(4) == b"\x89HDF":
                return  # HDF5: its parameters are stored as arrays, not parsed from text
            file.seek(0)
            text = file.read().decode("latin-1")
    except OSError as error:
        raise InputError(f"{name}: cannot be read ({error.strerror or error}); check that it is a transform file you "
                         "may read") from None
    kind = None
    for number, line in enumerate(text.splitlines(), start=1):
        key, _, value = line.partition(":")
        if key.strip() == "Transform":
            kind = value.strip()
        elif key.strip() in ("Parameters", "FixedParameters"):
            try:
                values = [float(token) for token in value.split()]
            except ValueError:
                values = [math.nan]
            if not all(math.isfinite(v) for v in values):
                raise InputError(f"{name}: line {number}: {key.strip()} holds a value that is not a finite number "
                                 f"({value.strip()[:80]!r}); compute and write the transform again")
            expected = _linear_parameter_count(kind) if key.strip() == "Parameters" else None
            if expected is not None and len(values) != expected:
                raise InputError(f"{name}: line {number}: {kind} takes {expected} Parameters, the file gives "
                                 f"{len(values)}; compute and write the transform again")


def _linear_parameter_count(kind: str | None) -> int | None:
    """How many parameters a linear ITK transform class named ``kind`` (``Euler3DTransform_double_3_3``) takes;
    ``None`` for classes whose count depends on the file (B-splines, fields) or that SimpleITK lacks. Fixed
    parameters are not counted: see docs/design_notes/io.md."""
    match = re.fullmatch(r"(\w+?)_(?:double|float)_3_3", (kind or "").strip())
    if match is None:  # another dimension (ReadTransform says so) or an unknown layout
        return None
    factory = getattr(sitk, match.group(1).replace("MatrixOffsetTransformBase", "AffineTransform"), None)
    if not isinstance(factory, type) or not issubclass(factory, sitk.Transform):
        return None
    try:
        instance = factory()
    except (TypeError, RuntimeError):
        try:
            instance = factory(3)
        except (TypeError, RuntimeError):
            return None
    if instance.GetDimension() != 3 or not instance.IsLinear():
        return None
    return len(instance.GetParameters())


def _finite_parameters(transform: sitk.Transform) -> bool:
    """Whether every parameter and fixed parameter of ``transform`` is finite (what reading and writing require)."""
    return bool(np.isfinite(transform.GetParameters()).all() and np.isfinite(transform.GetFixedParameters()).all())
