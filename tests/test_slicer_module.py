"""The Slicer extension (slicer_module/) outside Slicer: its Lib against real MRML nodes from slicer-core (no Qt), the
registration process it drives, and the consistency of the module file, its .ui and its CMake lists.

No stand-ins: volumes are read by Slicer's own storage node, transforms by its transform storage node, and the
registration runs ``dpcn-med`` in a child Python exactly as PythonSlicer would.
"""

from __future__ import annotations

import ast
import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.cli import main as dpcn_med_cli
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity
from dpcn_med.geometry import slicer_to_parent_ras
from tests.conftest import shared_path

slicer = pytest.importorskip("slicer", reason="slicer-core (the test extra) is not installed")
vtk = pytest.importorskip("vtk")

from DPCNRegistrationLib import dependencies, process  # noqa: E402  (needs slicer-core, checked above)
from DPCNRegistrationLib.logic import Registration, RegistrationError, register_volumes  # noqa: E402
from DPCNRegistrationLib.process import Job, Options, parse_line  # noqa: E402
from DPCNRegistrationLib.transforms import (  # noqa: E402
    ROLE_ATTRIBUTES,
    base_transform_node,
    place_result,
    read_transform_file,
    reusable_output,
)
from DPCNRegistrationLib.volumes import (  # noqa: E402
    LPS_TO_RAS,
    RAS_TO_LPS,
    array_to_matrix,
    ijk_to_ras,
    image_to_volume,
    mask_on_volume,
    matrix_to_array,
    parent_to_world,
    read_volume,
    transform_to_world,
    volume_to_image,
)

MODULE = Path(__file__).resolve().parents[1] / "slicer_module" / "DPCNRegistration"
QUICK = Options(model="learning-free", bandwidth=16)


def linear_transform(scene, matrix: np.ndarray, name: str = "transform"):
    node = slicer.vtkMRMLLinearTransformNode()
    node.SetName(name)
    scene.AddNode(node)
    node.SetMatrixTransformToParent(array_to_matrix(matrix))
    return node


