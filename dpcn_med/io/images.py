"""Every file the project reads or writes: images, masks, transforms, meshes, JSON and text.

Nothing else in ``dpcn_med`` opens a file. Readers check what they read and raise :class:`InputError`
(:class:`InputNotFoundError` for a missing path) with one line, ``"{path}: {problem}; {fix}"``, which the CLI prints
as it is. Writers go through :func:`atomic_output`: a file appears under its final name complete or not at all.

Convention:
    Physical space is ITK's LPS in millimetres (:mod:`dpcn_med.geometry` owns the frames). Images keep the origin,
    spacing and direction stored in the file; NIfTI stores them as float32, so they round-trip to about 1e-7 there
    and exactly in NRRD and MetaImage.
"""

from __future__ import annotations

import contextlib
import csv
import gzip
import io
import json
import math
import os
import re
import secrets
import signal
import threading
import zlib
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError, InputNotFoundError

if TYPE_CHECKING:
    import pyvista

IMAGE_WRITE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha")
"""Image formats :func:`write_image` writes: one file each, so the atomic rename moves all of it."""
TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")
"""ITK transform files (text or HDF5), readable by SimpleITK, ITK and Slicer."""
MESH_SUFFIXES = (".stl", ".vtk", ".vtp", ".ply", ".obj")
"""Surface meshes and point clouds :func:`read_mesh` reads."""

SPACING_RANGE_MM = (0.01, 100.0)
"""Voxel sizes outside this range are unit mistakes (metres, micrometres) or broken headers, not anatomy."""
WORKING_COPIES = 4
"""float32 copies of a volume alive at once while it is normalised and resampled (estimate for the memory check)."""
GRID_TOLERANCE = 1e-4
"""Relative and absolute tolerance for a mask's spacing and direction against its image's, and for orthonormal
direction cosines; a mask's origin may differ by this relative to the coordinate, but never by a tenth of a voxel."""

_GZIP_MAGIC = b"\x1f\x8b"
_CHUNK = 1 << 20
_NAME_BYTES = 255
"""Longest file name most file systems take (ext4, XFS, APFS, NTFS in UTF-16 units)."""
_INPUT_FORMATS = "NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd) or a folder of DICOM slices"
# Bytes per element of MetaImage's element types (MetaIO's MET_LONG is 32-bit).
_META_ELEMENT_BYTES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
                       "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
                       "MET_DOUBLE": 8}


# ---------------------------------------------------------------------------------------------------------- images
def read_image(path: str | os.PathLike, *, max_bytes: int | None = None) -> sitk.Image:
    """A checked 3-D scalar volume from an image file or a DICOM series folder.

    Args:
        path: .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, or a folder holding one DICOM series (slice files, or one
            multi-frame file); ``FOLDER@SERIES_UID`` picks one series from a folder holding several.
        max_bytes: working memory the volume may take (see :data:`WORKING_COPIES`); default: the memory available
            now.

    Returns:
        The volume with the origin, spacing and direction of the file, pixel type as stored.

    Raises:
        InputNotFoundError: the path does not exist.
        InputError: the file is unreadable, truncated, not a 3-D scalar volume, has an absurd spacing or sheared
            axes, is a DICOM series with unevenly spaced or tilted slices or of several multi-frame files, is a
            NIfTI whose qform and sform disagree, would not fit in memory, holds NaN or infinite voxels, or is
            constant.
    """
    name = os.fspath(path)
    return check_volume(_read_volume(name, max_bytes), name)


_LABEL_MAP_PIXELS = (sitk.sitkLabelUInt8, sitk.sitkLabelUInt16, sitk.sitkLabelUInt32, sitk.sitkLabelUInt64)
"""SimpleITK's run-length label maps: ``GetArrayFromImage`` on one aborts the process (SIGABRT), not raises."""


def check_volume(image: sitk.Image, name: str = "image") -> sitk.Image:
    """``image`` itself if it is a usable volume (:func:`read_image`'s checks, for images made in memory).

    Args:
        image: the volume.
        name: what to call it in messages (its file, or "fixed image").

    Raises:
        InputError: not a 3-D scalar real-valued volume (a label map included), an absurd spacing, sheared axes,
            NaN or infinite voxels, or constant.
    """
    if image.GetPixelID() in _LABEL_MAP_PIXELS:  # before any voxel access: SimpleITK aborts the process on one
        raise InputError(f"{name}: is a label map ({image.GetPixelIDTypeAsString()}); expected an intensity volume "
                         "(convert a segmentation with sitk.LabelMapToLabel)")
    _check_shape(name, image.GetDimension(), image.GetSize(), image.GetNumberOfComponentsPerPixel(), False)
    if image.GetPixelID() in (sitk.sitkComplexFloat32, sitk.sitkComplexFloat64):
        raise InputError(f"{name}: has complex voxels; expected a real-valued volume (keep the magnitude: "
                         "sitk.ComplexToModulus)")
    if image.GetNumberOfComponentsPerPixel() == 1 and "vector" in image.GetPixelIDTypeAsString():
        raise InputError(f"{name}: is a vector image of one component ({image.GetPixelIDTypeAsString()}); expected "
                         "a scalar volume: sitk.VectorIndexSelectionCast(image, 0)")
    _check_spacing(name, image.GetSpacing())
    _check_origin(name, image.GetOrigin())
    _check_direction(name, image.GetDirection())
    array = sitk.GetArrayViewFromImage(image)  # a view: ``image`` must stay referenced while it is used
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all():
            nan = int(np.isnan(array).sum())
            infinite = array.size - int(finite.sum()) - nan
            raise InputError(f"{name}: holds {nan} NaN and {infinite} infinite voxels out of {array.size}; replace "
                             "them (e.g. numpy.nan_to_num) and save the volume again")
    low, high = array.min(), array.max()
    if low == high:
        raise InputError(f"{name}: all voxels equal {low.item():g}; the volume is blank: check that the right file "
                         "was exported")
    return image


