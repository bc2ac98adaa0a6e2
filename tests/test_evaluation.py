"""Ground-truth helpers: known physical transforms and the target registration error."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.evaluation import (
    foreground_corners,
    moved_copy,
    random_similarity,
    rotation_error,
    target_registration_error,
)
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

    @pytest.mark.parametrize("centre, options, message", [
        (np.array([0.0, np.nan, 0.0]), {}, "centre must be 3 finite numbers"),
        (np.zeros(2), {}, "centre must be 3 finite numbers"),
        (np.zeros(3), {"max_shift_mm": -1.0}, "max_shift_mm must be finite"),
        (np.zeros(3), {"max_shift_mm": np.inf}, "max_shift_mm must be finite"),
        (np.zeros(3), {"scale_range": (-1.0, 1.0)}, "0 < low <= high"),
        (np.zeros(3), {"scale_range": (1.2, 0.8)}, "0 < low <= high"),
        (np.zeros(3), {"scale_range": (1.0, np.nan)}, "0 < low <= high"),
    ])
    def test_refuses_invalid_settings(self, centre, options, message):
        with pytest.raises(ValueError, match=message):
            random_similarity(np.random.default_rng(0), centre, **options)


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

    def test_a_mask_on_its_own_grid(self):
        """The box was found in the mask's voxels and placed with the image's geometry: 15 mm off here."""
        mask = sitk.Image(20, 20, 20, sitk.sitkUInt8)
        mask.SetSpacing((0.5, 2.0, 1.0))
        mask.SetOrigin((-7.0, 3.0, 11.0))
        mask[4:8, 2:5, 6:9] = 1  # SimpleITK slices [x, y, z]: voxels x 4-7, y 2-4, z 6-8
        corners = foreground_corners(_asymmetric_image(), mask)
        np.testing.assert_allclose(corners.min(0), (-7.0 + 3.5 * 0.5, 3.0 + 1.5 * 2.0, 11.0 + 5.5))
        np.testing.assert_allclose(corners.max(0), (-7.0 + 7.5 * 0.5, 3.0 + 4.5 * 2.0, 11.0 + 8.5))

    # Before: ITK's RuntimeError "No label object with label 1" from LabelShapeStatisticsImageFilter.
    def test_empty_mask(self):
        mask = sitk.Image(16, 14, 12, sitk.sitkUInt8)
        with pytest.raises(InputError, match=r"mask is empty \(no voxel > 0\)"):
            foreground_corners(_asymmetric_image(), mask)

    def test_blank_image(self):
        with pytest.raises(InputError, match="image has no foreground"):
            foreground_corners(sitk.Image(16, 14, 12, sitk.sitkFloat32))


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

    def test_lists_of_points(self):  # before: AttributeError ('list' object has no attribute 'tolist')
        shift = sitk.TranslationTransform(3, (3.0, 0.0, 4.0))
        identity = sitk.Transform(3, sitk.sitkIdentity)
        assert target_registration_error(shift, identity, [[0.0, 0.0, 0.0], (1, 2, 3)]) == pytest.approx(5.0)
        assert target_registration_error(shift, identity, ((1.0, 2.0, 3.0),)) == pytest.approx(5.0)

    # Before: an empty set gave NaN with a RuntimeWarning, a NaN point NaN, a single (3,) point a SWIG TypeError.
    @pytest.mark.parametrize(("points", "message"), [
        (np.zeros((0, 3)), r"points has shape \(0, 3\); expected \(K, 3\) with at least one point"),
        ([], r"points has shape \(0,\); expected \(K, 3\)"),
        (np.array([1.0, 2.0, 3.0]), r"points has shape \(3,\); expected \(K, 3\)"),
        (np.zeros((4, 2)), r"points has shape \(4, 2\); expected \(K, 3\)"),
        ([[0.0, 0.0, 0.0], [np.nan, 1.0, 2.0]], r"points holds 1 points with NaN or Inf coordinates"),
        ([[np.inf, 0.0, 0.0]], r"points holds 1 points with NaN or Inf coordinates"),
        ([[1.0, 2.0, 3.0], [1.0, 2.0]], r"points is \[\[1\.0, 2\.0, 3\.0\], \[1\.0, 2\.0\]\] \(list\); "
                                        r"expected \(K, 3\)"),
        ("corners", r"points is 'corners' \(str\); expected \(K, 3\) numbers"),
    ], ids=["empty", "empty list", "one flat point", "2-D points", "nan", "inf", "ragged", "string"])
    def test_bad_points_are_refused(self, points, message):
        identity = sitk.Transform(3, sitk.sitkIdentity)
        with pytest.raises(InputError, match=message):
            target_registration_error(identity, identity, points)


class TestRotationError:
    @staticmethod
    def turned(degrees: float, axis=(1.0, 2.0, -0.5), scale: float = 1.0, shift=(0.0, 0.0, 0.0),
               centre=(0.0, 0.0, 0.0)) -> sitk.Similarity3DTransform:
        transform = sitk.Similarity3DTransform()
        transform.SetCenter(centre)
        transform.SetRotation(axis, math.radians(degrees))
        transform.SetScale(scale)
        transform.SetTranslation(shift)
        return transform

    def test_the_angle_between_the_rotations_whatever_the_scale_shift_and_centre(self):
        first = self.turned(30.0, scale=1.3, shift=(5.0, -2.0, 9.0), centre=(10.0, 0.0, 4.0))
        assert rotation_error(first, sitk.Transform(3, sitk.sitkIdentity)) == pytest.approx(30.0, abs=1e-9)
        assert rotation_error(first, self.turned(30.0, scale=0.8)) == pytest.approx(0.0, abs=1e-6)
        assert rotation_error(first, self.turned(-15.0)) == pytest.approx(45.0, abs=1e-9)
        assert rotation_error(self.turned(179.0), self.turned(-179.0)) == pytest.approx(2.0, abs=1e-6)
        assert rotation_error(self.turned(180.0), sitk.Transform(3, sitk.sitkIdentity)) == pytest.approx(180.0)

    def test_a_small_shear_does_not_count(self):
        affine = sitk.AffineTransform(3)
        matrix = np.asarray(self.turned(20.0).GetMatrix()).reshape(3, 3) @ np.array([[1, 0.01, 0], [0, 1, 0],
                                                                                      [0, 0, 1.02]])
        affine.SetMatrix(matrix.ravel().tolist())
        assert rotation_error(affine, self.turned(20.0)) < 0.5

    def test_a_displacement_field_is_refused(self):
        field = sitk.DisplacementFieldTransform(sitk.Image([4, 4, 4], sitk.sitkVectorFloat64, 3))
        with pytest.raises(ValueError):
            rotation_error(field, sitk.Transform(3, sitk.sitkIdentity))
