"""Ground-truth helpers: known physical transforms and the target registration error."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.geometry import homogeneous_matrix


def _asymmetric_image() -> sitk.Image:
    rng = np.random.default_rng(0)
    array = rng.random((12, 14, 16)).astype(np.float32)
    array[3:9, 4:10, 2:7] += 5.0
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.9, 1.1, 2.0))
    image.SetOrigin((-10.0, 4.0, 7.0))
    image.SetDirection((0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0))
    return image


class TestRandomSimilarity:
    def test_ranges(self):
        rng = np.random.default_rng(1)
        for _ in range(20):
            transform = random_similarity(rng, np.array([1.0, 2.0, 3.0]), max_shift_mm=40.0, scale_range=(0.85, 1.15))
            assert 0.85 <= transform.GetScale() <= 1.15
            assert np.linalg.norm(transform.GetTranslation()) <= 40.0
            np.testing.assert_allclose(transform.GetCenter(), (1.0, 2.0, 3.0))

    def test_same_seed_same_transform(self):
        a = random_similarity(np.random.default_rng(5), np.zeros(3))
        b = random_similarity(np.random.default_rng(5), np.zeros(3))
        assert a.GetParameters() == b.GetParameters()


class TestMovedCopy:
    def test_moved_at_t_of_x_equals_image_at_x(self):
        image = _asymmetric_image()
        truth = random_similarity(np.random.default_rng(2), np.zeros(3), scale_range=(0.8, 1.2))
        moved = moved_copy(image, truth)
        resampled = sitk.Resample(moved, image, truth, sitk.sitkLinear, -1.0)
        inner = (slice(1, -1),) * 3  # border voxels may fall a rounding error outside the moved grid
        np.testing.assert_allclose(sitk.GetArrayFromImage(resampled)[inner], sitk.GetArrayFromImage(image)[inner],
                                   atol=1e-4)

    def test_input_untouched(self):
        image = _asymmetric_image()
        origin = image.GetOrigin()
        moved_copy(image, random_similarity(np.random.default_rng(3), np.zeros(3)))
        assert image.GetOrigin() == origin


class TestForegroundCorners:
    def test_corners_of_the_bright_block(self):
        image = _asymmetric_image()
        corners = foreground_corners(image)
        assert corners.shape == (8, 3)
        expected = image.TransformContinuousIndexToPhysicalPoint((1.5, 3.5, 2.5))
        assert any(np.allclose(c, expected) for c in corners)


class TestTargetRegistrationError:
    def test_pure_shift(self):
        truth = sitk.TranslationTransform(3, (1.0, 2.0, 2.0))
        points = np.random.default_rng(0).normal(size=(8, 3))
        assert target_registration_error(sitk.Transform(3, sitk.sitkIdentity), truth, points) == pytest.approx(3.0)

    def test_zero_for_the_same_transform(self):
        truth = random_similarity(np.random.default_rng(4), np.zeros(3))
        copy = sitk.Similarity3DTransform(truth)
        assert target_registration_error(copy, truth, np.eye(3) * 50) == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(homogeneous_matrix(copy), homogeneous_matrix(truth))