def read_mask(path: str | os.PathLike, image: sitk.Image, *, role: str = "mask",
              max_bytes: int | None = None) -> sitk.Image:
    """A binary mask on the voxel grid of ``image``.

    Args:
        path: mask file, any format :func:`read_image` reads.
        image: the volume the mask belongs to.
        role: what the mask is, for messages ("fixed mask").
        max_bytes: as in :func:`read_image`.

    Returns:
        sitkUInt8 image, 1 inside and 0 outside, with exactly the origin, spacing and direction of ``image`` (the
        file's may differ within :data:`GRID_TOLERANCE`).

    Raises:
        InputError: the file is unusable as in :func:`read_image`, or the mask is on another grid, empty, or holds
            more than two values.
    """
    name = os.fspath(path)
    return check_mask(_read_volume(name, max_bytes), image, name, role=role)


def check_mask(mask: sitk.Image, image: sitk.Image, name: str = "mask", *, role: str = "mask") -> sitk.Image:
    """:func:`read_mask`'s checks and result for a mask made in memory; ``name`` is what messages call it.

    A label map (``sitk.sitkLabelUInt8`` etc.) is converted to its label image first.

    Raises:
        InputError: not a 3-D scalar volume, on another grid than ``image``, empty, or more than two values.
    """
    if mask.GetPixelID() in _LABEL_MAP_PIXELS:  # its voxels cannot be read as an array: SimpleITK would abort
        mask = sitk.LabelMapToLabel(mask)
    _check_shape(name, mask.GetDimension(), mask.GetSize(), mask.GetNumberOfComponentsPerPixel(), False)
    _check_same_grid(name, role, mask, image)
    array = sitk.GetArrayViewFromImage(mask)  # ``mask`` stays referenced while the view is used
    values = np.unique(array)
    if values.size == 1 and values[0] == 0:
        raise InputError(f"{name}: {role} is empty (every voxel is 0); give a mask with foreground or leave it out")
    if values.size == 1:
        raise InputError(f"{name}: {role} has no background (every voxel is {values[0]:g}); expected 0 outside and "
                         "one value inside")
    if values.size > 2 or values[0] != 0:
        shown = ", ".join(f"{v:g}" for v in values[:6]) + (f" and {values.size - 6} more" if values.size > 6 else "")
        raise InputError(f"{name}: {role} is not binary: found {values.size} distinct values ({shown}); expected 0 "
                         "outside and one value inside (for a label map, keep one label: sitk.BinaryThreshold)")
    binary = sitk.GetImageFromArray((array != 0).astype(np.uint8))
    binary.CopyInformation(image)  # snap the tolerated differences so later filters see one grid
    return binary


def image_summary(image: sitk.Image) -> dict[str, Any]:
    """Geometry and intensity range of a 3-D volume, for ``dpcn-med info``.

    Returns:
        ``size``, ``spacing`` (mm), ``origin`` (mm, LPS) as tuples, ``direction`` as a 3x3 nested list (columns are
        the voxel axes), ``orientation`` (three letters, e.g. "LPS"), ``pixel_type``, ``extent_mm`` (size x spacing,
        voxel edge to voxel edge), ``voxels``, and ``intensity_min``, ``intensity_max``, ``intensity_p1``,
        ``intensity_p99`` as floats.

    Raises:
        InputError: ``image`` is not a 3-D scalar volume.
    """
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"image is {image.GetDimension()}-D with {image.GetNumberOfComponentsPerPixel()} "
                         "component(s) per voxel; a summary needs a 3-D scalar volume")
    array = sitk.GetArrayViewFromImage(image)
    p1, p99 = np.percentile(array, [1.0, 99.0])
    return {
        "size": image.GetSize(),
        "spacing": image.GetSpacing(),
        "origin": image.GetOrigin(),
        "direction": np.reshape(image.GetDirection(), (3, 3)).tolist(),
        "orientation": sitk.DICOMOrientImageFilter.GetOrientationFromDirectionCosines(image.GetDirection()),
        "pixel_type": image.GetPixelIDTypeAsString(),
        "extent_mm": tuple(n * s for n, s in zip(image.GetSize(), image.GetSpacing())),
        "voxels": math.prod(image.GetSize()),
        "intensity_min": float(array.min()),
        "intensity_max": float(array.max()),
        "intensity_p1": float(p1),
        "intensity_p99": float(p99),
    }


def _read_volume(name: str, max_bytes: int | None) -> sitk.Image:
    """The volume at ``name`` after every check that does not look at voxel values."""
    folder, uid = _split_series(name)
    if folder is not None:
        return _read_dicom(name, folder, uid, max_bytes)
    if not os.path.exists(name):
        raise InputNotFoundError(f"{name}: not found (no such file or folder); check the path")
    if os.path.isdir(name):
        return _read_dicom(name, Path(name), None, max_bytes)
    return _read_file(name, name, max_bytes)


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


_NIFTI_HEADER_BYTES = 348
"""Length of a NIfTI-1 header."""


def _nifti_header_bytes(filename: str) -> int | None:
    """How many of a NIfTI header's bytes ``filename`` (named .nii or .nii.gz) holds, up to 348; ``None`` for
    other names and for a .gz that is not gzip."""
    lower = filename.lower()
    if not lower.endswith((".nii", ".nii.gz")):
        return None
    if lower.endswith(".gz"):
        with open(filename, "rb") as stream:
            if stream.read(2) != _GZIP_MAGIC:  # not gzip at all: not a cut NIfTI either
                return None
    found = b""
    with contextlib.suppress(OSError, EOFError, zlib.error):  # a cut or corrupt gzip stream: what came before counts
        with (gzip.open(filename, "rb") if lower.endswith(".gz") else open(filename, "rb")) as stream:
            while len(found) < _NIFTI_HEADER_BYTES:
                chunk = stream.read(_NIFTI_HEADER_BYTES - len(found))
                if not chunk:
                    break
                found += chunk
    return len(found)


def _split_series(name: str) -> tuple[Path | None, str | None]:
    """``(folder, uid)`` for an existing ``FOLDER@UID``, else ``(None, None)``."""
    if "@" not in name or os.path.exists(name):
        return None, None
    folder, _, uid = name.rpartition("@")
    return (Path(folder), uid) if os.path.isdir(folder) else (None, None)


@contextlib.contextmanager
def _itk_warnings_off() -> Iterator[None]:
    """ITK's warnings (several lines on stderr each) off: what they report, the caller checks and says itself."""
    shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(shown)