def rotation_ras(degrees: float, axis, shift) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    axis = np.asarray(axis, dtype=float)
    matrix[:3, :3] = Rotation.from_rotvec(np.deg2rad(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    matrix[:3, 3] = shift
    return matrix


def oblique_image(dtype=sitk.sitkInt16) -> sitk.Image:
    rng = np.random.default_rng(3)
    image = sitk.GetImageFromArray(rng.integers(-1000, 2000, size=(7, 9, 11)).astype(np.int16))
    image = sitk.Cast(image, dtype)
    image.SetSpacing((0.7, 1.3, 2.9))
    image.SetOrigin((-40.5, 12.25, 7.0))
    image.SetDirection(rotation_ras(33, (1, 2, -0.5), (0, 0, 0))[:3, :3].ravel().tolist())
    return image


def homogeneous(points: np.ndarray) -> np.ndarray:
    return np.hstack([points, np.ones((len(points), 1))]).T


def launcher_of_a_sleeping_python(folder: Path) -> tuple[str, Path]:
    """A stand-in for PythonSlicer, a launcher that runs Python as its child (not by exec): ``(its path, the file
    that child writes its process ID to once it runs)``. The child prints a line, then sleeps for a minute."""
    pid_file = folder / "python.pid"
    launcher = folder / "launcher"
    launcher.write_text(f'#!/bin/sh\n"{sys.executable}" -c "import os, time; '
                        f"open('{pid_file}', 'w').write(str(os.getpid())); print('started', flush=True); "
                        f'time.sleep(60)"\n')
    launcher.chmod(0o755)
    return str(launcher), pid_file


def ended(pid: int, within: float = 2.0) -> bool:
    """Whether process ``pid`` ends within ``within`` seconds (as a zombie that no one has reaped yet, too): a process
    closes its files, the output pipe included, a moment before it has ended."""
    status = Path(f"/proc/{pid}/status")
    started = time.perf_counter()
    while time.perf_counter() - started < within:
        try:
            os.kill(pid, 0)
            if status.is_file() and re.search(r"^State:\s*Z", status.read_text(), re.MULTILINE):
                return True
        except (ProcessLookupError, FileNotFoundError):
            return True
        time.sleep(0.01)
    return False


class TestVolumes:
    def test_unreadable_file_is_refused_by_name(self, tmp_path):
        path = tmp_path / "broken.nrrd"
        path.write_text("not a volume\n")
        with pytest.raises(ValueError, match=r"broken\.nrrd: Slicer's volume storage node could not read it"):
            read_volume(slicer.vtkMRMLScene(), path, "broken")

    @pytest.mark.shared_data
    @pytest.mark.parametrize("relative", ["rire/training_001_mr_T1.mha", "stroke/T1.nii.gz",
                                          "mridir/mridir_ct_3p0mm.nii.gz"])
    def test_what_slicer_reads_converts_to_what_simpleitk_reads(self, relative):
        path = shared_path(relative)
        node = read_volume(slicer.vtkMRMLScene(), path, "volume")
        converted, expected = volume_to_image(node), sitk.ReadImage(str(path))
        assert converted.GetSize() == expected.GetSize()
        np.testing.assert_allclose(converted.GetSpacing(), expected.GetSpacing(), atol=1e-5)
        np.testing.assert_allclose(converted.GetOrigin(), expected.GetOrigin(), atol=1e-4)
        np.testing.assert_allclose(converted.GetDirection(), expected.GetDirection(), atol=1e-5)
        np.testing.assert_array_equal(sitk.GetArrayViewFromImage(converted), sitk.GetArrayViewFromImage(expected))

    @pytest.mark.parametrize("pixel", [sitk.sitkInt16, sitk.sitkFloat32, sitk.sitkUInt8])
    def test_round_trip_keeps_voxels_type_and_oblique_geometry(self, pixel):
        image = oblique_image(pixel)
        node = slicer.vtkMRMLScalarVolumeNode()
        image_to_volume(image, node)
        back = volume_to_image(node)
        assert back.GetPixelID() == image.GetPixelID()
        np.testing.assert_array_equal(sitk.GetArrayViewFromImage(back), sitk.GetArrayViewFromImage(image))
        np.testing.assert_allclose(back.GetSpacing(), image.GetSpacing(), atol=1e-12)
        np.testing.assert_allclose(back.GetOrigin(), image.GetOrigin(), atol=1e-12)
        np.testing.assert_allclose(back.GetDirection(), image.GetDirection(), atol=1e-12)

    def test_a_voxel_lands_at_the_same_physical_point_in_ras(self):
        image = oblique_image()
        node = slicer.vtkMRMLScalarVolumeNode()
        image_to_volume(image, node)
        index = (3, 5, 6)
        ras = ijk_to_ras(node) @ np.array([*index, 1.0])
        np.testing.assert_allclose(LPS_TO_RAS[:3, :3] @ image.TransformIndexToPhysicalPoint(index), ras[:3],
                                   atol=1e-9)

    def test_world_geometry_hardens_linear_parents(self):
        scene = slicer.vtkMRMLScene()
        node = slicer.vtkMRMLScalarVolumeNode()
        scene.AddNode(node)
        image = oblique_image()
        image_to_volume(image, node)
        outer = linear_transform(scene, rotation_ras(70, (0, 1, 1), (5, -3, 2)), "outer")
        inner = linear_transform(scene, rotation_ras(-20, (1, 0, 0), (0, 8, 0)), "inner")
        inner.SetAndObserveTransformNodeID(outer.GetID())
        node.SetAndObserveTransformNodeID(inner.GetID())
        world = parent_to_world(node)
        inner_matrix = matrix_to_array(inner.GetMatrixTransformToParent())
        np.testing.assert_allclose(world, transform_to_world(outer) @ inner_matrix, atol=1e-12)
        hardened = volume_to_image(node, world=world)
        index = (1, 7, 2)
        expected = world @ LPS_TO_RAS @ np.array([*image.TransformIndexToPhysicalPoint(index), 1.0])
        np.testing.assert_allclose(LPS_TO_RAS[:3, :3] @ hardened.TransformIndexToPhysicalPoint(index),
                                   expected[:3], atol=1e-9)

    def test_refuses_empty_vector_and_sheared_volumes(self):
        scene = slicer.vtkMRMLScene()
        empty = slicer.vtkMRMLScalarVolumeNode()
        empty.SetName("empty")
        with pytest.raises(ValueError, match="empty: holds no image data"):
            volume_to_image(empty)
        vector = slicer.vtkMRMLVectorVolumeNode()
        vector.SetName("rgb")
        data = vtk.vtkImageData()
        data.SetDimensions(4, 4, 4)
        data.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 3)
        vector.SetAndObserveImageData(data)
        with pytest.raises(ValueError, match="rgb: has 3 components"):
            volume_to_image(vector)
        node = slicer.vtkMRMLScalarVolumeNode()
        node.SetName("head")
        scene.AddNode(node)
        image_to_volume(oblique_image(), node)
        shear = np.eye(4)
        shear[0, 1] = 0.4
        node.SetAndObserveTransformNodeID(linear_transform(scene, shear, "shear").GetID())
        with pytest.raises(ValueError, match="head: its geometry .* sheared"):
            volume_to_image(node, world=parent_to_world(node))
        grid = slicer.vtkMRMLGridTransformNode()
        grid.SetName("warp")
        scene.AddNode(grid)
        node.SetAndObserveTransformNodeID(grid.GetID())
        with pytest.raises(ValueError, match="warp: is not a linear transform"):
            parent_to_world(node)


class TestMasks:
    @pytest.fixture
    def volume(self):
        scene = slicer.vtkMRMLScene()
        node = slicer.vtkMRMLScalarVolumeNode()
        node.SetName("volume")
        scene.AddNode(node)
        image_to_volume(oblique_image(), node)
        return scene, node, volume_to_image(node)

    @staticmethod
    def label_map(scene, image: sitk.Image, name: str = "label"):
        node = slicer.vtkMRMLLabelMapVolumeNode()
        node.SetName(name)
        scene.AddNode(node)
        image_to_volume(image, node)
        return node

    def test_a_label_map_on_the_volumes_grid_is_its_non_zero_voxels(self, volume):
        scene, node, image = volume
        labels = np.zeros(sitk.GetArrayViewFromImage(image).shape, np.uint8)
        labels[2:5, 3:7, 1:9] = 7  # one label, any value
        label_image = sitk.GetImageFromArray(labels)
        label_image.CopyInformation(image)
        mask = mask_on_volume(self.label_map(scene, label_image), node, image)
        assert mask.GetPixelID() == sitk.sitkUInt8 and mask.GetSize() == image.GetSize()
        assert mask.GetOrigin() == image.GetOrigin() and mask.GetDirection() == image.GetDirection()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), (labels != 0).astype(np.uint8))

    def test_a_label_map_moved_in_the_views_covers_what_it_overlays(self, volume):
        """The label map hangs under a transform that shifts it by two voxels along the volume's first axis: the
        mask is the label shifted by two voxels on the volume's grid."""
        scene, node, image = volume
        labels = np.zeros(sitk.GetArrayViewFromImage(image).shape, np.uint8)
        labels[2:5, 3:7, 1:6] = 1
        label_image = sitk.GetImageFromArray(labels)
        label_image.CopyInformation(image)
        label = self.label_map(scene, label_image)
        shift = np.eye(4)
        shift[:3, 3] = 2 * ijk_to_ras(node)[:3, 0]
        label.SetAndObserveTransformNodeID(linear_transform(scene, shift, "shift").GetID())
        expected = np.zeros_like(labels)
        expected[2:5, 3:7, 3:8] = 1
        np.testing.assert_array_equal(sitk.GetArrayFromImage(mask_on_volume(label, node, image)), expected)

    def test_a_label_map_that_covers_nothing_is_refused(self, volume):
        scene, node, image = volume
        empty = sitk.Image(image.GetSize(), sitk.sitkUInt8)
        empty.CopyInformation(image)
        with pytest.raises(ValueError, match="elsewhere: the mask covers no voxel of volume"):
            mask_on_volume(self.label_map(scene, empty, "elsewhere"), node, image)

    def test_masks_become_dpcn_med_arguments(self):
        command = process.command("f.nrrd", "m.nrrd", "out", Options(), fixed_mask="fm.nrrd", python="python")
        assert command[command.index("--fixed-mask") + 1] == "fm.nrrd" and "--moving-mask" not in command
        assert command[-2:] == ["--progress", "json"]


