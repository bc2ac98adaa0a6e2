"""From a physical image to a solver grid."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import grid_centre
from dpcn_med.preprocess import (
    Preprocessing,
    bounding_box,
    canonical_grid,
    detect_modality,
    dilate,
    foreground_box,
    foreground_mask,
    normalize_intensity,
    normalize_modality,
    pair_grids,
    prepare,
    resample_to_grid,
    shrink_factors,
    solver_grid,
    solver_slice,
    to_tensor,
    voxelize,
)
from tests.conftest import shared_path


def _box_image() -> sitk.Image:
    """A bright box (x 10..29, y 5..14, z 8..11) in a 40 x 20 x 16 image, spacing (1, 2, 3), rotated direction."""
    array = np.zeros((16, 20, 40), dtype=np.float32)
    array[8:12, 5:15, 10:30] = 100.0
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 2.0, 3.0))
    image.SetOrigin((-5.0, 7.0, 1.0))
    image.SetDirection((0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    return image


class TestPreprocessingSettings:
    def test_defaults_and_typical_values_construct(self):
        assert Preprocessing() == Preprocessing(fill=0.5, percentiles=(1, 99), ct_window=[-1000, 1000])
        settings = Preprocessing(fill=1, outline_weight=0, max_voxels=np.int64(1000), percentiles=[0, 100],
                                 ct_window=(np.float32(-1024), 3071), ct_detection_hu=-1024)
        assert settings.percentiles == (0.0, 100.0) and settings.ct_window == (-1024.0, 3071.0)
        assert type(settings.max_voxels) is int and type(settings.fill) is float

    @pytest.mark.parametrize(("changes", "message"), [
        ({"fill": 0.0}, r"fill is 0\.0; expected a finite number >= 0\.1 and <= 1$"),
        ({"fill": 1.5}, r"fill is 1\.5; expected a finite number >= 0\.1"),
        ({"fill": "0.5"}, r"fill is '0\.5' \(str\); expected a finite number"),
        ({"outline_weight": 3.0}, r"outline_weight is 3\.0; expected a finite number >= 0 and <= 1$"),
        ({"outline_weight": float("nan")}, r"outline_weight is nan; expected a finite number"),
        ({"max_voxels": 0}, r"max_voxels is 0; expected an integer >= 1000$"),
        ({"max_voxels": 2e6}, r"max_voxels is 2000000\.0 \(float\); expected an integer >= 1000$"),
        ({"percentiles": (99.0, 1.0)},
         r"percentiles is \(99\.0, 1\.0\); expected \(low, high\) with 0 <= low < high <= 100$"),
        ({"percentiles": (1.0,)}, r"percentiles is \(1\.0,\): 1 values; expected 2$"),
        ({"percentiles": (-1.0, 99.0)},
         r"percentiles is \(-1\.0, 99\.0\); expected \(low, high\) with 0 <= low < high <= 100$"),
        ({"percentiles": (1.0, float("nan"))}, r"percentiles\[1\] is nan; expected a finite number"),
        ({"ct_window": (0.0, 0.0)}, r"ct_window is \(0\.0, 0\.0\); expected \(low, high\) with low < high$"),
        ({"ct_window": "-1000,1000"}, r"ct_window is '-1000,1000' \(str\); expected a tuple of 2 values$"),
        ({"ct_detection_hu": float("-inf")}, r"ct_detection_hu is -inf; expected a finite number$"),
    ])
    def test_bad_values_are_refused(self, changes, message):
        with pytest.raises(InputError, match=message):
            Preprocessing(**changes)


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


def _padded_ct(lowest_hu: int = 0, insert_hu: int | None = None) -> tuple[sitk.Image, np.ndarray]:
    """A body off-centre in its scanner's circular field of view, -3024 HU outside it, int16: ``(image, body)``.

    Air at -1000 HU; the body ramps along x from ``lowest_hu`` to 300 HU (from -900, any shift of Otsu's threshold
    moves the outline); ``insert_hu`` marks a rod of 4 voxels inside it (metal at 3071 HU).
    """
    z, y, x = np.mgrid[:16, :48, :48]
    array = np.full(x.shape, -1000, dtype=np.int16)
    body = (((x - 23.5) / 13) ** 2 + ((y - 28) / 9) ** 2 <= 1) & (z > 2) & (z < 13)
    array[body] = (lowest_hu + (300 - lowest_hu) * (x[body] - 10) / 27).astype(np.int16)
    if insert_hu is not None:
        array[(abs(x - 20) < 1) & (abs(y - 28) < 1) & (z > 5) & (z < 10)] = insert_hu
    array[np.hypot(x - 23.5, y - 23.5) > 23.5] = -3024
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((1.0, 1.0, 2.0))
    return image, body


def _two_objects() -> tuple[sitk.Image, np.ndarray, sitk.Image]:
    """A large sphere (100) and, right of x = 55, a smaller ellipsoid (80): ``(image, smaller, mask)``, the mask
    holding the image's right half."""
    z, y, x = np.mgrid[:40, :60, :100]
    array = np.zeros(x.shape, dtype=np.float32)
    array[(x - 25) ** 2 + (y - 30) ** 2 + (z - 20) ** 2 < 15 ** 2] = 100.0
    smaller = ((x - 75) / 12) ** 2 + ((y - 30) / 9) ** 2 + ((z - 20) / 7) ** 2 <= 1
    array[smaller] = 80.0
    image = sitk.GetImageFromArray(array)
    mask = sitk.GetImageFromArray((x >= 55).astype(np.uint8))
    return image, smaller, mask


