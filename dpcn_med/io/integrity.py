"""Whether a file holds all it should: truncation and corruption forensics of NIfTI, Analyze, MetaImage and gzip,
and a file's SHA-256 digest.

SimpleITK reads several cut or corrupt files without an error (see docs/design_notes/io.md); these checks run before
it reads the voxels and raise :class:`InputError` naming what is missing.
"""

from __future__ import annotations

import contextlib
import gzip
import hashlib
import math
import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from dpcn_med.errors import InputError
from dpcn_med.io._common import _GZIP_MAGIC

_CHUNK = 1 << 20
"""Bytes read at a time (1 MiB) where a file is streamed rather than read whole."""

# Bytes per element of MetaImage's element types (MetaIO's MET_LONG is 32-bit).
_META_ELEMENT_BYTES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
                       "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
                       "MET_DOUBLE": 8}

_NIFTI_HEADER_BYTES = 348
"""Length of a NIfTI-1 header."""


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 digest of a file's content.

    Args:
        path: the file.

    Returns:
        The digest as 64 lower-case hexadecimal digits (``hashlib.sha256(content).hexdigest()``).

    Raises:
        OSError: the file cannot be opened or read (``FileNotFoundError`` when it is missing).
    """
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        # In blocks, so a file is never held whole: hashlib.file_digest is Python 3.11's, and 3.10 is supported.
        while block := stream.read(_CHUNK):
            digest.update(block)
    return digest.hexdigest()


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


def _check_complete(path: Path) -> None:
    """Raise if the file (NIfTI, Analyze or MetaImage; NRRD's reader checks itself) holds fewer voxel bytes than its
    header promises, or would be misread: a .nii beside the .nii.gz asked for, a .nii.gz that is not gzip, or what
    :func:`_check_nifti` refuses.

    See docs/design_notes/io.md.
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
    """Raise if a NIfTI file is truncated, holds non-finite voxels, has a voxel size of 0 or disagreeing qform and
    sform.

    See docs/design_notes/io.md.
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
    its header needs. See docs/design_notes/io.md."""
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
    """Refuse a NIfTI header whose qform and sform are both set but place the volume differently: some corner of the
    grid more than 0.1 mm plus 2 mrad of its distance from voxel 0 apart.

    Args:
        path: the file, for messages.
        header: its nibabel NIfTI header.
        shape: the grid's size in voxels, three axes.

    See docs/design_notes/io.md.
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
