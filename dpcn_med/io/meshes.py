"""Surface meshes and point clouds (pyvista, an optional dependency), returned in LPS millimetres."""

from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING

import numpy as np

from dpcn_med.errors import InputError, InputNotFoundError

if TYPE_CHECKING:
    import pyvista


MESH_SUFFIXES = (".stl", ".vtk", ".vtp", ".ply", ".obj")
"""Surface meshes and point clouds :func:`read_mesh` reads."""


def is_mesh_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a surface mesh or point cloud (by suffix, see :data:`MESH_SUFFIXES`)."""
    return os.fspath(path).lower().endswith(MESH_SUFFIXES)


def read_mesh(path: str | os.PathLike) -> pyvista.PolyData:
    """A surface mesh or point cloud with at least one point, coordinates in LPS mm.

    3D Slicer records the coordinate system of a saved model in the file: ``SPACE=RAS`` or ``SPACE=LPS`` in the
    header text (.vtk's header line, .stl's header or ``solid`` line, a .ply or .obj comment), or a field-data string
    array ``SPACE`` (.vtp). A model marked ``SPACE=RAS`` is returned with x and y negated (a rotation by 180 degrees
    about z, so the surface stays right-handed, normals included); one marked ``SPACE=LPS`` or not marked at all is
    returned as stored, taken as LPS. See docs/design_notes/io.md.

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
        from dpcn_med.geometry import RAS_TO_LPS  # here: geometry imports torch, which reading an image needs not

        mesh = mesh.transform(RAS_TO_LPS, inplace=False)  # a copy; active normals follow
        if "SPACE" in mesh.field_data:
            mesh.field_data["SPACE"] = ["LPS"]
    return mesh


_MESH_HEADER_BYTES = 4096

_MESH_SPACE = re.compile(rb"\bSPACE=(\w*)")  # not COLORSPACE=...: a word of its own


def _mesh_space(name: str, mesh: pyvista.DataSet) -> str | None:
    """The coordinate system ``name`` declares as Slicer writes it, ``"RAS"`` or ``"LPS"``; None when it says nothing.

    A field-data string array ``SPACE`` (Slicer's .vtp) wins; otherwise the first ``SPACE=...`` in the file's first
    4 KB, read as bytes (the header of .vtk, .stl, .ply and .obj files Slicer writes). See docs/design_notes/io.md.

    Raises:
        InputError: the file declares a ``SPACE`` other than RAS or LPS.
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