def _on_grid(array: np.ndarray, image: sitk.Image) -> sitk.Image:
    out = sitk.GetImageFromArray(array)
    out.CopyInformation(image)
    return out


class TestForegroundMask:
    def test_scanner_padding_is_neither_counted_nor_foreground(self):
        """Otsu over the raw histogram split the padding from air and gave the whole field of view."""
        image, body = _padded_ct()
        foreground = sitk.GetArrayFromImage(foreground_mask(image)).astype(bool)
        np.testing.assert_array_equal(foreground, body)

    @pytest.mark.shared_data
    def test_resampled_padding_is_not_foreground(self):
        """The MRI-DIR CT at 3 mm: its -2048 HU padding, resampled, runs from -2049 to -1025 HU; counted, 18378 voxels
        of air (below -500 HU) joined the phantom."""
        image = sitk.ReadImage(str(shared_path("mridir/mridir_ct_3p0mm.nii.gz")))
        foreground = sitk.GetArrayFromImage(foreground_mask(image)).astype(bool)
        assert foreground.sum() > 100_000 and not (sitk.GetArrayFromImage(image)[foreground] < -500).any()

    def test_metal_in_a_ct_is_not_an_outlier(self):
        """3071 HU lies 2.2 of the bulk's 0.1-99.9 percentile ranges beyond it, not far enough to be clipped: the
        foreground is Otsu's over the field of view."""
        image, body = _padded_ct(lowest_hu=-900, insert_hu=3071)
        field_of_view = sitk.Cast(image != -3024, sitk.sitkUInt8)
        unclipped = sitk.OtsuThreshold(sitk.Cast(image, sitk.sitkFloat32), field_of_view, 0, 1, 128, True, 1)
        largest = sitk.RelabelComponent(sitk.ConnectedComponent(unclipped), sortByObjectSize=True) == 1
        expected = sitk.GetArrayFromImage(sitk.BinaryFillhole(largest))
        assert 0 < expected.sum() < body.sum()  # the threshold falls within the body's ramp
        np.testing.assert_array_equal(sitk.GetArrayFromImage(foreground_mask(image)), expected)

    def test_a_few_hot_voxels_do_not_take_over(self):
        """8 voxels at 300 times the maximum (a hot pixel, fit failures) made the foreground 1 voxel."""
        image, smaller, _ = _two_objects()
        array = sitk.GetArrayFromImage(image) + np.random.default_rng(0).normal(0, 2, smaller.shape).astype(np.float32)
        clean = sitk.GetArrayFromImage(foreground_mask(_on_grid(array, image)))
        array.flat[np.flatnonzero(smaller)[::500][:8]] = 300 * array.max()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(foreground_mask(_on_grid(array, image))), clean)

    def test_a_mask_around_the_smaller_object_gives_that_object(self):
        """Otsu counts only the voxels inside the mask; the largest object elsewhere no longer decides."""
        image, smaller, mask = _two_objects()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(foreground_mask(image, mask)), smaller)

    def test_a_segmentation_mask_is_its_own_foreground(self):
        """A lung mask on a chest CT: dark inside, bright wall just outside. Otsu inside it finds only the vessels."""
        z, y, x = np.mgrid[:24, :40, :48]
        array = np.full(x.shape, -1000, dtype=np.int16)
        array[((x - 23.5) / 21) ** 2 + ((y - 20) / 15) ** 2 <= 1] = 40
        lungs = (((abs(x - 23.5) - 10) / 6) ** 2 + ((y - 20) / 9) ** 2 <= 1) & (z >= 4)  # open: not a hole
        array[lungs] = -850
        array[lungs & (np.random.default_rng(0).random(x.shape) < 0.03)] = 0  # vessels
        image = sitk.GetImageFromArray(array)
        mask = _on_grid(lungs.astype(np.uint8), image)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(foreground_mask(image, mask)), lungs)


    def test_holes_are_filled_as_simpleitk_fills_them(self):
        """Enclosed cavities are filled; one open to the border through a face is not; one that reaches the outside
        only through an edge or a corner is enclosed (face connectivity), as SimpleITK's BinaryFillhole has it."""
        array = np.zeros((20, 24, 28), dtype=np.float32)
        array[2:18, 3:21, 4:24] = 100.0
        array[5:9, 6:10, 7:11] = 0.0  # enclosed
        array[10:14, 12:16, 4:24] = 0.0  # a tunnel through the object, open on two faces
        array[4:7, 5:8, 18:21] = 0.0  # enclosed, but for a chain of voxels that meet at corners only:
        array[3, 4, 17] = array[2, 3, 16] = 0.0  # the last of them lies on the surface
        rng = np.random.default_rng(7)
        array[rng.random(array.shape) < 0.02] = 0.0  # pinholes, some on the object's surface
        image = sitk.GetImageFromArray(array)
        largest = sitk.RelabelComponent(sitk.ConnectedComponent(image > 50), sortByObjectSize=True) == 1
        expected = sitk.GetArrayFromImage(sitk.BinaryFillhole(largest))
        foreground = sitk.GetArrayFromImage(foreground_mask(image))
        np.testing.assert_array_equal(foreground, expected)
        assert foreground[6, 7, 8] == foreground[5, 6, 19] == foreground[3, 4, 17] == 1
        assert foreground[11, 13, 10] == foreground[2, 3, 16] == 0