def _read_dicom(name: str, folder: Path, uid: str | None, max_bytes: int | None) -> sitk.Image:
    with _itk_warnings_off():  # no series, or uneven slices (checked below)
        return _read_series(name, folder, uid, max_bytes)


def _read_series(name: str, folder: Path, uid: str | None, max_bytes: int | None) -> sitk.Image:
    series = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    if not series:
        count = sum(1 for entry in folder.iterdir() if entry.is_file())
        raise InputError(f"{name}: is a folder holding no DICOM series ({count} files); expected {_INPUT_FORMATS}")
    files = {s: sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), s) for s in series}
    if uid is None and len(series) > 1:
        raise InputError(f"{name}: holds {len(series)} DICOM series: {_series_listing(files)}; choose one as "
                         f"{folder}@UID")
    if uid is None:
        uid = series[0]
    elif uid not in files:
        raise InputError(f"{name}: {folder} holds no DICOM series with UID {uid}; it holds "
                         f"{_series_listing(files)}; choose one as {folder}@UID")
    try:
        frame_size = _file_information(files[uid][0]).GetSize()
    except RuntimeError as error:
        raise InputError(f"{name}: DICOM series {uid} cannot be read ({_sitk_reason(error)}); check that its "
                         "files are complete") from None
    if len(frame_size) == 3 and frame_size[2] > 1:  # enhanced (multi-frame) DICOM: one file holds the whole volume
        if len(files[uid]) == 1:
            return _read_file(name, files[uid][0], max_bytes)
        raise InputError(f"{name}: DICOM series {uid} is {len(files[uid])} multi-frame files of {frame_size[2]} "
                         "frames each (volumes or time points, which ITK would stack as 4-D); pass one file's path")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files[uid])
    reader.MetaDataDictionaryArrayUpdateOn()
    try:
        check_memory(name, (*frame_size[:2], len(files[uid])), max_bytes)
        image = reader.Execute()
    except RuntimeError as error:
        raise InputError(f"{name}: DICOM series {uid} cannot be read ({_sitk_reason(error)}); check that its "
                         "files are complete") from None
    _check_shape(name, image.GetDimension(), image.GetSize(), image.GetNumberOfComponentsPerPixel(), False)
    _check_spacing(name, image.GetSpacing())
    _check_slice_positions(name, reader, image)
    return image


def _check_slice_positions(name: str, reader: sitk.ImageSeriesReader, image: sitk.Image) -> None:
    """Refuse a series whose slices are not where ITK stacks them: off the evenly spaced line that fits their Image
    Positions best (a missing slice, or two acquisitions mixed: ITK only warns and stacks the slices at their mean
    spacing, which stretches the volume), or stepping off the slice normal (a gantry tilt: ITK stacks them along the
    normal, unsheared, silently).

    Fitting the whole series, rather than comparing neighbours, keeps the positions' rounding (often to 0.01 mm in
    the files) from reading as uneven or tilted slices.
    """
    key = "0020|0032"  # Image Position (Patient)
    count = image.GetSize()[2]
    if count < 2 or not all(reader.HasMetaDataKey(i, key) for i in range(count)):
        return  # without positions (e.g. secondary captures) ITK stacks the slices as given; nothing to compare
    try:
        positions = np.array([[float(v) for v in reader.GetMetaData(i, key).split("\\")] for i in range(count)])
    except ValueError:
        return
    normal = np.reshape(image.GetDirection(), (3, 3))[:, 2]
    index = np.arange(count)
    (first, stride), *_ = np.linalg.lstsq(np.stack([np.ones(count), index], 1), positions, rcond=None)
    along = float(stride @ normal)
    off = np.linalg.norm(positions - first - index[:, None] * stride, axis=1)
    if off.max() > max(0.1 * abs(along), 0.1):
        steps = np.diff(positions, axis=0) @ normal
        typical = float(np.median(steps))
        uneven = np.flatnonzero(np.abs(steps - typical) > 0.1 * abs(typical))
        worst = int(off.argmax())
        detail = (f"{steps[uneven[0]]:.3g} mm between slices {uneven[0] + 1} and {uneven[0] + 2}, {typical:.3g} mm "
                  f"elsewhere ({uneven.size} uneven gap(s))" if uneven.size else
                  f"slice {worst + 1} lies {off[worst]:.3g} mm from where an evenly spaced stack puts it")
        raise InputError(f"{name}: its {count} slices are not evenly spaced along one line: {detail}; a slice is "
                         "missing or the folder mixes acquisitions: export the whole series again")
    sideways = float(np.linalg.norm(stride - along * normal))
    spread = sideways * (count - 1)
    if sideways > 0.01 * abs(along) and spread > 0.1:
        tilt = math.degrees(math.atan2(sideways, abs(along)))
        raise InputError(f"{name}: its slices are sheared, each {sideways:.3g} mm off the slice normal from the one "
                         f"before (a gantry tilt of {tilt:.3g} degrees); read as a stack they would be misplaced by "
                         f"up to {spread:.3g} mm: resample the series onto an orthogonal grid first (dcm2niix "
                         "corrects the tilt; so does Slicer's DICOM import with acquisition geometry regularization)")


def _file_information(filename: str) -> sitk.ImageFileReader:
    reader = sitk.ImageFileReader()
    reader.SetFileName(filename)
    reader.ReadImageInformation()
    return reader


def _series_listing(files: dict[str, tuple[str, ...]]) -> str:
    """``UID (N files, 'description')`` for each series, joined by "; "."""
    entries = []
    for uid, names in files.items():
        try:
            reader = _file_information(names[0])
            description = reader.GetMetaData("0008|103e").strip() if reader.HasMetaDataKey("0008|103e") else ""
        except RuntimeError:  # the description only helps to choose; a series without a readable one still lists
            description = ""
        entries.append(f"{uid} ({len(names)} files" + (f", {description!r})" if description else ")"))
    return "; ".join(entries)


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


MAX_ORIGIN_MM = 1e5
"""Largest coordinate of a volume's origin, mm (100 m): scanner frames lie within metres of their isocentre. A NaN
origin hung the foreground search; one of 1e9 mm left float64 too few digits for the pose (48 mm off)."""


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


