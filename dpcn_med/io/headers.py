"""One image file, read header first: the checks on what its header says (shape, spacing, origin, direction) and
on the memory its size needs, made before its voxels are read."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.io._common import _INPUT_FORMATS, IMAGE_WRITE_SUFFIXES, _sitk_reason
from dpcn_med.io.integrity import _NIFTI_HEADER_BYTES, _check_complete, _nifti_header_bytes

SPACING_RANGE_MM = (0.01, 100.0)
"""Voxel sizes outside this range are unit mistakes (metres, micrometres) or broken headers, not anatomy."""

WORKING_COPIES = 4
"""float32 copies of a volume alive at once while it is normalised and resampled (estimate for the memory check)."""

GRID_TOLERANCE = 1e-4
"""Relative and absolute tolerance for a mask's spacing and direction against its image's, and for orthonormal
direction cosines; a mask's origin may differ by this relative to the coordinate, but never by a tenth of a voxel."""

MAX_ORIGIN_MM = 1e5
"""Largest coordinate of a volume's origin, mm (100 m): scanner frames lie within metres of their isocentre. See
docs/design_notes/io.md."""


def _read_file(name: str, filename: str, max_bytes: int | None) -> sitk.Image:
    """The image file ``filename`` (a DICOM series' one multi-frame file, or ``name`` itself), messages naming
    ``name``."""
    reader = sitk.ImageFileReader()
    reader.SetFileName(filename)
    try:
        reader.ReadImageInformation()
    except RuntimeError as error:
        if os.path.getsize(filename) == 0:
            raise InputError(f"{name}: is empty (0 bytes); copy or export it again") from None
        header = _nifti_header_bytes(filename)
        if header is not None and header < _NIFTI_HEADER_BYTES:  # a NIfTI cut inside its header
            raise InputError(f"{name}: is truncated (its NIfTI header ends after {header} of {_NIFTI_HEADER_BYTES} "
                             "bytes); copy or export it again") from None
        if "Unable to determine ImageIO reader" in str(error) and filename.lower().endswith(
                (*IMAGE_WRITE_SUFFIXES, ".nhdr", ".mhd")):  # a reader for the name, but not for the content
            raise InputError(f"{name}: its content is in none of the formats read here ({_INPUT_FORMATS}), whatever "
                             "its name says; export it again as one of them") from None
        raise InputError(f"{name}: not a readable image ({_sitk_reason(error)}); expected {_INPUT_FORMATS}") from None
    single_dicom = sitk.ImageFileReader.GetImageIOFromFileName(filename) == "GDCMImageIO"
    _check_shape(name, reader.GetDimension(), reader.GetSize(), reader.GetNumberOfComponents(), single_dicom)
    _check_spacing(name, reader.GetSpacing())
    check_memory(name, reader.GetSize(), max_bytes)
    _check_complete(Path(filename))
    try:
        return reader.Execute()
    except RuntimeError as error:
        raise InputError(f"{name}: the voxels cannot be read ({_sitk_reason(error)}); the file is probably truncated "
                         "or corrupt: copy or export it again") from None


def _check_shape(name: str, dimension: int, size: tuple[int, ...], components: int, single_dicom: bool) -> None:
    if dimension == 4:
        raise InputError(f"{name}: is 4-D (size {size}); extract one volume first (e.g. image[:, :, :, 0] in "
                         "SimpleITK, or fslroi)")
    if dimension == 2:
        raise InputError(f"{name}: is 2-D (size {size}); expected a 3-D volume (2-D slices go to "
                         "dpcn_med.solver.solve2d)")
    if dimension != 3:
        raise InputError(f"{name}: is {dimension}-D (size {size}); expected a 3-D volume")
    if 0 in size:
        raise InputError(f"{name}: holds no voxels (size {size}); export the volume again")
    if 1 in size:
        hint = ("a single DICOM file is one slice: pass the folder holding the whole series" if single_dicom
                else "expected a 3-D volume (2-D slices go to dpcn_med.solver.solve2d)")
        raise InputError(f"{name}: is effectively 2-D (size {size}, one voxel thick along axis {size.index(1)}); "
                         f"{hint}")
    if components != 1:
        raise InputError(f"{name}: has {components} components per voxel (a vector or colour image); expected a "
                         "scalar volume: keep one component first (sitk.VectorIndexSelectionCast)")


def _check_spacing(name: str, spacing: tuple[float, ...]) -> None:
    low, high = SPACING_RANGE_MM
    if not all(math.isfinite(s) for s in spacing):
        problem = "is not finite"
    elif min(spacing) <= 0:
        problem = "must be positive"
    elif min(spacing) < low:
        problem = f"is below {low} mm (micrometres, or a broken header?)"
    elif max(spacing) > high:
        problem = f"is above {high} mm (metres, or a broken header?)"
    else:
        return
    raise InputError(f"{name}: spacing {spacing} mm {problem}; set the voxel size in millimetres "
                     "(image.SetSpacing) and save the volume again")


def _check_origin(name: str, origin: tuple[float, ...]) -> None:
    if not all(math.isfinite(o) for o in origin):
        problem = "is not finite"
    elif max(abs(o) for o in origin) > MAX_ORIGIN_MM:
        problem = f"lies over {MAX_ORIGIN_MM / 1000:g} m from the scanner's origin (a broken header?)"
    else:
        return
    raise InputError(f"{name}: origin {origin} mm {problem}; set the origin in millimetres (image.SetOrigin) and "
                     "save the volume again")


def _check_direction(name: str, direction: tuple[float, ...]) -> None:
    """Refuse sheared or scaled voxel axes: the registration, the resampled output and NIfTI need orthonormal ones."""
    matrix = np.reshape(direction, (3, 3))
    if not np.isfinite(matrix).all():  # NaN passes the orthonormality test below
        raise InputError(f"{name}: its direction cosines {direction} are not finite; set the direction "
                         "(image.SetDirection) and save the volume again")
    error = float(np.abs(matrix.T @ matrix - np.eye(3)).max())
    if error > GRID_TOLERANCE:
        raise InputError(f"{name}: its direction cosines {tuple(round(d, 4) for d in direction)} are not orthonormal "
                         f"(axes sheared or scaled, off by {error:.2g}); resample it onto an orthogonal grid first "
                         "(sitk.Resample onto a grid with the identity direction)")


def check_memory(name: str, size: tuple[int, ...], max_bytes: int | None = None) -> None:
    """Refuse a volume whose float32 working copies would not fit, judged from its size alone (before it is read
    or made)."""
    voxels = math.prod(size)
    needed = voxels * np.dtype(np.float32).itemsize * WORKING_COPIES
    limit = _available_memory() if max_bytes is None else max_bytes
    if limit is not None and needed > limit:
        raise InputError(f"{name}: size {size} ({voxels:,} voxels) needs about {_bytes_text(needed)} of working "
                         f"memory ({WORKING_COPIES} float32 copies), more than the {_bytes_text(limit)} available; "
                         "resample it to a coarser spacing first (e.g. sitk.Resample onto 1 mm voxels: dpcn-med works "
                         "at about 1-2 mm anyway)")


def _available_memory() -> int | None:
    """Bytes of memory available now (Linux MemAvailable, else free pages), or None where neither is known."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def _bytes_text(count: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if count < 1024:
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} PiB"