class TestBoundingBox:
    def test_every_voxel_above_zero_counts(self):
        """Labels other than 1 are inside too; the box is in voxels (x, y, z), whatever the spacing."""
        array = np.zeros((16, 20, 40), dtype=np.int16)
        array[8:12, 5:15, 10:30] = 1
        array[3, 17, 35] = 7
        mask = sitk.GetImageFromArray(array)
        mask.SetSpacing((1.0, 2.0, 3.0))
        start, size = bounding_box(mask)
        np.testing.assert_array_equal(start, [10, 5, 3])
        np.testing.assert_array_equal(size, [26, 13, 9])

    def test_an_empty_mask_has_none(self):
        assert bounding_box(sitk.Image([5, 4, 3], sitk.sitkUInt8)) is None


class TestDilate:
    @pytest.mark.parametrize("radius", [0, 1, 2, 3, 5])
    def test_the_voxels_of_simpleitks_ball(self, radius):
        """Sparse voxels, some on the border, on an anisotropic grid: the ball counts voxels, not mm."""
        array = (np.random.default_rng(radius).random((18, 15, 12)) > 0.993).astype(np.uint8)
        array[0, 0, 0] = array[-1, 7, 11] = 1
        mask = sitk.GetImageFromArray(array)
        mask.SetSpacing((0.5, 1.0, 3.0))
        mask.SetOrigin((4.0, -2.0, 1.0))
        dilated = dilate(mask, radius)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(dilated),
                                      sitk.GetArrayFromImage(sitk.BinaryDilate(mask, [radius] * 3)))
        assert dilated.GetPixelID() == sitk.sitkUInt8
        assert (dilated.GetSpacing(), dilated.GetOrigin()) == (mask.GetSpacing(), mask.GetOrigin())

    def test_an_empty_mask_stays_empty(self):
        mask = sitk.Image([6, 5, 4], sitk.sitkUInt8)
        assert not sitk.GetArrayFromImage(dilate(mask, 3)).any()

    def test_a_negative_radius_is_refused(self):
        with pytest.raises(InputError, match="radius is -1"):
            dilate(sitk.Image([4, 4, 4], sitk.sitkUInt8), -1)


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

    def test_a_uniform_foreground_maps_to_one(self):
        """A binary phantom's percentiles coincide; mapped from them, the object was 0 like the background."""
        image = _box_image()
        normalised = sitk.GetArrayFromImage(normalize_intensity(image))
        np.testing.assert_array_equal(normalised, sitk.GetArrayFromImage(image) / 100.0)

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

    @pytest.mark.parametrize(("arguments", "message"), [
        ({"spacing": 0.0}, r"^spacing is 0\.0; expected a finite number > 0$"),  # was taken for None: fill's spacing
        ({"spacing": float("nan")}, r"^spacing is nan; expected a finite number > 0$"),  # was an all-zero cube
        ({"fill": 0.0}, r"^fill is 0\.0; expected a finite number >= 0\.1 and <= 1$"),  # was ZeroDivisionError
        ({"size": 16.0}, r"^size is 16\.0 \(float\); expected an integer >= 2$"),
    ])
    def test_bad_grid_arguments_are_named(self, arguments, message):
        with pytest.raises(InputError, match=message):
            solver_grid(_box_image(), **{"size": 16, **arguments})

    def test_reversed_percentiles_are_refused(self):
        """They clipped nearly every voxel to 0 or 1."""
        with pytest.raises(InputError, match=r"^percentiles is \(99\.0, 1\.0\); expected \(low, high\) with 0 <= "):
            normalize_intensity(_box_image(), (99.0, 1.0))

    def test_to_tensor_rejects_2d_images(self):
        with pytest.raises(InputError, match="image is 2-D"):
            to_tensor(sitk.Image([8, 8], sitk.sitkFloat32))