class TestTransforms:
    @pytest.mark.parametrize("suffix", [".tfm", ".h5"])
    def test_reads_a_transform_file_as_slicer_models_it(self, tmp_path, suffix):
        transform = sitk.VersorRigid3DTransform()
        transform.SetCenter((10.0, -20.0, 5.0))
        transform.SetRotation((0.2, -0.5, 0.3), 2.1)
        transform.SetTranslation((4.0, 7.5, -12.0))
        path = tmp_path / f"t{suffix}"
        io.write_transform(transform, path)
        read = read_transform_file(path, slicer.vtkMRMLScene())
        np.testing.assert_allclose(read, slicer_to_parent_ras(transform), atol=1e-9)

    def test_unreadable_file_is_refused(self, tmp_path):
        path = tmp_path / "broken.tfm"
        path.write_text("#Insight Transform File V1.0\nnot a transform\n")
        with pytest.raises(ValueError, match="broken.tfm: not a readable linear transform file"):
            read_transform_file(path, slicer.vtkMRMLScene())

    def test_result_goes_under_the_moving_volumes_parent_and_keeps_it(self):
        scene = slicer.vtkMRMLScene()
        fixed, moving = slicer.vtkMRMLScalarVolumeNode(), slicer.vtkMRMLScalarVolumeNode()
        scene.AddNode(fixed)
        scene.AddNode(moving)
        base_matrix = rotation_ras(40, (1, 1, 0), (3, 2, 1))
        base = linear_transform(scene, base_matrix, "user's transform")
        moving.SetAndObserveTransformNodeID(base.GetID())
        output = linear_transform(scene, np.eye(4), "result")
        assert base_transform_node(moving, output).GetID() == base.GetID()
        registration = rotation_ras(150, (0.3, -0.8, 0.5), (25, -15, 10))
        place_result(registration, moving, fixed, output, base)
        assert moving.GetParentTransformNode().GetID() == output.GetID()
        assert output.GetParentTransformNode().GetID() == base.GetID()
        np.testing.assert_allclose(parent_to_world(moving), registration @ base_matrix, atol=1e-9)
        np.testing.assert_allclose(matrix_to_array(base.GetMatrixTransformToParent()), base_matrix, atol=1e-12)
        assert (output.GetAttribute(ROLE_ATTRIBUTES[0]), output.GetAttribute(ROLE_ATTRIBUTES[1])) == (
            fixed.GetID(), moving.GetID())
        # Registering again into the same output measures from the base again, not from the previous result.
        assert base_transform_node(moving, output).GetID() == base.GetID()

    def test_an_output_holding_other_nodes_is_not_reused(self):
        scene = slicer.vtkMRMLScene()
        moving, other, mask = (scene.AddNewNodeByClass(c) for c in (
            "vtkMRMLScalarVolumeNode", "vtkMRMLScalarVolumeNode", "vtkMRMLLabelMapVolumeNode"))
        mine = linear_transform(scene, np.eye(4), "my transform")
        assert reusable_output(None, moving) is None
        assert reusable_output(mine, moving) is mine
        for node in (moving, mask):
            node.SetAndObserveTransformNodeID(mine.GetID())
        assert reusable_output(mine, moving, mask) is mine  # the moving volume and its mask follow the result
        other.SetAndObserveTransformNodeID(mine.GetID())
        assert reusable_output(mine, moving, mask) is None  # writing it would move another volume
        result = linear_transform(scene, np.eye(4), "an earlier result")
        result.SetAttribute(ROLE_ATTRIBUTES[1], other.GetID())
        assert reusable_output(result, moving) is None  # another volume's registration
        result.SetAttribute(ROLE_ATTRIBUTES[1], moving.GetID())
        other.SetAndObserveTransformNodeID(result.GetID())  # put there to follow the moving volume
        assert reusable_output(result, moving) is result


