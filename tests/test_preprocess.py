"""From a physical image to a solver grid."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import grid_centre
from dpcn_med.preprocess import (
    canonical_grid,
    foreground_box,
    normalize_intensity,
    resample_to_grid,
    solver_grid,
    solver_slice,
    to_tensor,
)


def _box_image() -> sitk.Image:
    """A bright box (x 10..29, y 5..14, z 8..11) in a 40 x 20 x 16 image, spacing (1, 2, 3), rotated direction."""
    array = np.zeros((16, 20, 40), dtype=np.float32)
    array[8:12, 5:15, 10:30] = 100.0
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 2.0, 3.0))
    image.SetOrigin((-5.0, 7.0, 1.0))
    image.SetDirection((0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    return image


class TestForegroundBox:
    def test_physical_centre_and_diagonal(self):
        image = _box_image()
        centre, diagonal = foreground_box(image)
        expected = np.array(image.TransformContinuousIndexToPhysicalPoint((19.5, 9.5, 9.5)))
        np.testing.assert_allclose(centre, expected, atol=1e-9)
        assert diagonal == pytest.approx(np.sqrt(20.0 ** 2 + 20.0 ** 2 + 12.0 ** 2))

    def test_constant_image_has_no_foreground(self):
        image = sitk.Image([8, 8, 8], sitk.sitkFloat32) + 3.0
        with pytest.raises(InputError, match="no foreground"):
            foreground_box(image)


class TestCanonicalGrid:
    def test_centred_on_the_foreground_with_the_requested_fill(self):
        image = _box_image()
        grid = canonical_grid(image, 32, fill=0.5)
        centre, diagonal = foreground_box(image)
        np.testing.assert_allclose(grid.centre, centre)
        assert grid.spacing == pytest.approx(diagonal / 16)

    def test_resampled_grid_has_the_canonical_geometry_and_content(self):
        image = _box_image()
        grid = canonical_grid(image, 32, fill=0.5)
        resampled = resample_to_grid(image, grid)
        assert resampled.GetSize() == (32, 32, 32)
        assert resampled.GetDirection() == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        centre_voxel = (grid_centre(32),) * 3
        np.testing.assert_allclose(resampled.TransformIndexToPhysicalPoint(centre_voxel), grid.centre, atol=1e-9)
        assert resampled[centre_voxel] == pytest.approx(100.0)
        assert resampled[0, 0, 0] == 0.0


class TestSolverGrid:
    def test_tensor_layout_and_range(self):
        tensor, grid = solver_grid(_box_image(), 16)
        assert tensor.shape == (1, 1, 16, 16, 16)
        assert tensor.min() >= 0.0 and tensor.max() <= 1.0
        assert grid.size == 16

    def test_normalisation_maps_foreground_percentiles_to_the_unit_range(self):
        array = np.linspace(0, 1000, 16 * 16 * 16, dtype=np.float32).reshape(16, 16, 16)
        normalised = sitk.GetArrayFromImage(normalize_intensity(sitk.GetImageFromArray(array)))
        assert normalised.min() == 0.0 and normalised.max() == 1.0

    def test_a_pair_can_share_one_spacing(self):
        _, fixed_grid = solver_grid(_box_image(), 16)
        _, moving_grid = solver_grid(_box_image(), 16, spacing=fixed_grid.spacing * 2)
        assert moving_grid.spacing == pytest.approx(2 * fixed_grid.spacing)

    def test_slice_is_the_central_plane_of_the_cube(self):
        image = _box_image()
        cube, _ = solver_grid(image, 32)
        plane = solver_slice(image, 32, fill=0.5)
        assert plane.shape == (1, 1, 32, 32)
        torch.testing.assert_close(plane[0, 0], cube[0, 0, grid_centre(32)])

    def test_to_tensor_rejects_2d_images(self):
        with pytest.raises(InputError, match="image is 2-D"):
            to_tensor(sitk.Image([8, 8], sitk.sitkFloat32))
