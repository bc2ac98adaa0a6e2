"""Volumes and masks: read, checked, summarised and written.

Convention:
    Physical space is ITK's LPS in millimetres (:mod:`dpcn_med.geometry` owns the frames). Images keep the origin,
    spacing and direction stored in the file; NIfTI stores them as float32, so they round-trip to about 1e-7 there
    and exactly in NRRD and MetaImage.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.io._common import IMAGE_WRITE_SUFFIXES
from dpcn_med.io.atomic import _check_nifti_length, _check_write_suffix, _check_written, atomic_output
from dpcn_med.io.dicom import _read_dicom
from dpcn_med.io.headers import (
    GRID_TOLERANCE,
    _check_direction,
    _check_origin,
    _check_shape,
    _check_spacing,
    _read_file,
)


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
"""SimpleITK's run-length label-map pixel types, refused or converted before any voxel is read. See
docs/design_notes/io.md."""


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
        if compress and target.name.lower().endswith(".nii.gz"):
            _write_nifti_gz(image, temporary)
        else:
            sitk.WriteImage(image, str(temporary), useCompression=compress)
        _check_written(target, lambda: _check_nifti_length(temporary))


NIFTI_GZIP_LEVEL = 1
"""zlib level of the .nii.gz files :func:`write_image` writes: as fast as ITK's own gzip, files about 2% larger."""


def _write_nifti_gz(image: sitk.Image, path: Path) -> None:
    """``image`` as a gzipped NIfTI at ``path``: ITK writes the plain .nii beside it, Python's zlib compresses it.

    Why not ITK's gzip: it holds Python's lock while it compresses (0.4-0.5 s for a 1 mm head), where zlib releases
    it, so a thread can write the volume while the command draws its overview (``dpcn_med.outputs``).
    """
    import gzip
    import shutil

    plain = path.with_name(path.name[:-len(".gz")])  # a temporary name already (atomic_output's), beside it
    try:
        sitk.WriteImage(image, str(plain), useCompression=False)
        # No name in the gzip header (it would be the temporary one), and no time: the same image, the same bytes.
        with open(plain, "rb") as source, open(path, "wb") as raw, gzip.GzipFile(
                filename="", mode="wb", fileobj=raw, compresslevel=NIFTI_GZIP_LEVEL, mtime=0) as target:
            shutil.copyfileobj(source, target, 1 << 22)
    finally:
        plain.unlink(missing_ok=True)


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


def _split_series(name: str) -> tuple[Path | None, str | None]:
    """``(folder, uid)`` for an existing ``FOLDER@UID``, else ``(None, None)``."""
    if "@" not in name or os.path.exists(name):
        return None, None
    folder, _, uid = name.rpartition("@")
    return (Path(folder), uid) if os.path.isdir(folder) else (None, None)


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