class TestProcess:
    def test_options_become_dpcn_med_arguments(self):
        assert Options().arguments() == ["--mode", "rigid", "--device", "auto"]  # the bandwidth: the model's
        assert Options(mode="similarity", model="learning-free", refine=False, device="cpu", bandwidth=16
                       ).arguments() == ["--mode", "similarity", "--bandwidth", "16", "--device", "cpu",
                                         "--model", "none", "--no-refine"]
        assert Options(model="/models/ct_mr.safetensors").arguments()[-2:] == ["--model", "/models/ct_mr.safetensors"]
        assert Options(fixed_modality="us", moving_modality="mr").arguments()[-4:] == [
            "--fixed-modality", "us", "--moving-modality", "mr"]
        assert "--fixed-modality" not in Options(moving_modality="ct").arguments()

    def test_the_unverified_key_is_dpcn_meds(self):
        from DPCNRegistrationLib.logic import UNVERIFIED_KEY

        from dpcn_med.result import SIMILARITY_KEYS
        assert UNVERIFIED_KEY == SIMILARITY_KEYS["lc2"]
        command = process.command("f.nrrd", "m.nrrd", "out", Options(), python="PythonSlicer")
        assert command[:3] == ["PythonSlicer", str(process.SCRIPT), "register"]
        assert command[-2:] == ["--progress", "json"]
        assert "--no-overview" in command and "--no-resampled" not in command
        assert "--no-resampled" in process.command("f.nrrd", "m.nrrd", "out", Options(), resampled=False)

    def test_parses_progress_and_keeps_other_lines(self):
        event = parse_line('{"stage": "solving", "fraction": 0.3, "pair": ""}\n')
        assert (event.kind, event.text, event.fraction) == ("progress", "solving", 0.3)
        assert parse_line("rotation 150.0 deg, scale 1.0000").kind == "log"
        assert parse_line("{not json").kind == "log"
        assert parse_line('{"other": 1}').kind == "log"

    def test_job_streams_events_and_the_exit_code(self):
        script = textwrap.dedent("""
            import json, sys
            print(json.dumps({"stage": "solving", "fraction": 0.5}), flush=True)
            print("dpcn-med: error: moving.nrrd: holds NaN", flush=True)
            print("trailing note", flush=True)
            sys.exit(2)
        """)
        job = Job([sys.executable, "-c", script])
        events = job.wait(30)
        assert [e.kind for e in events] == ["progress", "log", "log", "exit"]
        assert job.returncode == 2 and job.finished
        assert job.error_message() == "dpcn-med: error: moving.nrrd: holds NaN"

    def test_bytes_that_are_not_utf8_neither_hang_nor_hide_the_exit(self):
        """An undecodable byte ended the reader thread: no exit event, the job never finished (Cancel forever)."""
        job = Job([sys.executable, "-c", "import sys; sys.stdout.buffer.write(b'caf\\xe9\\n'); sys.exit(2)"])
        events = job.wait(30)
        assert job.finished and job.returncode == 2 and events[-1].kind == "exit"
        assert job.error_message() == "caf\ufffd"

    def test_the_child_prints_non_ascii_on_any_code_page(self):
        """A child on a legacy code page (Windows) failed printing a non-ASCII path, after its work was done."""
        job = Job([sys.executable, "-c", "print('Łukasz', flush=True)"],
                  environment={**os.environ, "PYTHONIOENCODING": "cp1252"})
        job.wait(30)
        assert job.returncode == 0 and job.log == ["Łukasz"], job.log

    def test_cancel_stops_the_process(self):
        job = Job([sys.executable, "-c", "import time; print('started', flush=True); time.sleep(60)"])
        started = time.perf_counter()
        while not any(e.kind == "log" for e in job.poll()):
            time.sleep(0.01)
            assert time.perf_counter() - started < 30
        job.cancel()
        job.wait(10)
        assert job.finished and job.returncode != 0 and job.cancelled
        assert time.perf_counter() - started < 30

    @pytest.mark.skipif(os.name != "posix", reason="the stand-in launcher is a shell script")
    def test_cancel_stops_what_a_launcher_started_without_blocking(self, tmp_path):
        """PythonSlicer is a launcher that runs Python as its child: terminating the launcher alone left that child
        registering, and cancel blocked (the GUI thread) for seconds."""
        launcher, pid_file = launcher_of_a_sleeping_python(tmp_path)
        job = Job([launcher])
        started = time.perf_counter()
        while not any(e.kind == "log" for e in job.poll()):
            time.sleep(0.01)
            assert time.perf_counter() - started < 30
        python = int(pid_file.read_text())
        started = time.perf_counter()
        job.cancel()
        assert time.perf_counter() - started < 0.5
        job.wait(5)  # the output pipe closes only when every process holding it has ended
        assert job.finished and job.cancelled and ended(python)

    def test_script_says_when_dpcn_med_is_missing(self):
        # -S: no site-packages, so dpcn_med is not importable, as in a Slicer where it is not installed yet.
        done = subprocess.run([sys.executable, "-S", str(process.SCRIPT), "register"], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 2
        assert "dpcn_med is not installed in this Python" in done.stdout


class TestDependencies:
    def test_what_still_does_not_import_after_installing_is_named(self, monkeypatch):
        dependencies.check_installed()
        monkeypatch.setattr(dependencies, "missing", lambda: ["torch", "dpcn_med"])
        with pytest.raises(RuntimeError, match="torch and dpcn_med still cannot be imported after installing; "
                                               "restart Slicer"):
            dependencies.check_installed()

    def test_nothing_missing_here(self):
        assert dependencies.missing() == []

    def test_installs_from_this_checkout_else_from_the_index(self, tmp_path):
        assert dependencies.source(MODULE / "DPCNRegistration.py") == str(MODULE.parents[1])
        elsewhere = tmp_path / "Extensions" / "DPCNRegistration" / "DPCNRegistration.py"
        elsewhere.parent.mkdir(parents=True)
        assert dependencies.source(elsewhere) == "dpcn_med"

    def test_never_reinstalls_what_slicer_provides(self):
        requires = importlib.metadata.requires("dpcn_med")
        kept = dependencies.requirements_to_install(requires)
        names = {re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower() for r in kept}
        assert {"monai", "nibabel", "scipy"} <= names
        assert not names & {"simpleitk", "torch", "vtk", "pyvista", "pytest", "slicer-core", "itk"}


def moved_head(tmp_path: Path, *, seed: int, max_shift_mm: float):
    """The seg3d head MR (fixed) and a copy moved by a known rigid transform (moving), both loaded by Slicer's storage
    node into a new scene: ``(image, foreground corners (8, 3) LPS, truth fixed_to_moving, scene, fixed, moving)``."""
    fixed_path = shared_path("seg3d/MR.nii.gz")
    image = sitk.ReadImage(str(fixed_path))
    corners = foreground_corners(image)
    truth = random_similarity(np.random.default_rng(seed), corners.mean(axis=0), max_shift_mm=max_shift_mm)
    io.write_image(moved_copy(image, truth), tmp_path / "moving.nii.gz")
    scene = slicer.vtkMRMLScene()
    return (image, corners, truth, scene, read_volume(scene, fixed_path, "MR"),
            read_volume(scene, tmp_path / "moving.nii.gz", "MR moved"))


def landing_errors(moving, truth, points: np.ndarray) -> np.ndarray:
    """``(K,)`` mm: fixed anatomy ``x`` (LPS) sits at ``truth(x)`` in the moved file; under the moving volume's
    transforms it must come back to ``x``."""
    moved_points = np.array([truth.TransformPoint(p.tolist()) for p in points])
    world = parent_to_world(moving) @ LPS_TO_RAS @ homogeneous(moved_points)
    return np.linalg.norm((RAS_TO_LPS @ world).T[:, :3] - points, axis=1)


@pytest.mark.shared_data
class TestRegistration:
    def test_moving_volume_under_a_users_transform_lands_on_the_fixed_one(self, tmp_path):
        """A real head MRI moved by a known rigid transform and put under a user's transform: the result node, under
        that transform, maps the moving volume's anatomy onto the fixed one (checked at the head's corners)."""
        image, corners, truth, scene, fixed, moving = moved_head(tmp_path, seed=11, max_shift_mm=40)
        user = rotation_ras(25, (0, 0, 1), (12, 0, -6))
        base = linear_transform(scene, user, "user's transform")
        moving.SetAndObserveTransformNodeID(base.GetID())
        output_volume = slicer.vtkMRMLScalarVolumeNode()
        scene.AddNode(output_volume)
        stages = []
        result = register_volumes(fixed, moving, QUICK, output_volume=output_volume,
                                  progress=lambda stage, fraction: stages.append((stage, fraction)))

        assert not result.low_confidence and result.confidence > 0.5 and result.overlap == 1.0
        assert result.success_probability == result.report["success_probability"] > 0.9 and not result.unverified
        assert stages[-1] == ("done", 1.0) and "solving" in {s for s, _ in stages}
        assert moving.GetParentTransformNode().GetID() == result.transform.GetID()
        assert result.transform.GetParentTransformNode().GetID() == base.GetID()
        np.testing.assert_allclose(transform_to_world(base), user, atol=1e-12)  # the user's transform is untouched
        error = landing_errors(moving, truth, corners)
        assert error.max() < 1.5, f"corner errors {np.round(error, 2)} mm"
        # The resampled output lies on the fixed grid and shows the same head.
        resampled, reference = volume_to_image(output_volume), volume_to_image(fixed)
        assert resampled.GetSize() == reference.GetSize()
        np.testing.assert_allclose(ijk_to_ras(output_volume), ijk_to_ras(fixed), atol=1e-4)
        correlation = np.corrcoef(sitk.GetArrayFromImage(resampled).ravel(),
                                  sitk.GetArrayFromImage(reference).ravel())[0, 1]
        assert correlation > 0.95

    def test_a_fixed_mask_reaches_dpcn_med_and_the_slab_registers(self, tmp_path):
        """Only the upper 60% of the fixed head (a label map drawn on it) against the whole moved head."""
        image, corners, truth, scene, fixed, moving = moved_head(tmp_path, seed=12, max_shift_mm=30)
        labels = np.zeros(sitk.GetArrayViewFromImage(image).shape, np.uint8)
        labels[int(0.4 * labels.shape[0]):] = 1  # slices along the image's third axis
        label_image = sitk.GetImageFromArray(labels)
        label_image.CopyInformation(image)
        slab = TestMasks.label_map(scene, label_image, "slab")

        result = register_volumes(fixed, moving, QUICK, fixed_mask=slab)
        assert result.report["inputs"]["fixed_mask"].endswith("fixed_mask.nrrd")
        assert result.report["inputs"]["moving_mask"] is None
        kept = np.array([p for p in corners if image.TransformPhysicalPointToContinuousIndex(p.tolist())[2]
                         >= 0.4 * labels.shape[0]])
        error = landing_errors(moving, truth, kept)
        assert error.max() < 2.0, f"corner errors {np.round(error, 2)} mm"

    def test_transform_node_equals_the_cli_transform_file_read_by_slicer(self, tmp_path):
        """The real MRI-DIR CT onto its T2 (unaligned scanner frames): the module's node and the CLI's .tfm read
        through vtkMRMLTransformStorageNode give the same matrix."""
        ct, t2 = shared_path("mridir/mridir_ct_3p0mm.nii.gz"), shared_path("mridir/mridir_t2_3p0mm.nii.gz")
        assert dpcn_med_cli(["register", str(t2), str(ct), "-o", str(tmp_path / "cli"), "-q",
                             *QUICK.arguments()]) in (0, 3)
        scene = slicer.vtkMRMLScene()
        from_cli = read_transform_file(tmp_path / "cli" / "transform.tfm", scene)
        result = register_volumes(read_volume(scene, t2, "T2"), read_volume(scene, ct, "CT"), QUICK)
        from_module = matrix_to_array(result.transform.GetMatrixTransformToParent())
        np.testing.assert_allclose(from_module[:3, :3], from_cli[:3, :3], atol=1e-3)
        np.testing.assert_allclose(from_module[:3, 3], from_cli[:3, 3], atol=0.05)
        report = json.loads((tmp_path / "cli" / "report.json").read_text())
        assert result.confidence == pytest.approx(report["confidence"], rel=1e-3)


class TestUltrasound:
    def test_a_volume_named_ultrasound_is_refined_by_lc2_and_flagged(self):
        """An ultrasound-like sub-volume (fixed, ``us``) of a phantom against the whole phantom as stored (aligned):
        the modality reaches dpcn-med, which refines by LC2, flags the result as unverified, and keeps it aligned."""
        from tests.test_lc2 import _phantom, _ultrasound_of

        whole = _phantom()
        scene = slicer.vtkMRMLScene()
        nodes = []
        for name, image in (("ultrasound", _ultrasound_of(whole, (6, 26))), ("phantom", whole)):
            node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", name)
            image_to_volume(image, node)
            nodes.append(node)
        result = register_volumes(*nodes, Options(model="learning-free", bandwidth=16, fixed_modality="us"))
        assert result.unverified and result.low_confidence and "negative_lc2" in result.report
        assert result.report["similarity"].startswith("LC2")
        world = transform_to_world(result.transform)
        np.testing.assert_allclose(world[:3, :3], np.eye(3), atol=0.02)
        assert np.linalg.norm(world[:3, 3]) < 1.0, world[:3, 3]


def turned_oblique_image(degrees: float) -> sitk.Image:
    """:func:`oblique_image` (float) with its axes turned by ``degrees`` about z."""
    image = oblique_image(sitk.sitkFloat32)
    image.SetDirection(rotation_ras(degrees, (0, 0, 1), (0, 0, 0))[:3, :3].ravel().tolist())
    return image


def _drop_report_key(key: str):
    def edit(folder: Path) -> None:
        report = json.loads((folder / "report.json").read_text())
        del report[key]
        (folder / "report.json").write_text(json.dumps(report))
    return edit


def _overwrite(name: str, content: str):
    return lambda folder: (folder / name).write_text(content)


PAIR_ANGLES = {"fixed": 0, "moving": 40}
"""Degrees the failure tests' fixed and moving volumes are turned by (:func:`turned_oblique_image`)."""


@pytest.fixture(scope="module")
def complete_result(tmp_path_factory) -> Path:
    """The folder dpcn-med writes for the failure tests' pair, as the module asks for it (no overview)."""
    folder = tmp_path_factory.mktemp("complete")
    for name, angle in PAIR_ANGLES.items():
        sitk.WriteImage(turned_oblique_image(angle), str(folder / f"{name}.nrrd"))
    assert dpcn_med_cli(["register", str(folder / "fixed.nrrd"), str(folder / "moving.nrrd"), "-o",
                         str(folder / "result"), "-q", "--no-overview", *QUICK.arguments()]) in (0, 3)
    return folder / "result"


class TestRegistrationFailures:
    @pytest.fixture
    def pair(self):
        scene = slicer.vtkMRMLScene()
        nodes = []
        for name, angle in PAIR_ANGLES.items():
            node = slicer.vtkMRMLScalarVolumeNode()
            node.SetName(name)
            scene.AddNode(node)
            image_to_volume(turned_oblique_image(angle), node)
            nodes.append(node)
        return scene, nodes[0], nodes[1]

    @staticmethod
    def child_writing(folder: Path, tmp_path: Path) -> str:
        """A stand-in for the child Python that exits 0 after copying ``folder`` to the output it is given
        (arguments: run_registration.py register FIXED MOVING -o OUTPUT ...)."""
        python = tmp_path / "python-writing-a-prepared-result"
        python.write_text(f'#!/bin/sh\nexec cp -R "{folder}" "$6"\n')
        python.chmod(0o755)
        return str(python)

    def test_a_complete_result_folder_loads(self, pair, tmp_path, complete_result):
        scene, fixed, moving = pair
        output_volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
        registration = Registration(fixed, moving, QUICK, output_volume=output_volume,
                                    python=self.child_writing(complete_result, tmp_path), workspace=str(tmp_path))
        result = registration.finish()
        report = json.loads((complete_result / "report.json").read_text())
        assert moving.GetParentTransformNode().GetID() == result.transform.GetID()
        assert result.confidence == report["confidence"] and result.overlap == report["overlap_fraction"]
        assert output_volume.GetImageData() is not None

    @pytest.mark.parametrize(("edit", "message"), [
        (lambda folder: (folder / "moving_resampled.nii.gz").unlink(), "dpcn-med wrote no moving_resampled.nii.gz"),
        (lambda folder: (folder / "transform.tfm").unlink(), "dpcn-med wrote no transform.tfm"),
        (lambda folder: (folder / "report.json").unlink(), "dpcn-med wrote no report.json"),
        (_drop_report_key("overlap_fraction"),
         "report.json lacks overlap_fraction: the dpcn_med in Slicer's Python is older than this module"),
        (_drop_report_key("confidence"), "report.json lacks confidence: the dpcn_med in Slicer's Python is older"),
        (_overwrite("report.json", '{"confidence": "high", "overlap_fraction": 1.0}'),
         "report.json: confidence is 'high', expected a number"),
        (_overwrite("report.json", '{"confidence": 0.9,'), "report.json: not a readable JSON file"),
        (_overwrite("transform.tfm", "not a transform"), "transform.tfm: not a readable linear transform file"),
        (_overwrite("moving_resampled.nii.gz", "not an image"), "moving_resampled.nii.gz: not a readable volume"),
    ], ids=["no-resampled", "no-transform", "no-report", "no-overlap", "no-confidence", "text-confidence",
            "truncated-report", "bad-transform", "bad-resampled"])
    def test_an_incomplete_result_changes_nothing(self, pair, tmp_path, complete_result, edit, message):
        """A result folder missing a file, or a report value (a dpcn_med older than the module), is refused whole."""
        scene, fixed, moving = pair
        folder = tmp_path / "result"
        shutil.copytree(complete_result, folder)
        edit(folder)
        output_volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
        nodes = scene.GetNumberOfNodes()
        registration = Registration(fixed, moving, QUICK, output_volume=output_volume,
                                    python=self.child_writing(folder, tmp_path), workspace=str(tmp_path))
        with pytest.raises(RegistrationError, match=message):
            registration.finish()
        assert scene.GetNumberOfNodes() == nodes and moving.GetParentTransformNode() is None
        assert output_volume.GetImageData() is None and not registration.folder.exists()

    def test_bad_choices_are_refused_before_anything_runs(self, pair):
        scene, fixed, moving = pair
        with pytest.raises(ValueError, match="choose a fixed volume"):
            Registration(None, moving)
        with pytest.raises(ValueError, match="fixed: is both the fixed and the moving volume"):
            Registration(fixed, fixed)
        with pytest.raises(ValueError, match="fixed: the output volume is an input"):
            Registration(fixed, moving, output_volume=fixed)
        with pytest.raises(ValueError, match="moving: the fixed mask is one of the volumes being registered"):
            Registration(fixed, moving, fixed_mask=moving)
        empty = slicer.vtkMRMLScalarVolumeNode()
        empty.SetName("empty")
        scene.AddNode(empty)
        with pytest.raises(ValueError, match="empty: the moving volume holds no scalar image data"):
            Registration(fixed, empty)
        output = linear_transform(scene, np.eye(4), "result")
        output.SetAttribute(ROLE_ATTRIBUTES[1], moving.GetID())  # the moving volume's: reused, unlike other nodes'
        fixed.SetAndObserveTransformNodeID(output.GetID())
        with pytest.raises(ValueError, match="result: the fixed volume depends on this output transform"):
            Registration(fixed, moving, output_transform=output)
        fixed.SetAndObserveTransformNodeID(None)
        between = linear_transform(scene, rotation_ras(10, (0, 0, 1), (1, 2, 3)), "fine-tune")
        between.SetAndObserveTransformNodeID(output.GetID())
        moving.SetAndObserveTransformNodeID(between.GetID())  # MRML would refuse output's new parent: a cycle
        with pytest.raises(ValueError, match="result: the moving volume depends on this output transform"):
            Registration(fixed, moving, output_transform=output)
        moving.SetAndObserveTransformNodeID(output.GetID())  # directly under it: a repeated registration, allowed
        Registration(fixed, moving, QUICK, output_transform=output, python="/bin/true").cancel()

    def test_errors_name_the_nodes_not_the_deleted_files(self, pair, tmp_path):
        scene, fixed, moving = pair
        moving.SetName("CTBrain")
        image_to_volume(sitk.Image(turned_oblique_image(0).GetSize(), sitk.sitkInt16), moving)  # all zero
        registration = Registration(fixed, moving, QUICK, workspace=str(tmp_path))
        with pytest.raises(RegistrationError) as caught:
            registration.finish()
        assert "dpcn-med: error: CTBrain (the moving volume): all voxels equal 0" in str(caught.value)
        assert "DPCNRegistration-" not in str(caught.value)

    def test_a_volume_removed_while_it_runs_changes_nothing(self, pair, tmp_path, complete_result):
        scene, fixed, moving = pair
        registration = Registration(fixed, moving, QUICK, python=self.child_writing(complete_result, tmp_path),
                                    workspace=str(tmp_path))
        nodes = scene.GetNumberOfNodes()
        scene.RemoveNode(moving)
        with pytest.raises(RegistrationError, match="moving: was removed from the scene while it was being "
                                                    "registered"):
            registration.finish()
        assert scene.GetNumberOfNodes() == nodes - 1 and not registration.folder.exists()

    @pytest.mark.parametrize(("edit", "message"), [
        (lambda scene, base, fixed_parent: scene.RemoveNode(base),
         "user's transform: was removed from the scene while it was being registered"),
        (lambda scene, base, fixed_parent: base.SetMatrixTransformToParent(array_to_matrix(np.eye(4))),
         "moving: its parent transforms changed while it was being registered; the scene is left as it is: apply "
         "again"),
        (lambda scene, base, fixed_parent: fixed_parent.SetMatrixTransformToParent(
            array_to_matrix(rotation_ras(5, (0, 0, 1), (0, 0, 0)))),
         "fixed: its parent transforms changed while it was being registered"),
        (lambda scene, base, fixed_parent: scene.GetFirstNodeByName("moving").SetAndObserveTransformNodeID(
            fixed_parent.GetID()), "moving: its parent transforms changed"),
    ], ids=["base-removed", "base-edited", "fixed-parent-edited", "moving-reparented"])
    def test_a_frame_changed_while_it_runs_changes_nothing(self, pair, tmp_path, complete_result, edit, message):
        """The result is a matrix in the frame the volumes were registered in; placed after that frame changed, it
        hung under a removed node or put the moving volume off the fixed one."""
        scene, fixed, moving = pair
        base = linear_transform(scene, rotation_ras(20, (1, 0, 0), (5, -3, 8)), "user's transform")
        moving.SetAndObserveTransformNodeID(base.GetID())
        fixed_parent = linear_transform(scene, rotation_ras(-10, (0, 1, 0), (1, 2, 3)), "fixed's transform")
        fixed.SetAndObserveTransformNodeID(fixed_parent.GetID())
        registration = Registration(fixed, moving, QUICK, python=self.child_writing(complete_result, tmp_path),
                                    workspace=str(tmp_path))
        edit(scene, base, fixed_parent)
        parent, nodes = moving.GetParentTransformNode(), scene.GetNumberOfNodes()
        with pytest.raises(RegistrationError, match=message):
            registration.finish()
        assert scene.GetNumberOfNodes() == nodes and moving.GetParentTransformNode() is parent
        assert not registration.folder.exists()

    def test_an_output_holding_another_volume_is_left_alone(self, pair, tmp_path, complete_result):
        """After a first Apply the widget offered its transform as the output of the next; registering another
        moving volume into it moved the first one off its registration."""
        scene, fixed, moving = pair
        moving.SetName("CTBrain")
        other = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "MRBrainT2")
        image_to_volume(turned_oblique_image(PAIR_ANGLES["moving"]), other)
        python = self.child_writing(complete_result, tmp_path)
        first = register_volumes(fixed, moving, QUICK, python=python, workspace=str(tmp_path)).transform
        placed = transform_to_world(first)
        second = register_volumes(fixed, other, QUICK, output_transform=first, python=python,
                                  workspace=str(tmp_path)).transform
        assert second.GetID() != first.GetID() and second.GetName() == "MRBrainT2 to fixed"
        assert other.GetParentTransformNode().GetID() == second.GetID()
        assert moving.GetParentTransformNode().GetID() == first.GetID()
        assert first.GetAttribute(ROLE_ATTRIBUTES[1]) == moving.GetID()
        np.testing.assert_array_equal(transform_to_world(first), placed)
        # Registered again, the first volume reuses its own transform.
        again = register_volumes(fixed, moving, QUICK, output_transform=first, python=python, workspace=str(tmp_path))
        assert again.transform.GetID() == first.GetID()

    def test_a_moving_mask_covers_the_same_voxels_when_registered_again(self, pair, tmp_path, complete_result):
        """The second Apply registers the moving volume without the first result; its mask was placed with it, and
        came out shifted or refused."""
        scene, fixed, moving = pair
        size = moving.GetImageData().GetDimensions()
        label = sitk.Image(size, sitk.sitkUInt8)
        label.CopyInformation(volume_to_image(moving))
        label[size[0] // 4:size[0] // 2, size[1] // 4:size[1] // 2, :] = 1
        mask = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
        image_to_volume(label, mask)
        first = Registration(fixed, moving, QUICK, moving_mask=mask,
                             python=self.child_writing(complete_result, tmp_path), workspace=str(tmp_path))
        sent = sitk.ReadImage(str(first.folder / "moving_mask.nrrd"))
        output = first.finish().transform
        output.SetMatrixTransformToParent(array_to_matrix(rotation_ras(0, (0, 0, 1), (3 * 1.5, 0, 0))))
        again = Registration(fixed, moving, QUICK, moving_mask=mask, output_transform=output,
                             python=self.child_writing(complete_result, tmp_path), workspace=str(tmp_path))
        assert np.array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(again.folder / "moving_mask.nrrd"))),
                              sitk.GetArrayFromImage(sent))
        again.cancel()

    def test_a_failed_process_changes_nothing_and_leaves_no_files(self, pair, tmp_path):
        scene, fixed, moving = pair
        python = tmp_path / "python-without-site-packages"
        python.write_text(f'#!/bin/sh\nexec "{sys.executable}" -S "$@"\n')
        python.chmod(0o755)
        nodes = scene.GetNumberOfNodes()
        registration = Registration(fixed, moving, QUICK, python=str(python), workspace=str(tmp_path))
        with pytest.raises(RegistrationError, match="dpcn_med is not installed in this Python"):
            registration.finish()
        assert scene.GetNumberOfNodes() == nodes and moving.GetParentTransformNode() is None
        assert not registration.folder.exists()

    def test_cancel_stops_the_registration_and_cleans_up(self, pair, tmp_path):
        scene, fixed, moving = pair
        registration = Registration(fixed, moving, QUICK, workspace=str(tmp_path))
        started = time.perf_counter()
        registration.cancel()
        assert time.perf_counter() - started < 0.5  # the widget calls it on the GUI thread
        with pytest.raises(RegistrationError, match="cancelled"):
            registration.finish()
        assert registration.job.cancelled and registration.finished
        assert not registration.folder.exists() and moving.GetParentTransformNode() is None

    @pytest.mark.skipif(os.name != "posix", reason="the stand-in launcher is a shell script")
    def test_cancel_returns_at_once_and_stops_the_launchers_python(self, pair, tmp_path):
        """Cancel waited up to 15 s on the GUI thread for a launcher's Python it never stopped."""
        scene, fixed, moving = pair
        launcher, pid_file = launcher_of_a_sleeping_python(tmp_path)
        registration = Registration(fixed, moving, QUICK, python=launcher, workspace=str(tmp_path))
        started = time.perf_counter()
        while not pid_file.is_file() or not pid_file.read_text():
            time.sleep(0.01)
            assert time.perf_counter() - started < 30
        started = time.perf_counter()
        registration.cancel()
        assert time.perf_counter() - started < 0.5
        with pytest.raises(RegistrationError, match="cancelled"):
            registration.finish()
        assert time.perf_counter() - started < 5 and ended(int(pid_file.read_text()))
        assert not registration.folder.exists()

    def test_cancelled_files_go_without_finish(self, pair, tmp_path):
        """The widget drops a cancelled registration without finishing it; its files go once the process ends."""
        scene, fixed, moving = pair
        registration = Registration(fixed, moving, QUICK, workspace=str(tmp_path))
        registration.cancel()
        registration.job.wait(30)
        started = time.perf_counter()
        while registration.folder.exists() and time.perf_counter() - started < 10:
            time.sleep(0.05)
        assert not registration.folder.exists()


