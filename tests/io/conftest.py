"""Shared fixtures and helpers of the io tests: an asymmetric volume, files cut short, a child Python."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

SIZE = (20, 24, 28)  # (x, y, z): every axis different, so a transposition cannot pass
SPACING = (0.75, 1.25, 2.5)
ORIGIN = (-12.3456789, 30.25, 7.1)
# Origin, spacing and direction survive exactly in NRRD and MetaImage; NIfTI keeps them as float32.
GEOMETRY_TOLERANCE = {".nii": 1e-6, ".nii.gz": 1e-6, ".nrrd": 1e-12, ".nhdr": 1e-12, ".mha": 0.0, ".mhd": 0.0}


def oblique_direction() -> tuple[float, ...]:
    return sitk.VersorTransform((0.3, -0.5, 0.8), 0.7).GetMatrix()


def make_volume(seed: int = 0, pixel: type = np.float32) -> sitk.Image:
    """A random asymmetric volume with non-trivial origin, spacing and direction."""
    rng = np.random.default_rng(seed)
    image = sitk.GetImageFromArray((rng.random(SIZE[::-1]) * 1000).astype(pixel))
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    image.SetDirection(oblique_direction())
    return image


def assert_same_geometry(a: sitk.Image, b: sitk.Image, tolerance: float = 0.0) -> None:
    assert a.GetSize() == b.GetSize()
    for get in ("GetOrigin", "GetSpacing", "GetDirection"):
        np.testing.assert_allclose(getattr(a, get)(), getattr(b, get)(), rtol=0, atol=tolerance, err_msg=get)


def cut(path: Path, fraction: float = 0.5) -> None:
    """Keep only the first ``fraction`` of a file's bytes, as an interrupted copy does."""
    content = path.read_bytes()
    path.write_bytes(content[:int(len(content) * fraction)])


def edit_header(path: Path, old: bytes, new: bytes) -> None:
    content = path.read_bytes()
    assert old in content, content[:400]
    path.write_bytes(content.replace(old, new, 1))


def run_child(body: str) -> subprocess.CompletedProcess:
    """``body`` in a fresh Python with ``sitk``, ``io`` and ``InputError`` imported; output captured."""
    code = "import SimpleITK as sitk\nfrom dpcn_med import io\nfrom dpcn_med.errors import InputError\n"
    return subprocess.run([sys.executable, "-c", code + textwrap.dedent(body)], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})


@pytest.fixture
def volume() -> sitk.Image:
    return make_volume()
