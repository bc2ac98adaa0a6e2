"""What the module needs in Slicer's Python, and how to install it without breaking Slicer.

torch comes through the PyTorch extension (it picks the CUDA build for the machine); dpcn_med from the checkout the
module lives in (``pip install <checkout>``) or else from the package index. Slicer bundles SimpleITK and VTK built
for itself: pip must not replace them, so dpcn_med's own requirements are installed with those left out. numpy is
passed with dpcn_med's lower bound, which the numpy Slicer bundles meets, so pip keeps Slicer's.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

PACKAGE = "dpcn_med"
MINIMUM_PYTHON = (3, 10)
SLICER_PROVIDED_NAMES = ("SimpleITK", "vtk", "torch")
"""Distributions never installed over Slicer's own; torch is the PyTorch extension's to install."""


def missing() -> list[str]:
    """Import names of what is not importable yet, ``torch`` first (it must come before dpcn_med)."""
    return [name for name in ("torch", PACKAGE) if importlib.util.find_spec(name) is None]


def check_installed() -> None:
    """Raise ``RuntimeError`` naming what still does not import after installing it: a failed installation that
    reported none, or one that Slicer's Python sees only after a restart."""
    still = missing()
    if still:
        raise RuntimeError(f"{' and '.join(still)} still cannot be imported after installing; restart Slicer and "
                           "press Apply again")


def check_python() -> None:
    """Raise ``RuntimeError`` when this Slicer's Python is older than dpcn_med supports."""
    if sys.version_info < MINIMUM_PYTHON:
        raise RuntimeError(f"dpcn_med needs Python {'.'.join(map(str, MINIMUM_PYTHON))} or newer; this Slicer has "
                           f"{sys.version.split()[0]}: use 3D Slicer 5.10 or newer")


def source(module_file: str | Path) -> str:
    """Where to install dpcn_med from: the repository holding this module when it is a checkout (a
    ``pyproject.toml`` naming dpcn_med two folders above the module folder), else the package index."""
    root = Path(module_file).resolve().parents[2]
    pyproject = root / "pyproject.toml"
    if pyproject.is_file() and re.search(r'^name\s*=\s*"dpcn[_-]med"', pyproject.read_text(), re.MULTILINE):
        return str(root)
    return PACKAGE


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirements_to_install(requires: list[str]) -> list[str]:
    """dpcn_med's requirement strings (``importlib.metadata.requires``) minus extras-only ones and
    :data:`SLICER_PROVIDED_NAMES`."""
    kept = []
    for requirement in requires:
        if "extra ==" in requirement.replace("extra==", "extra =="):
            continue
        name = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
        if name and _normalise(name.group(1)) not in {_normalise(n) for n in SLICER_PROVIDED_NAMES}:
            kept.append(requirement.split(";")[0].strip())
    return kept
