"""Tests for dpcn_med.io.images: volumes and masks read, checked, summarised and written."""

from __future__ import annotations

import os
from pathlib import Path

import nibabel
import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError
from tests.io.conftest import GEOMETRY_TOLERANCE, SIZE, SPACING, assert_same_geometry, make_volume, run_child


class TestReadImage:
    @pytest.mark.parametrize("suffix", list(GEOMETRY_TOLERANCE))
    @pytest.mark.parametrize("compress", [False, True], ids=["raw", "compressed"])
    def test_round_trip(self, volume, tmp_path, suffix, compress):
        path = tmp_path / f"volume{suffix}"
        sitk.WriteImage(volume, str(path), useCompression=compress)
        image = io.read_image(path)
        assert_same_geometry(image, volume, GEOMETRY_TOLERANCE[suffix])
        np.testing.assert_array_equal(sitk.GetArrayFromImage(image), sitk.GetArrayFromImage(volume))

    def test_integer_volume_keeps_pixel_type(self, tmp_path):
        path = tmp_path / "ct.nrrd"
        sitk.WriteImage(make_volume(pixel=np.int16), str(path))
        assert io.read_image(str(path)).GetPixelID() == sitk.sitkInt16

    def test_missing_path(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"nope\.nii\.gz: not found") as caught:
            io.read_image(tmp_path / "nope.nii.gz")
        assert isinstance(caught.value, FileNotFoundError) and isinstance(caught.value, InputError)

    @pytest.mark.parametrize("value", [0, 7])
    def test_constant_volume(self, tmp_path, value):
        path = tmp_path / "blank.nrrd"
        sitk.WriteImage(sitk.GetImageFromArray(np.full(SIZE[::-1], value, np.int16)), str(path))
        with pytest.raises(InputError, match=rf"all voxels equal {value}; the volume is blank"):
            io.read_image(path)


class TestReadMask:
    @staticmethod
    def write_mask(tmp_path: Path, array: np.ndarray, like: sitk.Image, name: str = "mask.nii.gz") -> Path:
        mask = sitk.GetImageFromArray(array)
        mask.CopyInformation(like)
        sitk.WriteImage(mask, str(tmp_path / name))
        return tmp_path / name

    def test_binary_mask_on_the_image_grid(self, volume, tmp_path):
        array = np.zeros(SIZE[::-1], np.float32)
        array[4:10, 5:15, 3:9] = 255.0
        mask = io.read_mask(self.write_mask(tmp_path, array, volume), volume)
        assert mask.GetPixelID() == sitk.sitkUInt8
        np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), (array > 0).astype(np.uint8))
        assert_same_geometry(mask, volume)  # NIfTI's float32 geometry snapped onto the image's

    def test_grid_mismatch_shows_both_grids(self, volume, tmp_path):
        other = sitk.Image(20, 24, 30, sitk.sitkUInt8)
        other.SetSpacing((1.0, 1.0, 2.0))
        other[3, 3, 3] = 1
        path = tmp_path / "m.nrrd"
        sitk.WriteImage(other, str(path))
        with pytest.raises(InputError, match=r"m\.nrrd: fixed mask is not on its image's voxel grid \(size \(20, 24, "
                                             r"30\) vs \(20, 24, 28\), spacing \(1, 1, 2\) vs \(0\.75, 1\.25, "
                                             r"2\.5\), origin .*sitkNearestNeighbor"):
            io.read_mask(path, volume, role="fixed mask")

    def test_a_mismatch_shows_rounded_numbers(self, volume, tmp_path):
        """Sixteen-digit floats made the message about 700 characters long."""
        other = sitk.Image(20, 24, 28, sitk.sitkUInt8)
        other.SetSpacing((0.1 + 0.2, 1.0 / 3.0, 2.0))
        other.SetOrigin((1.0 / 7.0, 2.0, 3.0))
        other[3, 3, 3] = 1
        sitk.WriteImage(other, str(tmp_path / "m.nrrd"))
        with pytest.raises(InputError, match=r"spacing \(0\.3, 0\.333333, 2\) vs \(0\.75, 1\.25, 2\.5\), origin "
                                             r"\(0\.142857, 2, 3\) vs") as caught:
            io.read_mask(tmp_path / "m.nrrd", volume, role="fixed mask")
        assert len(str(caught.value)) < len(str(tmp_path)) + 500

    def test_direction_mismatch(self, volume, tmp_path):
        array = np.zeros(SIZE[::-1], np.uint8)
        array[5, 5, 5] = 1
        path = self.write_mask(tmp_path, array, volume, "m.mha")
        volume.SetDirection((1, 0, 0, 0, 1, 0, 0, 0, 1))
        with pytest.raises(InputError, match=r"voxel grid \(.*direction \("):
            io.read_mask(path, volume)

    def test_empty(self, volume, tmp_path):
        path = self.write_mask(tmp_path, np.zeros(SIZE[::-1], np.uint8), volume)
        with pytest.raises(InputError, match=r"mask\.nii\.gz: moving mask is empty \(every voxel is 0\)"):
            io.read_mask(path, volume, role="moving mask")

    def test_no_background(self, volume, tmp_path):
        path = self.write_mask(tmp_path, np.ones(SIZE[::-1], np.uint8), volume)
        with pytest.raises(InputError, match=r"mask has no background \(every voxel is 1\)"):
            io.read_mask(path, volume)

    def test_label_map_is_not_binary(self, volume, tmp_path):
        array = np.zeros(SIZE[::-1], np.uint8)
        array[1, 1, :3] = (1, 2, 5)
        path = self.write_mask(tmp_path, array, volume)
        with pytest.raises(InputError, match=r"mask is not binary: found 4 distinct values \(0, 1, 2, 5\)"):
            io.read_mask(path, volume)

    def test_missing(self, volume, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"m\.nii\.gz: not found"):
            io.read_mask(tmp_path / "m.nii.gz", volume)

    def test_origin_tolerance_is_under_a_tenth_of_a_voxel_at_any_coordinate(self, volume):
        array = np.zeros(SIZE[::-1], np.uint8)
        array[5, 5, 5] = 1
        for origin in ((0.0, 0.0, 0.0), (1e6, -1e6, 5e5)):
            volume.SetOrigin(origin)
            mask = sitk.GetImageFromArray(array)
            mask.CopyInformation(volume)
            mask.SetOrigin(tuple(np.float32(origin).astype(float)))  # NIfTI's float32 storage passes
            io.check_mask(mask, volume)
            mask.SetOrigin(tuple(np.add(origin, (0.0, 0.0, 0.1 * SPACING[0]))))  # a tenth of the finest voxel does not
            with pytest.raises(InputError, match="not on its image's voxel grid"):
                io.check_mask(mask, volume)