def _ct_like() -> sitk.Image:
    """Air at -1000 HU with a water cylinder (0 HU) holding a bone rod (1000 HU), int16."""
    array = np.full((30, 40, 40), -1000, dtype=np.int16)
    z, y, x = np.mgrid[:30, :40, :40]
    array[(y - 20) ** 2 + (x - 18) ** 2 < 12 ** 2] = 0
    array[(y - 24) ** 2 + (x - 14) ** 2 < 3 ** 2] = 1000
    return sitk.GetImageFromArray(array)


class TestDetectModality:
    def test_ct_by_its_air(self):
        assert detect_modality(_ct_like()) == "ct"

    def test_mr_otherwise(self):
        assert detect_modality(_box_image()) == "mr"


class TestNormalizeModality:
    def test_ct_uses_the_hounsfield_window(self):
        image = _ct_like()
        low, high = Preprocessing().ct_window
        out = sitk.GetArrayFromImage(normalize_modality(image, "ct", image > -500))
        assert out.min() == pytest.approx(0.0) and out.max() == pytest.approx(min(1.0, (1000 - low) / (high - low)))
        assert out[15, 20, 18] == pytest.approx((0 - low) / (high - low))

    def test_ct_window_keeps_geometry(self):
        image = _ct_like()
        image.SetOrigin((1.0, 2.0, 3.0))
        image.SetSpacing((0.5, 0.7, 2.0))
        out = normalize_modality(image, "ct", image > -500)
        assert out.GetPixelID() == sitk.sitkFloat32
        assert (out.GetOrigin(), out.GetSpacing()) == (image.GetOrigin(), image.GetSpacing())

    def test_mr_uses_foreground_percentiles(self):
        array = sitk.GetArrayFromImage(_box_image())
        array[8:12, 5:15, 10:30] += np.arange(0.0, 200.0, 10.0, dtype=np.float32)  # a ramp of 100..290 along x
        array[9, 9, 12], array[10, 10, 28] = 60.0, 5000.0  # one dark voxel and one hot one (a marker)
        image = sitk.GetImageFromArray(array)
        image.CopyInformation(_box_image())
        mask = image > 50
        low, high = np.percentile(array[array > 50], Preprocessing().percentiles)
        assert (low, high) == (100.0, 290.0)  # the two outliers do not set the range
        out = sitk.GetArrayFromImage(normalize_modality(image, "mr", mask))
        assert out[10, 10, 10] == 0.0 and out[10, 10, 29] == 1.0  # the 1st and 99th percentiles
        assert out[9, 9, 12] == 0.0 and out[10, 10, 28] == 1.0  # clipped below the 1st, above the 99th percentile
        assert out[10, 10, 14] == pytest.approx((140.0 - low) / (high - low), rel=1e-6)  # inside the range
        np.testing.assert_array_equal(out, sitk.GetArrayFromImage(normalize_intensity(image, (1, 99), mask)))
        window = sitk.GetArrayFromImage(normalize_modality(image, "ct", mask))
        assert abs(window[10, 10, 14] - out[10, 10, 14]) > 0.1  # not the Hounsfield window

    def test_unknown_modality(self):
        with pytest.raises(InputError, match="modality 'pet' is not supported"):
            normalize_modality(_box_image(), "pet", _box_image() > 50)


