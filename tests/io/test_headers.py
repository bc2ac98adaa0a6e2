"""Tests for dpcn_med.io.headers: what an image header must say, checked before the voxels are read."""

from __future__ import annotations

import os

import nibabel
import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError
from tests.io.conftest import SIZE, edit_header


class TestReadImageHeader:
    """read_image refuses a file by what its header says, before it reads the voxels."""

    def test_garbage_bytes(self, tmp_path):
        path = tmp_path / "garbage.nii.gz"
        path.write_bytes(os.urandom(3000))
        with pytest.raises(InputError, match=r"garbage\.nii\.gz: its content is in none of the formats read here "
                                             r"\(NIfTI .*\), whatever its name says"):
            io.read_image(path)
        path.write_bytes(b"")
        with pytest.raises(InputError, match=r"garbage\.nii\.gz: is empty \(0 bytes\); copy or export it again$"):
            io.read_image(path)

    def test_unsupported_format(self, tmp_path):
        path = tmp_path / "notes.xyz"
        path.write_text("not an image\n")
        with pytest.raises(InputError, match=r"notes\.xyz: not a readable image .*expected NIfTI"):
            io.read_image(path)

    def test_sheared_axes(self, volume, tmp_path):
        path = tmp_path / "sheared.nrrd"
        volume.SetDirection((1, 0, 0, 0, 1, 0.3, 0, 0, 0.954))
        sitk.WriteImage(volume, str(path))
        with pytest.raises(InputError, match=r"sheared\.nrrd: its direction cosines .* are not orthonormal"):
            io.read_image(path)

    def test_two_dimensional(self, tmp_path):
        path = tmp_path / "slice.nii.gz"
        sitk.WriteImage(sitk.GetImageFromArray(np.random.default_rng(0).random((24, 20))), str(path))
        with pytest.raises(InputError, match=r"is 2-D \(size \(20, 24\)\); expected a 3-D volume"):
            io.read_image(path)

    def test_one_voxel_thick(self, tmp_path):
        path = tmp_path / "thin.nrrd"
        sitk.WriteImage(sitk.GetImageFromArray(np.random.default_rng(0).random((1, 24, 20))), str(path))
        with pytest.raises(InputError, match=r"is effectively 2-D \(size \(20, 24, 1\), one voxel thick along axis 2"):
            io.read_image(path)

    def test_four_dimensional(self, tmp_path):
        path = tmp_path / "fmri.nii.gz"
        nibabel.save(nibabel.Nifti1Image(np.random.default_rng(0).random((20, 24, 28, 3)).astype(np.float32),
                                         np.eye(4)), path)
        with pytest.raises(InputError, match=r"is 4-D \(size \(20, 24, 28, 3\)\); extract one volume first"):
            io.read_image(path)

    def test_vector_pixels(self, volume, tmp_path):
        path = tmp_path / "field.mha"
        sitk.WriteImage(sitk.Compose(volume, volume, volume), str(path))
        with pytest.raises(InputError, match="has 3 components per voxel"):
            io.read_image(path)

    @pytest.mark.parametrize(("spacing", "message"), [
        (b"0.001 1 1", r"spacing \(0\.001, 1\.0, 1\.0\) mm is below 0\.01 mm"),
        (b"250 1 1", r"spacing \(250\.0, 1\.0, 1\.0\) mm is above 100\.0 mm"),
        (b"-1 1 1", r"spacing \(-1\.0, 1\.0, 1\.0\) mm must be positive"),
        (b"nan 1 1", r"spacing \(0\.0, 0\.0, 0\.0\) mm must be positive"),  # ITK's parser turns nan into zeros
    ])
    def test_absurd_spacing(self, volume, tmp_path, spacing, message):
        path = tmp_path / "v.mha"
        volume.SetSpacing((1.0, 1.0, 1.0))
        sitk.WriteImage(volume, str(path))
        edit_header(path, b"ElementSpacing = 1 1 1", b"ElementSpacing = " + spacing)
        with pytest.raises(InputError, match=message):
            io.read_image(path)

    @pytest.mark.parametrize(("change", "message"), [
        (lambda image: image.SetOrigin((float("nan"), 0.0, 0.0)), r"origin \(nan, 0\.0, 0\.0\) mm is not finite"),
        (lambda image: image.SetOrigin((0.0, float("inf"), 0.0)), r"origin \(0\.0, inf, 0\.0\) mm is not finite"),
        (lambda image: image.SetOrigin((1e12, 0.0, 0.0)), r"origin \(1000000000000\.0, 0\.0, 0\.0\) mm lies over "
         "100 m from the scanner's origin"),
        (lambda image: image.SetDirection((float("nan"), 0, 0, 0, 1, 0, 0, 0, 1)), r"its direction cosines \(nan, "
         r".*\) are not finite"),
    ], ids=["nan_origin", "infinite_origin", "far_origin", "nan_direction"])
    def test_absurd_geometry_in_memory(self, volume, change, message):
        """A NaN origin or direction passed every check, then hung the foreground search."""
        image = sitk.Image(volume)
        change(image)
        with pytest.raises(InputError, match="^in memory: " + message):
            io.check_volume(image, "in memory")


class TestCheckMemory:
    def test_header_claiming_more_than_memory(self, tmp_path):
        # Checked from the header alone: the voxel file it names does not exist.
        path = tmp_path / "huge.mhd"
        path.write_text("ObjectType = Image\nNDims = 3\nDimSize = 100000 100000 100000\nElementSpacing = 0.5 0.5 0.5\n"
                        "ElementType = MET_FLOAT\nElementDataFile = huge.raw\n")
        with pytest.raises(InputError, match=r"1,000,000,000,000,000 voxels\) needs about 14\.2 PiB .*sitk\.Resample"):
            io.read_image(path)

    def test_memory_limit_is_injectable(self, volume, tmp_path):
        path = tmp_path / "v.nrrd"
        sitk.WriteImage(volume, str(path))
        with pytest.raises(InputError, match=r"needs about 210\.0 KiB .*more than the 100\.0 KiB available"):
            io.read_image(path, max_bytes=100 * 1024)
        assert io.read_image(path, max_bytes=1 << 20).GetSize() == SIZE
