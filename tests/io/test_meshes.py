"""Tests for dpcn_med.io.meshes: surface meshes and point clouds in LPS."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError


class TestReadMesh:
    @pytest.mark.parametrize("suffix", io.MESH_SUFFIXES)
    def test_round_trip(self, tmp_path, suffix):
        import pyvista as pv

        sphere = pv.Sphere(radius=7.0, center=(10.0, -20.0, 5.0))
        path = tmp_path / f"model{suffix}"
        sphere.save(path)
        mesh = io.read_mesh(path)
        assert isinstance(mesh, pv.PolyData) and mesh.n_points == sphere.n_points
        np.testing.assert_allclose(mesh.bounds, sphere.bounds, atol=1e-5)

    def test_point_cloud(self, tmp_path):
        import pyvista as pv

        points = np.random.default_rng(0).random((30, 3)) * 50
        pv.PolyData(points).save(tmp_path / "cloud.vtp")
        np.testing.assert_allclose(io.read_mesh(tmp_path / "cloud.vtp").points, points, rtol=1e-6)

    def test_volumetric_mesh_becomes_its_surface(self, tmp_path):
        import pyvista as pv

        pv.Sphere().cast_to_unstructured_grid().save(tmp_path / "solid.vtk")
        mesh = io.read_mesh(tmp_path / "solid.vtk")
        assert isinstance(mesh, pv.PolyData) and mesh.n_points == pv.Sphere().n_points

    def test_empty(self, tmp_path):
        import pyvista as pv

        pv.PolyData().save(tmp_path / "empty.vtp")
        with pytest.raises(InputError, match=r"empty\.vtp: holds no points"):
            io.read_mesh(tmp_path / "empty.vtp")

    @pytest.mark.parametrize(("suffix", "message"), [(".stl", "holds no points"), (".vtk", "not a readable mesh")])
    @pytest.mark.filterwarnings("ignore::UserWarning")  # pyvista's warning about the VTK reader's failure
    def test_garbage(self, tmp_path, suffix, message):
        path = tmp_path / f"broken{suffix}"
        path.write_bytes(b"garbage\x00\x01" * 50)
        with pytest.raises(InputError, match=rf"broken\{suffix}: {message}"):
            io.read_mesh(path)

    def test_image_in_a_vtk_file(self, tmp_path):
        import pyvista as pv

        pv.ImageData(dimensions=(3, 4, 5)).save(tmp_path / "grid.vtk")
        with pytest.raises(InputError, match="holds ImageData data, not a surface mesh"):
            io.read_mesh(tmp_path / "grid.vtk")

    def test_missing(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"m\.stl: not found"):
            io.read_mesh(tmp_path / "m.stl")

    def test_without_pyvista_says_how_to_install_it(self, tmp_path, monkeypatch):
        (tmp_path / "m.stl").write_bytes(b"solid m\nendsolid m\n")
        monkeypatch.setitem(sys.modules, "pyvista", None)  # what an installation without the mesh extra gives
        with pytest.raises(InputError, match=r"m\.stl: reading surface meshes needs pyvista.*dpcn_med\[mesh\]"):
            io.read_mesh(tmp_path / "m.stl")


# Formats 3D Slicer marks with its coordinate system: (suffix, how the marker is written).
SLICER_MESH_FORMATS = ["stl-binary", "stl-ascii", "vtk", "ply", "obj", "vtp"]


def write_slicer_mesh(mesh, path: Path, space: str | None) -> Path:
    """``mesh`` saved the way 3D Slicer saves a model, marked ``SPACE=space`` (no marker when None)."""
    import vtk

    header = "3D Slicer output." + (f" SPACE={space}" if space else "")
    kind = path.suffix
    if kind in (".stl-binary", ".stl-ascii"):
        writer = vtk.vtkSTLWriter()
        writer.SetHeader(header)  # binary: the 80-byte header; ASCII: the "solid ..." line
        (writer.SetFileTypeToBinary if kind == ".stl-binary" else writer.SetFileTypeToASCII)()
        path = path.with_suffix(".stl")
    elif kind == ".vtk":
        writer = vtk.vtkPolyDataWriter()
        writer.SetHeader(header)  # the second line of a legacy .vtk file
        writer.SetFileTypeToBinary()
    elif kind == ".ply":
        writer = vtk.vtkPLYWriter()
        writer.AddComment(header)
        writer.SetFileTypeToBinary()
    elif kind == ".vtp":
        mesh = mesh.copy()
        if space:
            marker = vtk.vtkStringArray()
            marker.SetName("SPACE")
            marker.InsertNextValue(space)
            mesh.GetFieldData().AddArray(marker)
        writer = vtk.vtkXMLPolyDataWriter()
    elif kind == ".obj":  # vtkOBJWriter writes no header: put Slicer's comment line first by hand
        mesh.save(path)
        path.write_bytes(f"# {header}\n".encode() + path.read_bytes())
        return path
    else:
        raise AssertionError(kind)
    writer.SetInputData(mesh)
    writer.SetFileName(str(path))
    assert writer.Write() == 1
    return path


def ras_copy(mesh):
    """``mesh`` with x and y negated: the same surface in RAS coordinates."""
    return mesh.transform(np.diag([-1.0, -1.0, 1.0, 1.0]), inplace=False)


class TestReadMeshSpace:
    """Slicer's SPACE=RAS / SPACE=LPS marker: a RAS model comes back in LPS, an unmarked one as stored."""

    @pytest.fixture
    def surface(self):
        pv = pytest.importorskip("pyvista")
        return pv.Sphere(radius=7.0, center=(10.0, -20.0, 5.0), theta_resolution=9, phi_resolution=7)

    @pytest.mark.parametrize("kind", SLICER_MESH_FORMATS)
    def test_ras_file_reads_as_its_lps_twin(self, tmp_path, surface, kind):
        lps = io.read_mesh(write_slicer_mesh(surface, tmp_path / f"lps.{kind}", "LPS"))
        ras = io.read_mesh(write_slicer_mesh(ras_copy(surface), tmp_path / f"ras.{kind}", "RAS"))
        assert ras.n_points == lps.n_points
        np.testing.assert_allclose(ras.points, lps.points, atol=1e-5)
        np.testing.assert_allclose(lps.bounds, surface.bounds, atol=1e-5)  # LPS: as stored
        if "Normals" in lps.point_data and "Normals" in ras.point_data:
            np.testing.assert_allclose(ras.point_data["Normals"], lps.point_data["Normals"], atol=1e-5)

    @pytest.mark.parametrize("kind", SLICER_MESH_FORMATS)
    def test_unmarked_file_reads_as_stored(self, tmp_path, surface, kind):
        stored = ras_copy(surface)  # whatever is stored is taken as LPS, Slicer's default
        mesh = io.read_mesh(write_slicer_mesh(stored, tmp_path / f"plain.{kind}", None))
        np.testing.assert_allclose(mesh.bounds, stored.bounds, atol=1e-5)

    @pytest.mark.parametrize("kind", SLICER_MESH_FORMATS)
    def test_unknown_space_is_refused(self, tmp_path, surface, kind):
        path = write_slicer_mesh(surface, tmp_path / f"odd.{kind}", "foo")
        with pytest.raises(InputError, match=rf"odd\.{path.suffix[1:]}: declares SPACE=foo, an unknown coordinate"):
            io.read_mesh(path)

    def test_space_inside_another_word_is_not_a_marker(self, tmp_path, surface):
        path = tmp_path / "colours.vtk"
        surface.save(path, binary=False)
        path.write_bytes(path.read_bytes().replace(b"vtk output", b"COLORSPACE=RGB", 1))
        np.testing.assert_allclose(io.read_mesh(path).bounds, surface.bounds, atol=1e-4)  # ASCII: 6 digits

    def test_ras_field_data_is_relabelled(self, tmp_path, surface):
        mesh = io.read_mesh(write_slicer_mesh(ras_copy(surface), tmp_path / "ras.vtp", "RAS"))
        assert list(mesh.field_data["SPACE"]) == ["LPS"]

    def test_ras_point_cloud(self, tmp_path):
        pv = pytest.importorskip("pyvista")
        points = np.random.default_rng(1).random((20, 3)) * 50
        path = tmp_path / "cloud.vtk"
        write_slicer_mesh(pv.PolyData(points * [-1.0, -1.0, 1.0]), path, "RAS")
        np.testing.assert_allclose(io.read_mesh(path).points, points, rtol=1e-6)


class TestIsMeshPath:
    @pytest.mark.parametrize(("path", "expected"), [("a.STL", True), (Path("b.vtp"), True), ("c.obj", True),
                                                    ("d.nii.gz", False), ("e.vtk.nrrd", False)])
    def test_by_suffix(self, path, expected):
        assert io.is_mesh_path(path) is expected
