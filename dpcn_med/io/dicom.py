"""A DICOM series read from its folder: one series chosen, its slices checked to lie evenly on one line."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.io._common import _INPUT_FORMATS, _sitk_reason
from dpcn_med.io.headers import _check_shape, _check_spacing, _read_file, check_memory


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
    Positions best (a missing slice, or two acquisitions mixed), or stepping off the slice normal (a gantry tilt).

    See docs/design_notes/io.md.
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