class TestModuleFiles:
    """The module file, its .ui, its CMake lists and the Extensions Index entry agree with each other."""

    source = (MODULE / "DPCNRegistration.py").read_text()
    tree = ast.parse(source)
    ui = ElementTree.parse(MODULE / "Resources" / "UI" / "DPCNRegistration.ui").getroot()

    def _parameter_fields(self) -> dict[str, ast.expr]:
        cls = next(n for n in self.tree.body if isinstance(n, ast.ClassDef) and n.name.endswith("ParameterNode"))
        return {n.target.id: n.annotation for n in cls.body if isinstance(n, ast.AnnAssign)}

    def _widgets(self) -> dict[str, ElementTree.Element]:
        return {w.get("name"): w for w in self.ui.iter("widget")}

    def test_has_module_widget_logic_and_test_classes(self):
        classes = {n.name for n in self.tree.body if isinstance(n, ast.ClassDef)}
        assert {"DPCNRegistration", "DPCNRegistrationParameterNode", "DPCNRegistrationWidget",
                "DPCNRegistrationLogic", "DPCNRegistrationTest"} <= classes

    def test_every_ui_name_the_widget_uses_exists(self):
        used = {n.attr for n in ast.walk(self.tree)
                if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute) and n.value.attr == "ui"}
        assert used and used <= set(self._widgets()), used - set(self._widgets())

    def test_parameter_names_match_the_parameter_node(self):
        bound = {}
        for widget in self.ui.iter("widget"):
            for prop in widget.findall("property"):
                if prop.get("name") == "SlicerParameterName":
                    bound[prop.find("string").text] = widget
        assert set(bound) == set(self._parameter_fields())
        for name, annotation in self._parameter_fields().items():
            if isinstance(annotation, ast.Subscript) and "Choice" in ast.unparse(annotation):
                choices = ast.literal_eval(re.search(r"Choice\((\[.*?\])\)", ast.unparse(annotation)).group(1))
                items = [i.find("property/string").text for i in bound[name].findall("item")]
                assert items == choices, name

    def test_cmake_lists_every_lib_file_and_resource(self):
        cmake = (MODULE / "CMakeLists.txt").read_text()
        listed = set(re.findall(r"\$\{MODULE_NAME\}(Lib/\w+\.py|\.py)", cmake))
        present = {f"Lib/{p.name}" for p in (MODULE / "DPCNRegistrationLib").glob("*.py")} | {".py"}
        assert listed == present
        for resource in re.findall(r"(Resources/\S+)", cmake):
            assert (MODULE / resource.replace("${MODULE_NAME}", "DPCNRegistration")).is_file(), resource

    def test_extension_metadata_and_index_entry(self):
        cmake = (MODULE.parent / "CMakeLists.txt").read_text()
        for key in ("HOMEPAGE", "CATEGORY", "CONTRIBUTORS", "DESCRIPTION", "ICONURL", "DEPENDS"):
            assert re.search(rf"set\(EXTENSION_{key} \S", cmake), key
        assert re.search(r'set\(EXTENSION_DEPENDS "?PyTorch', cmake)
        entry = json.loads((MODULE.parent / "DPCNRegistration.json").read_text())
        assert {"$schema", "category", "scm_url"} <= set(entry) and "PyTorch" in entry["build_dependencies"]
        assert re.search(r"^project\(DPCNRegistration\)", cmake, re.MULTILINE)
        assert os.path.getsize(MODULE / "Resources" / "Icons" / "DPCNRegistration.png") > 0