# ------------------------------------------------------------------------------------------------------ truncation
def _check_complete(path: Path) -> None:
    """Raise if the file holds fewer voxel bytes than its header promises.

    SimpleITK 2.5 reads a truncated .nii or .nii.gz without an error and fills the missing voxels with zeros, and
    reports a truncated MetaImage as "No such file or directory"; NRRD's reader says what is missing itself.
    """
    lower = path.name.lower()
    if lower.endswith(".nii.gz"):
        sibling = path.with_name(path.name[:-3])
        if sibling.exists():
            # Measured: ITK's NIfTI reader given X.nii.gz opens X.nii when both exist.
            raise InputError(f"{path}: {sibling.name} lies beside it and SimpleITK would read that file instead; "
                             "rename or move one of the two")
        with open(path, "rb") as stream:
            if stream.read(2) != _GZIP_MAGIC:  # "corrupt, copy it again" would send the user for the same file
                raise InputError(f"{path}: is not gzip-compressed although its name ends in .gz (a browser or server "
                                 f"may have unpacked it); rename it to {path.name[:-3]}")
        _check_nifti(path, compressed=True)
    elif lower.endswith(".nii"):
        _check_nifti(path, compressed=False)
    elif lower.endswith((".mha", ".mhd")):
        _check_metaimage(path)
    elif lower.endswith((".hdr", ".img")):
        _check_analyze(path)


def _check_nifti(path: Path, *, compressed: bool) -> None:
    """Raise if a NIfTI file is truncated or holds non-finite voxels.

    Both go unnoticed otherwise: SimpleITK 2.5 zero-fills the missing voxels and reads NaN and infinite voxels as 0
    (measured).
    """
    import nibabel  # imported here: only NIfTI files need it

    try:
        loaded = nibabel.load(path)  # reads the header only
        proxy = loaded.dataobj
        # The header as stored: nibabel's checks on loading turn a voxel size of 0 into 1, as SimpleITK does.
        with (gzip.open(path, "rb") if compressed else open(path, "rb")) as stream:
            zooms = tuple(float(z) for z in type(loaded.header).from_fileobj(stream, check=False)["pixdim"][1:4])
    except (nibabel.filebasedimages.ImageFileError, OSError, ValueError, EOFError):
        # nibabel refuses a few headers ITK accepts, and SimpleITK's own read then has the last word; but a stream
        # cut inside its header is refused by nibabel too, and SimpleITK would zero-fill it (measured: 300 bytes).
        if compressed:
            _scan_nifti(path, compressed, 0, None, 0)
        return
    if 0 in zooms:  # SimpleITK reads a voxel size of 0 as 1 mm (measured), silently
        raise InputError(f"{path}: its header gives voxel size {zooms} mm (pixdim); set the spacing in millimetres "
                         "(image.SetSpacing) and save the volume again")
    _check_nifti_forms(path, loaded.header, (*loaded.shape, 1, 1)[:3])
    # The proxy's offset, not the header's vox_offset, which nibabel zeroes on loading.
    offset, dtype, voxels = int(proxy.offset), proxy.dtype, math.prod(proxy.shape)
    needed = offset + voxels * dtype.itemsize
    nan = infinite = 0
    if not compressed and dtype.kind != "f":
        found = path.stat().st_size
    else:
        found, nan, infinite = _scan_nifti(path, compressed, offset, dtype if dtype.kind == "f" else None, needed)
    if found < needed:
        raise _truncated(path, f"it holds {found:,} bytes, the header needs {needed:,}")
    if nan or infinite:
        raise InputError(f"{path}: holds {nan} NaN and {infinite} infinite voxels out of {voxels}; replace them "
                         "(e.g. numpy.nan_to_num) and save the volume again (SimpleITK would read them as 0)")


def _check_analyze(path: Path) -> None:
    """Raise if the voxel file of a ``.hdr`` / ``.img`` pair (Analyze, or NIfTI as a pair) is missing or shorter than
    its header needs: SimpleITK reads a cut ``.img`` zero-filled, with no error (measured: half the voxels 0)."""
    import nibabel  # imported here: only these files need it

    voxels = path.with_suffix(".img")
    if not voxels.exists():
        raise InputError(f"{path}: its voxel file {voxels} is missing; keep {voxels.name} beside the header")
    try:
        proxy = nibabel.load(path.with_suffix(".hdr")).dataobj
    except (nibabel.filebasedimages.ImageFileError, OSError, ValueError, EOFError):
        return  # SimpleITK's own read has the last word, as for a NIfTI header nibabel refuses
    needed = int(proxy.offset) + math.prod(proxy.shape) * proxy.dtype.itemsize
    found = voxels.stat().st_size
    if found < needed:
        raise _truncated(voxels, f"it holds {found:,} bytes, the header {path.with_suffix('.hdr').name} needs "
                                 f"{needed:,}")


def _check_nifti_forms(path: Path, header: Any, shape: tuple[int, ...]) -> None:
    """Refuse a NIfTI header whose qform and sform are both set but place the volume differently: readers disagree
    on which wins (measured: SimpleITK took the qform, nibabel, and so the tools built on it, the sform, 36 mm
    apart), so any result would be right for one and wrong for the other.

    Each corner of the grid may be off by 0.1 mm plus 2 mrad of its distance from voxel 0: the qform's rotation is a
    float32 quaternion, and for an oblique volume saved from LPS (a rotation near 180 degrees) writers' own rounding
    tilts it by up to 1.2 mrad (measured, SimpleITK; 0.43 mm at the far corner of a 360 x 360 x 300 mm grid).
    """
    qform, q_code = header.get_qform(coded=True)
    sform, s_code = header.get_sform(coded=True)
    if not (q_code and s_code):
        return
    corners = np.array([[i, j, k, 1] for i in (0, shape[0] - 1) for j in (0, shape[1] - 1) for k in (0, shape[2] - 1)])
    apart = np.linalg.norm((corners @ (qform - sform).T)[:, :3], axis=1)
    reach = np.linalg.norm(corners[:, :3] @ sform[:3, :3].T, axis=1)
    if np.any(apart > 0.1 + 2e-3 * reach):
        names = {1: "scanner", 2: "aligned", 3: "Talairach", 4: "MNI", 5: "template"}
        raise InputError(f"{path}: its header's qform (code {q_code}, {names.get(int(q_code), 'unknown')}) and sform "
                         f"(code {s_code}, {names.get(int(s_code), 'unknown')}) place the volume up to "
                         f"{apart.max():.3g} mm apart, and readers differ on which wins; make them agree (nibabel: "
                         "image.set_qform(image.get_sform()) or the reverse, or fslorient) and save the volume again")