class TestCheckVolume:
    """Images made in memory get the checks a file's voxels get."""

    def test_complex_voxels(self, volume):
        with pytest.raises(InputError, match="fixed image: has complex voxels"):
            io.check_volume(sitk.RealAndImaginaryToComplex(volume, volume), "fixed image")

    def test_infinite_voxels(self, volume):
        volume[1, 2, 3] = float("inf")
        with pytest.raises(InputError, match=r"image: holds 0 NaN and 1 infinite voxels"):
            io.check_volume(volume)

    def test_a_vector_image_of_one_component_is_refused(self, volume):
        with pytest.raises(InputError, match=r"^v: is a vector image of one component \(vector of 32-bit float\); "
                           "expected a scalar volume"):
            io.check_volume(sitk.Compose(sitk.Cast(volume, sitk.sitkFloat32)), "v")

    def test_two_dimensional_mask(self, volume):
        with pytest.raises(InputError, match="moving mask: is 2-D"):
            io.check_mask(sitk.Image(20, 24, sitk.sitkUInt8), volume, "moving mask")

    # SimpleITK aborts the whole process (SIGABRT, "not supported for LabelMaps") when a label map's voxels are read
    # as an array, as both checks did before: each case runs in a child so an abort fails the test, not pytest.
    def test_label_map_volume_is_refused_before_reading_voxels(self):
        result = run_child("""
            labels = sitk.Image([8, 9, 10], sitk.sitkUInt8)
            labels[2:5, 2:6, 3:7] = 1
            for pixel in (sitk.sitkLabelUInt8, sitk.sitkLabelUInt16, sitk.sitkLabelUInt32, sitk.sitkLabelUInt64):
                try:
                    io.check_volume(sitk.Cast(labels, pixel), "atlas")
                except InputError as error:
                    print(error)
            """)
        assert result.returncode == 0, result.stderr[-500:]
        assert result.stdout.splitlines() == [
            f"atlas: is a label map (label of {bits}-bit unsigned integer); expected an intensity volume (convert a "
            "segmentation with sitk.LabelMapToLabel)" for bits in (8, 16, 32, 64)]

    def test_label_map_mask_is_converted(self):
        result = run_child("""
            image = sitk.Image([8, 9, 10], sitk.sitkFloat32)
            labels = sitk.Image([8, 9, 10], sitk.sitkUInt8)
            labels[2:5, 2:6, 3:7] = 3
            labels.CopyInformation(image)
            mask = io.check_mask(sitk.LabelImageToLabelMap(labels), image)
            array = sitk.GetArrayFromImage(mask)
            print(mask.GetPixelIDTypeAsString(), int(array.sum()), array.max())
            """)
        assert result.returncode == 0, result.stderr[-500:]
        assert result.stdout == "8-bit unsigned integer 48 1\n"  # 3 x 4 x 4 voxels of label 3 become ones