class TestPrepare:
    def test_user_mask_zeroes_the_rest_and_sets_the_centre(self):
        image = _box_image()
        ramp = sitk.GetImageFromArray(np.broadcast_to(np.arange(1.0, 41.0, dtype=np.float32), (16, 20, 40)).copy())
        ramp.CopyInformation(image)
        image = image * ramp  # not constant inside the mask, so percentiles spread it over [0, 1]
        mask = sitk.Image(image.GetSize(), sitk.sitkUInt8)
        mask.CopyInformation(image)
        mask[10:20, 5:15, 8:12] = 1  # the box's first half along x
        prepared = prepare(image, mask=mask)
        array = sitk.GetArrayFromImage(prepared.image)
        assert array[8:12, 5:15, 20:30].max() == 0.0 and array[8:12, 5:15, 10:20].mean() > 0.2
        expected = image.TransformContinuousIndexToPhysicalPoint((14.5, 9.5, 9.5))
        np.testing.assert_allclose(prepared.centre, expected, atol=1e-9)

    def test_a_mask_around_the_smaller_object_centres_on_it(self):
        """The mask was intersected with the whole image's foreground, the larger object: "holds no foreground"."""
        image, smaller, mask = _two_objects()
        prepared = prepare(image, mask=mask, mask_name="right.nii.gz")
        np.testing.assert_array_equal(sitk.GetArrayFromImage(prepared.foreground), smaller)
        np.testing.assert_allclose(prepared.centre, (75.0, 30.0, 20.0))

    def test_a_mask_over_background_only_is_named(self):
        image, _, _ = _two_objects()
        mask = sitk.Image(image.GetSize(), sitk.sitkUInt8)
        mask[0:5, 0:5, 0:5] = 1
        with pytest.raises(InputError, match=r"^corner\.nii\.gz: holds no foreground of its image"):
            prepare(image, mask=mask, mask_name="corner.nii.gz")

    def test_large_images_are_shrunk_but_cover_the_same_space(self):
        image = _box_image()
        prepared = prepare(image, config=Preprocessing(max_voxels=2000))
        assert np.prod(prepared.image.GetSize()) < np.prod(image.GetSize())
        centre, _ = foreground_box(image)
        np.testing.assert_allclose(prepared.centre, centre, atol=2.0)


