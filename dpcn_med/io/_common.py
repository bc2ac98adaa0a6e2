"""What several io modules share: the image formats, gzip's leading bytes, SimpleITK's error messages."""

from __future__ import annotations

import re

IMAGE_WRITE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha")
"""Image formats :func:`write_image` writes: one file each, so the atomic rename moves all of it."""

_INPUT_FORMATS = "NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd) or a folder of DICOM slices"

_GZIP_MAGIC = b"\x1f\x8b"


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