class TestImageSummary:
    def test_known_values(self):
        image = sitk.GetImageFromArray(np.arange(101, dtype=np.float32).reshape(1, 1, 101).repeat(4, 0).repeat(3, 1))
        image.SetSpacing((0.5, 2.0, 3.0))
        image.SetOrigin((1.0, -2.0, 3.5))
        image.SetDirection((-1, 0, 0, 0, -1, 0, 0, 0, 1))
        summary = io.image_summary(image)
        assert summary["size"] == (101, 3, 4) and summary["spacing"] == (0.5, 2.0, 3.0)
        assert summary["origin"] == (1.0, -2.0, 3.5) and summary["voxels"] == 101 * 3 * 4
        assert summary["direction"] == [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
        assert summary["orientation"] == "RAS" and summary["pixel_type"] == "32-bit float"
        assert summary["extent_mm"] == (50.5, 6.0, 12.0)
        assert (summary["intensity_min"], summary["intensity_max"]) == (0.0, 100.0)
        assert summary["intensity_p1"] == pytest.approx(1.0) and summary["intensity_p99"] == pytest.approx(99.0)
        assert all(type(summary[k]) is float for k in ("intensity_min", "intensity_p1", "intensity_p99"))

    def test_identity_direction_is_lps(self, volume):
        volume.SetDirection((1, 0, 0, 0, 1, 0, 0, 0, 1))
        assert io.image_summary(volume)["orientation"] == "LPS"


class TestWriteImage:
    @pytest.mark.parametrize("suffix", io.IMAGE_WRITE_SUFFIXES)
    @pytest.mark.parametrize("compress", [False, True], ids=["raw", "compressed"])
    def test_round_trip(self, volume, tmp_path, suffix, compress):
        path = tmp_path / f"out{suffix}"
        io.write_image(volume, path, compress=compress)
        image = io.read_image(path)
        assert_same_geometry(image, volume, GEOMETRY_TOLERANCE[suffix])
        np.testing.assert_array_equal(sitk.GetArrayFromImage(image), sitk.GetArrayFromImage(volume))
        assert os.listdir(tmp_path) == [path.name]

    def test_a_gzipped_nifti_is_plain_gzip_without_a_name_and_the_same_every_time(self, volume, tmp_path):
        """Compressed by Python's zlib, which lets a thread write it while another works (io.images)."""
        import gzip

        for name in ("a.nii.gz", "b.nii.gz"):
            io.write_image(volume, tmp_path / name)
        first = (tmp_path / "a.nii.gz").read_bytes()
        assert first == (tmp_path / "b.nii.gz").read_bytes()
        assert first[:2] == b"\x1f\x8b" and not first[3] & 0x08  # gzip, and no FNAME field (the temporary name)
        plain = tmp_path / "plain.nii"
        io.write_image(volume, plain)
        assert gzip.decompress(first) == plain.read_bytes()

    def test_compression_shrinks_the_file(self, tmp_path):
        smooth = sitk.GetImageFromArray(np.tile(np.arange(20, dtype=np.float32), (28, 24, 1)))
        io.write_image(smooth, tmp_path / "raw.mha", compress=False)
        io.write_image(smooth, tmp_path / "small.mha")
        assert (tmp_path / "small.mha").stat().st_size < (tmp_path / "raw.mha").stat().st_size / 2

    def test_nan_voxels_are_written_as_they_are(self, tmp_path):
        # reading refuses them (SimpleITK would read 0); writing is the caller's business, and no short file
        array = np.ones((4, 5, 6), np.float32)
        array[1, 2, 3] = np.nan
        io.write_image(sitk.GetImageFromArray(array), tmp_path / "nan.nii.gz")
        assert np.isnan(nibabel.load(tmp_path / "nan.nii.gz").get_fdata()).sum() == 1  # SimpleITK reads NaN as 0

    def test_two_file_formats_refused(self, volume, tmp_path):
        with pytest.raises(InputError, match=r"out\.mhd: cannot write an image with this suffix; use \.nii\.gz"):
            io.write_image(volume, tmp_path / "out.mhd")
        assert os.listdir(tmp_path) == []