class TestShrinkFactors:
    def test_keeps_coarse_axes(self):
        image = sitk.Image([256, 256, 26], sitk.sitkInt16)
        image.SetSpacing((1.25, 1.25, 4.0))
        assert shrink_factors(image, 500_000) == [2, 2, 1]

    def test_small_images_untouched(self):
        assert shrink_factors(_box_image(), 2_000_000) == [1, 1, 1]

    def test_a_few_slices_stay_and_the_other_axes_take_their_share(self):
        image = sitk.Image([4000, 4000, 2], sitk.sitkUInt8)
        factors = shrink_factors(image, 2_000_000)
        assert factors[2] == 1
        assert 2_000_000 <= np.prod(np.array(image.GetSize()) // factors) <= 1.3 ** 3 * 2_000_000

    def test_coarse_slices_do_not_leave_too_many_voxels(self):
        image = sitk.Image([4000, 4000, 8], sitk.sitkUInt8)
        image.SetSpacing((0.5, 0.5, 5.0))
        factors = shrink_factors(image, 2_000_000)
        assert factors[2] == 1 and np.prod(np.array(image.GetSize()) // factors) <= 1.3 ** 3 * 2_000_000

    def test_a_thin_wide_image_is_prepared(self):
        array = np.zeros((2, 200, 200), dtype=np.float32)
        array[:, 50:150, 60:140] = 100.0
        prepared = prepare(sitk.GetImageFromArray(array), modality="mr", config=Preprocessing(max_voxels=1000))
        assert prepared.image.GetSize()[2] == 2 and np.prod(prepared.image.GetSize()) <= 1.3 ** 3 * 1000
        np.testing.assert_allclose(prepared.centre, (99.5, 99.5, 0.5), atol=3.0)


class TestPairGrids:
    def test_shared_spacing_covers_the_larger_foreground(self):
        small, large = prepare(_box_image()), prepare(_ct_like())
        fixed_grid, moving_grid = pair_grids(small, large, 32, Preprocessing(fill=0.5))
        assert fixed_grid.spacing == moving_grid.spacing
        assert fixed_grid.spacing == pytest.approx(max(small.diagonal, large.diagonal) / 16)
        np.testing.assert_allclose(moving_grid.centre, large.centre)


class TestVoxelize:
    def test_closed_surface_is_filled(self):
        pv = pytest.importorskip("pyvista")
        sphere = pv.Sphere(radius=10.0, center=(5.0, -3.0, 20.0), theta_resolution=60, phi_resolution=60)
        image = voxelize(sphere, spacing=1.0)
        array = sitk.GetArrayFromImage(image)
        assert array.sum() == pytest.approx(4 / 3 * np.pi * 1000, rel=0.05)
        centre, _ = foreground_box(image)
        np.testing.assert_allclose(centre, (5.0, -3.0, 20.0), atol=1.0)

    def test_point_cloud_marks_its_points(self):
        pv = pytest.importorskip("pyvista")
        points = np.array([[0.0, 0.0, 0.0], [20.0, 5.0, -4.0]])
        image = voxelize(pv.PolyData(points), spacing=2.0)
        for point in points:
            index = image.TransformPhysicalPointToIndex(point.tolist())
            assert image[index] == 1.0
        assert sitk.GetArrayFromImage(image).sum() == 2 * 27  # each point dilated to a 3 x 3 x 3 block