def _scan_nifti(path: Path, compressed: bool, offset: int, dtype: np.dtype | None, needed: int) -> tuple[int, int, int]:
    """Stream through a NIfTI file: ``(bytes found, NaN voxels, infinite voxels)``; counts only if ``dtype`` is set.

    A chunk at a time, so a volume is never held twice in memory.
    """
    found = nan = infinite = 0
    pending = b""
    try:
        with (gzip.open(path, "rb") if compressed else open(path, "rb")) as stream:
            # read1: a piece at a time, so ``found`` counts what a truncated stream held before it ended
            while chunk := stream.read1(_CHUNK):
                voxel_bytes = chunk[max(offset - found, 0):max(needed - found, 0)]
                found += len(chunk)
                if dtype is None:
                    continue
                data = pending + voxel_bytes
                whole = len(data) - len(data) % dtype.itemsize
                values = np.frombuffer(data, dtype, count=whole // dtype.itemsize)
                nan += int(np.isnan(values).sum())
                infinite += int(np.isinf(values).sum())
                pending = data[whole:]
    except EOFError:
        if needed and found >= needed:  # the voxels are all there, the stream's end (its checksum) is not
            raise _truncated(path, f"its compressed stream breaks off after {found:,} bytes, all the {needed:,} the "
                                   "header needs but before its end") from None
        detail = f"of the {needed:,} bytes the header needs" if needed else "before the end of its header"
        raise _truncated(path, f"its compressed stream ends after {found:,} bytes, {detail}") from None
    except (zlib.error, gzip.BadGzipFile) as error:
        raise InputError(f"{path}: the compressed data is corrupt ({error}); copy or export it again") from None
    return found, nan, infinite


def _check_metaimage(path: Path) -> None:
    fields, data_offset = _metaimage_header(path)
    data_file = fields.get("ElementDataFile", "")
    element_bytes = _META_ELEMENT_BYTES.get(fields.get("ElementType", ""))
    # ASCII data, slices listed in several files, and unknown types have no byte count to check.
    if (fields.get("BinaryData", "True").lower() != "true" or element_bytes is None or not data_file
            or data_file.upper().startswith("LIST") or "%" in data_file):
        return
    if data_file.upper() == "LOCAL":
        source = path
    else:
        source = path.parent / data_file
        data_offset = int(fields.get("HeaderSize", "0"))
        if not source.exists():
            raise InputError(f"{path}: its voxel file {source} is missing; keep {data_file} beside the header")
        if data_offset < 0:  # HeaderSize = -1: the voxels are the file's last bytes, so its size proves nothing
            return
    needed = math.prod(int(n) for n in fields.get("DimSize", "").split()) * element_bytes
    needed *= int(fields.get("ElementNumberOfChannels", "1"))
    if fields.get("CompressedData", "False").lower() == "true":
        try:
            found, complete = _inflated_length(source, data_offset)
        except zlib.error as error:  # was an uncaught internal error
            raise InputError(f"{path}: the compressed voxel data is corrupt ({error}); copy or export it again"
                             ) from None
        if not complete:
            raise _truncated(path, f"its compressed voxel stream ends after {found:,} of {needed:,} bytes")
    else:
        found = source.stat().st_size - data_offset
    if found < needed:
        raise _truncated(path, f"it holds {max(found, 0):,} voxel bytes, the header needs {needed:,}")


def _metaimage_header(path: Path) -> tuple[dict[str, str], int]:
    """The ``Key = Value`` fields of a MetaImage header and the byte offset just after it."""
    fields: dict[str, str] = {}
    with open(path, "rb") as stream:
        while line := stream.readline(4096):
            key, _, value = line.decode("latin-1").partition("=")
            fields[key.strip()] = value.strip()
            if key.strip() == "ElementDataFile":  # always the last field; the voxels of a .mha follow it
                break
        return fields, stream.tell()


def _inflated_length(path: Path, offset: int) -> tuple[int, bool]:
    """Bytes a zlib stream starting at ``offset`` inflates to, and whether the stream ends properly."""
    inflater = zlib.decompressobj()
    found = 0
    with open(path, "rb") as stream:
        stream.seek(offset)
        while (data := stream.read(_CHUNK)) and not inflater.eof:
            # Bounded output per call (a run of zeros inflates a thousandfold); a full output may leave more pending.
            while output := inflater.decompress(data, _CHUNK):
                found += len(output)
                data = inflater.unconsumed_tail
    return found, inflater.eof


def _truncated(path: Path, detail: str) -> InputError:
    return InputError(f"{path}: is truncated ({detail}); the copy or download was cut short: copy it again")


def _sitk_reason(error: RuntimeError) -> str:
    """The informative line of a SimpleITK exception, without source locations and object addresses."""
    lines = []
    for line in str(error).splitlines():
        line = re.sub(r"^(sitk::ERROR:|ITK ERROR: [^:]*\(0x[0-9a-fA-F]+\):)", "", line.strip()).strip()
        if line and not line.startswith("Exception thrown in SimpleITK"):
            lines.append(line)
    # Teem (NRRD) nests its messages; the innermost, last one says what went wrong.
    teem = [detail for line in lines if line.startswith("[nrrd]")
            if (detail := line.split(":", 1)[-1].strip()) and detail != "trouble"]
    if teem:
        return teem[-1]
    return lines[0] if lines else type(error).__name__


# ----------------------------------------------------------------------------------------------------- masks, grids
def _check_same_grid(name: str, role: str, mask: sitk.Image, image: sitk.Image) -> None:
    same_size = mask.GetSize() == image.GetSize()
    differing = [label for label, ours, theirs in (("spacing", mask.GetSpacing(), image.GetSpacing()),
                                                   ("direction", mask.GetDirection(), image.GetDirection()))
                 if not np.allclose(ours, theirs, rtol=GRID_TOLERANCE, atol=GRID_TOLERANCE)]
    # Relative for float32 storage (NIfTI) of large coordinates, but never a tenth of a voxel.
    slack = np.minimum(GRID_TOLERANCE * (1 + np.abs(image.GetOrigin())), 0.1 * min(image.GetSpacing()))
    if (np.abs(np.subtract(mask.GetOrigin(), image.GetOrigin())) > slack).any():
        differing.append("origin")
    if same_size and not differing:
        return
    def rounded(values: tuple[float, ...]) -> str:  # 16-digit floats made the message 700 characters long
        return f"({', '.join(f'{v:.6g}' for v in values)})"

    shown = [f"size {mask.GetSize()} vs {image.GetSize()}",
             f"spacing {rounded(mask.GetSpacing())} vs {rounded(image.GetSpacing())}"]
    if "origin" in differing:
        shown.append(f"origin {rounded(mask.GetOrigin())} vs {rounded(image.GetOrigin())}")
    if "direction" in differing:
        shown.append(f"direction {rounded(mask.GetDirection())} vs {rounded(image.GetDirection())}")
    raise InputError(f"{name}: {role} is not on its image's voxel grid ({', '.join(shown)}, {role} vs image); "
                     "resample it onto the image with nearest-neighbour interpolation: sitk.Resample(mask, image, "
                     "sitk.Transform(), sitk.sitkNearestNeighbor)")


# ------------------------------------------------------------------------------------------------------ transforms
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


def _check_transform_text(name: str) -> None:
    """Refuse an ITK text transform file whose parameters ITK would misread, before it reads them.

    ITK stops at the first token of a ``Parameters:`` line that is not a number (``nan``, ``abc``) and keeps what it
    read; when a linear transform then has fewer parameters than its class, it reads past them, and the process dies
    of heap corruption ("corrupted size vs. prev_size"), or goes on with values from uninitialised memory.
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
    ``None`` for classes whose count depends on the file (B-splines, fields) or that SimpleITK lacks. (Fixed
    parameters are left to ITK, which refuses too few and takes 3 or 4 for Euler3DTransform.)"""
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


# ---------------------------------------------------------------------------------------------------------- writers
@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` that becomes ``path`` when the block succeeds.

    The temporary name keeps the full suffix (``x.nii.gz`` -> ``.x.tmp1a2b3c4d.nii.gz``), so writers that choose the
    format by extension work on it. On success it is renamed onto ``path`` (``os.replace``, atomic within one
    folder); on any exception, Ctrl-C included, it is removed and ``path`` is left as it was.

    Raises:
        InputError: the folder of ``path`` does not exist (creating it is the caller's choice).

    Example:
        >>> with atomic_output("out/report.png") as temporary:  # doctest: +SKIP
        ...     figure.savefig(temporary)
    """
    target = Path(path)
    if not target.parent.is_dir():
        raise InputError(f"{target}: folder {target.parent} does not exist; create it first")
    suffix = _full_suffix(target.name)
    stem = target.name[:len(target.name) - len(suffix)]
    # The stem shortened as needed: a target name within the file system's 255 bytes gave a temporary name beyond
    # them (its 14 more bytes), and the write failed with "File name too long".
    room = _NAME_BYTES - len(f"..tmp{secrets.token_hex(4)}{suffix}".encode())
    stem = stem.encode()[:max(room, 1)].decode(errors="ignore")
    temporary = target.with_name(f".{stem}.tmp{secrets.token_hex(4)}{suffix}")
    try:
        yield temporary
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM (which the command line turns into ``KeyboardInterrupt``) until the block ends, then
    raise: for outputs that must change together (a checkpoint's two files, a registration's set of files). Outside
    the main thread, where Python delivers no signal and handlers cannot be set, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    signals = (signal.SIGINT, signal.SIGTERM)
    previous = [signal.signal(number, lambda number, frame: received.append(number)) for number in signals]
    try:
        yield
    finally:
        for number, handler in zip(signals, previous, strict=True):
            signal.signal(number, handler)
    if received:
        raise KeyboardInterrupt


def _full_suffix(name: str) -> str:
    """``.nii.gz`` for ``x.nii.gz``, ``.tfm`` for ``a.b.tfm``: the suffix a writer picks its format by."""
    suffixes = Path(name).suffixes
    if len(suffixes) >= 2 and suffixes[-1].lower() == ".gz":
        return "".join(suffixes[-2:])
    return suffixes[-1] if suffixes else ""


def write_image(image: sitk.Image, path: str | os.PathLike, *, compress: bool = True) -> None:
    """Write ``image`` atomically as .nii.gz, .nii, .nrrd or .mha (geometry as in :mod:`dpcn_med.io`'s Convention).

    Args:
        image: any SimpleITK image.
        path: destination; its folder must exist.
        compress: compress the voxels (gzip or zlib) where the format allows.

    Raises:
        InputError: another suffix, or the folder does not exist.
        OSError: the file came out short (a full disk, a file-size limit); ``path`` is left as it was.
    """
    target = Path(path)
    _check_write_suffix(target, IMAGE_WRITE_SUFFIXES, "an image", " (.mhd and .nhdr keep the voxels in a second "
                        "file, which one rename cannot move)")
    with atomic_output(target) as temporary:
        sitk.WriteImage(image, str(temporary), useCompression=compress)
        _check_written(target, lambda: _check_nifti_length(temporary))


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


def _check_write_suffix(target: Path, suffixes: tuple[str, ...], what: str, note: str = "") -> None:
    """Refuse a suffix SimpleITK has no writer for; it picks the writer by the suffix as spelt (``.MHA`` has none)."""
    if not target.name.endswith(suffixes):
        case = " in lower case" if target.name.lower().endswith(suffixes) else ""
        raise InputError(f"{target}: cannot write {what} with this suffix; use {', '.join(suffixes)}{case}{note}")


def _check_written(target: Path, check: Callable[[], None]) -> None:
    """Run ``check`` on the file just written for ``target``; raise ``OSError`` if it finds the file short.

    ITK's NIfTI and text-transform writers report a full disk or a file-size limit on stderr only and return as if
    all went well (measured with ``ulimit -f``: a cut .nii.gz, .nii and .tfm, no exception; the NRRD, MetaImage and
    HDF5 writers raise), so what they wrote is read back before it replaces anything.
    """
    try:
        check()
    except InputError as error:
        raise OSError(f"{target}: writing it failed: the file came out incomplete (is the disk full, or a file-size "
                      "limit set?); nothing was written") from error


def _check_nifti_length(path: Path) -> None:
    """Raise ``InputError`` if a NIfTI file just written holds fewer bytes than its header needs.

    A .nii.gz is judged by its gzip trailer (its last 4 bytes: the inflated length modulo 2^32; a cut stream ends in
    arbitrary bytes), not inflated again: reading back a 128 MiB CT that way added 46% to the write (measured). The
    NRRD and MetaImage writers raise on a short write themselves.
    """
    lower = path.name.lower()
    if not lower.endswith((".nii", ".nii.gz")):
        return
    import nibabel  # imported here: only NIfTI files need it

    try:
        proxy = nibabel.load(path).dataobj  # the header only
        needed = int(proxy.offset) + math.prod(proxy.shape) * proxy.dtype.itemsize
        if lower.endswith(".nii"):
            complete = path.stat().st_size >= needed
        else:
            with open(path, "rb") as stream:
                stream.seek(-4, os.SEEK_END)
                complete = int.from_bytes(stream.read(4), "little") == needed % 2 ** 32
    except (nibabel.filebasedimages.ImageFileError, OSError, ValueError, EOFError) as error:
        raise InputError(f"{path}: its header does not read back ({error})") from None
    if not complete:
        raise InputError(f"{path}: holds fewer bytes than its header needs ({needed:,})")


def _check_same_transform(path: Path, transform: sitk.Transform) -> None:
    """Raise ``InputError`` if ``path`` does not read back as ``transform``'s parameters (to text precision)."""
    try:
        written = sitk.ReadTransform(str(path))
    except RuntimeError as error:
        raise InputError(f"{path}: unreadable ({_sitk_reason(error)})") from None
    for found, expected in ((written.GetParameters(), transform.GetParameters()),
                            (written.GetFixedParameters(), transform.GetFixedParameters())):
        if len(found) != len(expected) or not np.allclose(found, expected, rtol=1e-9, atol=1e-12):
            raise InputError(f"{path}: holds other parameters than the transform written")


def write_json(data: Any, path: str | os.PathLike) -> None:
    """Write ``data`` as indented JSON (numpy scalars and arrays, and paths, converted), atomically."""
    write_text(json.dumps(data, indent=2, default=_json_value) + "\n", path)


def _json_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_text(text: str, path: str | os.PathLike) -> None:
    """Write ``text`` as UTF-8, newlines untranslated, atomically."""
    with atomic_output(path) as temporary, open(temporary, "w", encoding="utf-8", newline="") as stream:
        stream.write(text)


def write_csv(rows: list[dict], path: str | os.PathLike, columns: list[str] | None = None) -> None:
    """``rows`` as a CSV table with a header, ``\n`` line ends, atomically: the columns are ``columns`` (other keys
    ignored) or the first row's keys.

    Raises:
        ValueError: no ``rows`` and no ``columns``: there is no header to write.
    """
    if not rows and not columns:
        raise ValueError(f"{path}: no rows and no columns: nothing to write a header from")
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns or list(rows[0]), lineterminator="\n",
                            extrasaction="ignore" if columns else "raise")
    writer.writeheader()
    writer.writerows(rows)
    write_text(buffer.getvalue(), path)


def read_csv(path: str | os.PathLike, columns: dict[str, Callable[[str], Any]], *,
             allowed: Collection[str] | None = None) -> list[tuple[int, dict]]:
    """The rows of a CSV table with a header (as :func:`write_csv` writes it), each with the line it ends on, each
    value of ``columns`` converted by its type (``{"trial": int, "tre_mm": float}``); other columns stay strings, and
    a short row's missing cells are ``None``. Blank lines are skipped, before the header too.

    Args:
        allowed: the only columns the table may have (with ``columns``); ``None``: any.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not CSV, a column of ``columns`` is missing, a column is named twice or is not ``allowed``, a
            row has more cells than the header (an unquoted comma), or a value does not convert (the message names
            the line).
    """
    name = os.fspath(path)
    try:
        # utf-8-sig: spreadsheets save "CSV UTF-8" with a byte-order mark
        reader = csv.reader(io.StringIO(read_text(name, encoding="utf-8-sig"), newline=""))
        lines = [(reader.line_num, cells) for cells in reader if any(cell.strip() for cell in cells)]
    except csv.Error as error:
        raise InputError(f"{name}: not a readable CSV file ({error})") from None
    header = [field.strip() for field in lines[0][1]] if lines else []
    repeated = sorted({field for field in header if header.count(field) > 1})
    if repeated:
        raise InputError(f"{name}: column {', '.join(map(repr, repeated))} appears more than once in the header")
    missing = [column for column in columns if column not in header]
    if missing:
        found = f"its header row is {','.join(header)[:80]!r}" if header else "it holds no rows"
        raise InputError(f"{name}: no column {', '.join(missing)}: {found}; expected a header row naming "
                         f"{', '.join(columns)}, cells separated by commas")
    unknown = [field for field in header if allowed is not None and field not in {*columns, *allowed}]
    if unknown:
        raise InputError(f"{name}: unknown column {', '.join(map(repr, unknown))} (the columns are "
                         f"{', '.join(dict.fromkeys([*columns, *allowed]))})")
    rows = []
    for line, cells in lines[1:]:
        if len(cells) > len(header):
            raise InputError(f"{name}: line {line}: {len(cells)} cells under {len(header)} columns (a comma in a "
                             "value needs the value in double quotes)")
        row = dict(zip(header, [*cells, *[None] * (len(header) - len(cells))]))
        try:
            rows.append((line, {**row, **{column: kind(row[column]) for column, kind in columns.items()}}))
        except (TypeError, ValueError) as error:
            raise InputError(f"{name}: line {line}: {error}") from None
    return rows


# --------------------------------------------------------------------------------------------- tensors and JSON
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


def _umask() -> int:
    """The process's umask (which can only be read by setting it)."""
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


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


def read_text(path: str | os.PathLike, *, encoding: str = "utf-8") -> str:
    """The content of a text file (``latin-1`` decodes any bytes, for formats whose encoding is not stated).

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not decodable as ``encoding``.
    """
    name = _existing_file(path)
    try:
        with open(name, encoding=encoding) as stream:
            return stream.read()
    except UnicodeDecodeError as error:
        kind = _binary_kind(name)
        raise InputError(f"{name}: {f'is a {kind} file, not text' if kind else f'not a {encoding} text file ({error})'}"
                         ) from None


_MAGIC = {_GZIP_MAGIC: "gzip-compressed (.gz)", b"PK\x03\x04": "zip", b"\x89HDF": "HDF5",
          b"\x89PNG": "PNG image"}
"""Leading bytes of binary files a text reader may be handed by mistake (a .nii.gz for a pairs file)."""


def _binary_kind(name: str) -> str | None:
    """What ``name`` is when its first bytes say so (:data:`_MAGIC`), else ``None``."""
    with contextlib.suppress(OSError), open(name, "rb") as stream:
        start = stream.read(8)
        return next((kind for magic, kind in _MAGIC.items() if start.startswith(magic)), None)
    return None


def _existing_file(path: str | os.PathLike) -> str:
    """``path`` as a string if it names a file; else the error a reader raises."""
    name = os.fspath(path)
    if os.path.isdir(name):
        raise InputError(f"{name}: is a folder; expected a file")
    if not os.path.isfile(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    return name


def read_json(path: str | os.PathLike) -> Any:
    """The content of a JSON file.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not UTF-8 JSON, or JSON that Python cannot hold (nested too deeply, an integer of more digits
            than Python converts).
    """
    name = _existing_file(path)
    try:
        with open(name, encoding="utf-8") as stream:
            return json.load(stream)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{name}: not a JSON file ({error})") from None
    except RecursionError:
        raise InputError(f"{name}: JSON nested too deeply to read (beyond Python's recursion limit)") from None
    except ValueError as error:  # the limit on the digits of an integer (Python >= 3.11)
        raise InputError(f"{name}: unreadable JSON ({error})") from None


# ----------------------------------------------------------------------------------------------------------- meshes
def is_mesh_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a surface mesh or point cloud (by suffix, see :data:`MESH_SUFFIXES`)."""
    return os.fspath(path).lower().endswith(MESH_SUFFIXES)


def read_mesh(path: str | os.PathLike) -> pyvista.PolyData:
    """A surface mesh or point cloud with at least one point, coordinates in LPS mm.

    3D Slicer records the coordinate system of a saved model in the file: ``SPACE=RAS`` or ``SPACE=LPS`` in the
    header text (.vtk's header line, .stl's header or ``solid`` line, a .ply or .obj comment), or a field-data string
    array ``SPACE`` (.vtp). A model marked ``SPACE=RAS`` (older Slicer, or chosen on saving) is returned with x and y
    negated (a rotation by 180 degrees about z, so the surface stays right-handed, normals included); one marked
    ``SPACE=LPS`` or not marked at all is returned as stored, which is LPS as in Slicer >= 4.11.

    Args:
        path: .stl, .vtk, .vtp, .ply or .obj. A volumetric .vtk mesh becomes its outer surface.

    Raises:
        InputNotFoundError: the path does not exist.
        InputError: the file is unreadable, not a mesh, holds no points, or declares a ``SPACE`` other than RAS or
            LPS.
    """
    name = os.fspath(path)
    if not os.path.exists(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    if not is_mesh_path(name):
        raise InputError(f"{name}: not a mesh file; expected one of {', '.join(MESH_SUFFIXES)}")
    try:
        import pyvista as pv  # imported here: VTK takes about a second to load and most runs read no mesh
    except ImportError:
        raise InputError(f"{name}: reading surface meshes needs pyvista, an optional dependency (it brings its own "
                         "VTK, which clashes with Slicer's); install it with: pip install 'dpcn_med[mesh]'") from None

    try:
        mesh = pv.read(name)
    except (RuntimeError, ValueError, OSError) as error:
        raise InputError(f"{name}: not a readable mesh ({error}); export it again") from None
    space = _mesh_space(name, mesh)  # before extract_surface, which need not keep the field data
    if isinstance(mesh, pv.UnstructuredGrid):
        mesh = mesh.extract_surface(algorithm="dataset_surface")
    if not isinstance(mesh, pv.PolyData):
        raise InputError(f"{name}: holds {type(mesh).__name__} data, not a surface mesh or point cloud; save "
                         "images as .nii.gz, .nrrd or .mha")
    if mesh.n_points == 0:
        raise InputError(f"{name}: holds no points (an empty or unreadable mesh); export it again")
    if not np.isfinite(mesh.points).all():  # a NaN point became index -2**63 when voxelised
        raise InputError(f"{name}: has points with NaN or infinite coordinates; export it again")
    if space == "RAS":
        mesh = mesh.transform(np.diag([-1.0, -1.0, 1.0, 1.0]), inplace=False)  # a copy; active normals follow
        if "SPACE" in mesh.field_data:
            mesh.field_data["SPACE"] = ["LPS"]
    return mesh


_MESH_HEADER_BYTES = 4096
_MESH_SPACE = re.compile(rb"\bSPACE=(\w*)")  # not COLORSPACE=...: a word of its own


def _mesh_space(name: str, mesh: pyvista.DataSet) -> str | None:
    """The coordinate system ``name`` declares as Slicer writes it, ``"RAS"`` or ``"LPS"``; None when it says nothing.

    A field-data string array ``SPACE`` (Slicer's .vtp) wins; otherwise the first ``SPACE=...`` in the file's first
    4 KB, read as bytes (the header of .vtk, .stl, .ply and .obj files Slicer writes). The header is parsed by hand
    because ``pyvista.read`` hides its VTK reader and the readers expose it inconsistently (``GetHeader`` for .vtk
    and .stl, ``GetComments`` for .ply, ``GetComment`` for .obj, which depend on the VTK version).
    """
    if "SPACE" in mesh.field_data:
        values = np.asarray(mesh.field_data["SPACE"]).ravel()
        found = str(values[0]) if values.size == 1 else repr(values.tolist())
    else:
        with open(name, "rb") as stream:
            match = _MESH_SPACE.search(stream.read(_MESH_HEADER_BYTES))
        if match is None:
            return None
        found = match.group(1).decode("latin-1")
    if found.upper() not in ("RAS", "LPS"):
        raise InputError(f"{name}: declares SPACE={found}, an unknown coordinate system; expected SPACE=RAS or "
                         "SPACE=LPS (as 3D Slicer writes), or no SPACE for LPS")
    return found.upper()
