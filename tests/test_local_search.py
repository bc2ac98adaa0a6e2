"""The refinement's search in torch: pyramid levels, interpolation, samples, pose parameters, the regular-step
descent, and the same choice on every device."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.benchmark import CASES, rotation_in_bin
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.geometry import rotation_angle
from dpcn_med.local_search import (
    MIN_SAMPLES,
    fixed_samples,
    itk_step_weights,
    pyramid_level,
    regular_step_descent,
    residual_matrices,
    sample,
    volume,
)
from dpcn_med.preprocess import foreground_box
from dpcn_med.registration import register
from tests.conftest import shared_path
from tests.test_registration import mni_2mm

CPU = torch.device("cpu")


def _oblique(size: tuple[int, int, int] = (21, 18, 15)) -> sitk.Image:
    """A smooth random volume with anisotropic spacing, an origin and an oblique direction."""
    array = np.random.default_rng(0).random(size[::-1]).astype(np.float32)
    image = sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(array), 1.0)
    image.SetSpacing((1.0, 1.5, 2.0))
    image.SetOrigin((10.0, -20.0, 30.0))
    image.SetDirection(sitk.VersorTransform((1, 2, 3), 0.4).GetMatrix())
    return image


class TestPyramid:
    def test_a_level_without_smoothing_is_sitks_bin_shrink(self):
        image = _oblique()
        level = pyramid_level(volume(image, CPU), (2, 3, 2), 0.0)
        expected = sitk.BinShrink(image, [2, 3, 2])
        assert tuple(level.size) == expected.GetSize()
        np.testing.assert_allclose(level.origin, expected.GetOrigin(), atol=1e-9)
        np.testing.assert_allclose(level.spacing, expected.GetSpacing())
        np.testing.assert_allclose(level.values[0, 0].numpy(), sitk.GetArrayFromImage(expected), rtol=1e-5)

    def test_a_smoothed_level_is_itks_gaussian_then_shrink(self):
        """Box average then the rest of the Gaussian on the shrunk grid, against ITK's Gaussian on the whole image
        sampled at the same points: the same image but for the blur's shape at sharp edges (on average within 2% of
        its range; a level half a voxel off correlates at 0.96)."""
        image = sitk.Cast(mni_2mm(), sitk.sitkFloat32)
        level = pyramid_level(volume(image, CPU), (4, 4, 4), 4.0)
        smoothed = sitk.SmoothingRecursiveGaussian(image, 4.0)
        reference = sitk.Resample(smoothed, tuple(int(n) for n in level.size), sitk.Transform(), sitk.sitkLinear,
                                  level.origin.tolist(), level.spacing.tolist(), level.direction.flatten().tolist())
        ours, theirs = level.values[0, 0].numpy(), sitk.GetArrayFromImage(reference)
        inner = (slice(2, -2),) * 3  # away from the edges, where ITK's recursive filter and our replicated pad differ
        ours, theirs = ours[inner], theirs[inner]
        assert np.abs(ours - theirs).mean() < 0.02 * (theirs.max() - theirs.min())
        assert np.corrcoef(ours.ravel(), theirs.ravel())[0, 1] > 0.995


class TestSampling:
    def test_values_are_itks_linear_interpolation(self):
        image = _oblique()
        points = np.random.default_rng(1).random((200, 3)) * (np.asarray(image.GetSize()) - 1)
        physical = np.array([image.TransformContinuousIndexToPhysicalPoint(point.tolist()) for point in points])
        values, inside = sample(volume(image, CPU), torch.as_tensor(physical, dtype=torch.float32)[None])
        expected = [image.EvaluateAtPhysicalPoint(point.tolist(), sitk.sitkLinear) for point in physical]
        assert inside.all()
        np.testing.assert_allclose(values[0].numpy(), expected, rtol=1e-4, atol=1e-5)

    def test_the_image_ends_half_a_voxel_beyond_its_edge_voxels(self):
        image = _oblique()
        edge = [[-0.49, 3, 3], [-0.51, 3, 3], [20.49, 3, 3], [20.51, 3, 3]]
        physical = [image.TransformContinuousIndexToPhysicalPoint(index) for index in edge]
        _, inside = sample(volume(image, CPU), torch.tensor(physical, dtype=torch.float32)[None])
        assert inside[0].tolist() == [True, False, True, False]

    def test_samples_lie_in_the_mask_and_a_small_mask_still_gets_enough(self):
        image = mni_2mm()
        mask = sitk.Image(image.GetSize(), sitk.sitkUInt8)
        mask.CopyInformation(image)
        mask[40:44, 50:54, 40:44] = 1  # 64 voxels
        generator = torch.Generator().manual_seed(1)
        samples = fixed_samples(volume(image, CPU), mask, 30_000, 32, np.zeros(3), generator)
        assert samples.count == MIN_SAMPLES
        indices = np.array([image.TransformPhysicalPointToContinuousIndex(point) for point in
                            samples.points.double().numpy()[:500]])
        assert (indices >= [39.5, 49.5, 39.5]).all() and (indices <= [43.5, 53.5, 43.5]).all()
        again = fixed_samples(volume(image, CPU), mask, 30_000, 32, np.zeros(3), torch.Generator().manual_seed(1))
        assert torch.equal(again.points, samples.points)  # the seed decides


class TestPoses:
    def test_parameters_are_millimetres_of_shift(self):
        centre = np.array([10.0, 20.0, 30.0])
        assert torch.allclose(residual_matrices(torch.zeros(2, 7), centre, 50.0),
                              torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
        # A rotation parameter of 5 mm at a radius of 50 mm turns by 0.1 radians, about the centre.
        matrix = residual_matrices(torch.tensor([[0.0, 0.0, 5.0, 1.0, 2.0, 3.0]]), centre, 50.0)[0]
        assert rotation_angle(matrix[:3, :3]).item() == pytest.approx(0.1)
        torch.testing.assert_close(matrix[:3, :3] @ torch.as_tensor(centre) + matrix[:3, 3],
                                   torch.as_tensor(centre) + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
        scaled = residual_matrices(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 50 * math.log(1.1)]]), centre, 50.0)
        assert torch.linalg.det(scaled[0, :3, :3]).item() == pytest.approx(1.1 ** 3)


class TestDescent:
    @staticmethod
    def _bowls(parameters: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Pose k's metric: a bowl of depth -(k + 1) centred at (k, -k)."""
        centres = torch.stack([poses, -poses], dim=1).to(parameters)
        return ((parameters - centres) ** 2).sum(1) - (poses + 1).to(parameters)

    def test_each_pose_finds_its_own_minimum(self):
        parameters, values = regular_step_descent(self._bowls, torch.zeros(3, 2, dtype=torch.float64), 1.0, 200)
        torch.testing.assert_close(parameters, torch.tensor([[0.0, 0.0], [1.0, -1.0], [2.0, -2.0]],
                                                            dtype=torch.float64), atol=0.02, rtol=0)
        torch.testing.assert_close(values, torch.tensor([-1.0, -2.0, -3.0], dtype=torch.float64), atol=1e-3,
                                   rtol=0)

    def test_itks_steps_move_a_translation_by_the_step_and_a_rotation_further(self):
        """One step from a gradient of 1 (in mm of shift) along x's rotation and along x's translation, radius 100 mm:
        the translation moves by the step, the rotation by twice as much (ITK's versor), and the norm hardly feels
        the rotation (its weight 2/100)."""
        gradient = torch.tensor([1.0, 0, 0, 1.0, 0, 0], dtype=torch.float64)

        def plane(parameters: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
            return parameters @ gradient

        parameters, _ = regular_step_descent(plane, torch.zeros(1, 6, dtype=torch.float64), 0.5, 1,
                                             weights=itk_step_weights(6, 100.0, CPU))
        norm = math.hypot(1.0, 2 / 100)
        torch.testing.assert_close(parameters[0], -0.5 / norm * torch.tensor([2.0, 0, 0, 1.0, 0, 0],
                                                                             dtype=torch.float64))
        assert itk_step_weights(7, 100.0, CPU)[0][6].item() == pytest.approx(0.01)

    def test_it_stops_at_the_iteration_limit(self):
        parameters, _ = regular_step_descent(self._bowls, torch.zeros(3, 2, dtype=torch.float64), 0.1, 3)
        assert (parameters.norm(dim=1)[1:] == pytest.approx(0.3)) and parameters[0].norm() == 0  # pose 0 is there

    def test_poses_far_behind_the_leader_stop_with_it_unless_closing_in(self):
        """Pose 1 (a bowl 3 deep) leads and converges first. Pose 0 wanders down a slope too gentle to get within half
        of the leader's depth in the steps left, and stops with it; pose 2, far off in a bowl 4 deep, closes in fast
        enough, goes on, and ends in its own minimum."""
        def metric(parameters: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
            centres = torch.tensor([[0.0, 0.0], [0.5, 0.0], [30.0, 0.0]], dtype=torch.float64)[poses]
            bowls = ((parameters - centres) ** 2).sum(1) * 0.01 - torch.tensor([0.0, 3.0, 4.0],
                                                                                dtype=torch.float64)[poses]
            slope = -1 - 1e-4 * parameters[:, 0]
            return torch.where(poses == 0, slope, bowls)

        start = torch.zeros(3, 2, dtype=torch.float64)
        parameters, values = regular_step_descent(metric, start, 0.5, 500, settle=0.5)
        assert parameters[0, 0] < 20  # 0.5 per step: it stopped within 40 steps, not at 250
        assert abs(parameters[1, 0] - 0.5) < 0.05 and abs(parameters[2, 0] - 30) < 0.05
        assert values[2] == pytest.approx(-4, abs=1e-3)
        alone, _ = regular_step_descent(metric, start, 0.5, 500)
        assert alone[0, 0] == pytest.approx(250)  # without settle, it walks on to the last step


class TestDevices:
    def test_the_search_keeps_to_the_meta_device(self):
        """The pyramid, the interpolation and the residual poses make no tensor off their inputs' device."""
        meta = torch.device("meta")
        image = volume(_oblique(), meta)
        level = pyramid_level(image, (2, 2, 2), 3.0)
        assert level.values.device == meta and tuple(level.size) == (10, 9, 7)
        points = torch.empty(4, 100, 3, device=meta)
        values, inside = sample(level, points)
        assert values.device == meta and inside.device == meta and values.shape == (4, 100)
        assert residual_matrices(torch.zeros(4, 6, device=meta), np.zeros(3), 50.0).device == meta

    @pytest.mark.shared_data
    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run where one is lent)")
    def test_the_gpu_registers_as_the_cpu(self):
        """The whole registration on the GPU (solver, pyramid, search), the seg3d head T1 to its pseudo-CT turned
        by 150 degrees: the same start kept, and a pose within a quarter of a millimetre of the CPU's (sums in
        another order: 0.03-0.15 mm apart on an H200, docs/benchmarks/device_time.md)."""
        shared_path("seg3d/MR.nii.gz")
        fixed, whole = CASES["seg3d-pseudo-ct"][2]()
        truth = rotation_in_bin(np.random.default_rng(5), 150, 151, foreground_box(fixed)[0], 40.0)
        moving = moved_copy(whole, truth)
        on_cpu, on_gpu = (register(fixed, moving, device=device) for device in ("cpu", "cuda"))
        corners = foreground_corners(fixed)
        assert on_gpu.device.startswith("cuda") and on_gpu.candidate == on_cpu.candidate
        assert target_registration_error(on_gpu.fixed_to_moving, on_cpu.fixed_to_moving, corners) < 0.25
        assert target_registration_error(on_gpu.fixed_to_moving, truth, corners) < 0.5
        assert on_gpu.metric["refined"] == pytest.approx(on_cpu.metric["refined"], abs=0.01)
