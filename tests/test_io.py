"""Tests for dpcn_med.io: real files written into tmp_path, every bad input checked by its message."""

from __future__ import annotations

import gzip
import json
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import nibabel
import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.io import images

SIZE = (20, 24, 28)  # (x, y, z): every axis different, so a transposition cannot pass
SPACING = (0.75, 1.25, 2.5)
ORIGIN = (-12.3456789, 30.25, 7.1)
# Origin, spacing and direction survive exactly in NRRD and MetaImage; NIfTI keeps them as float32.
GEOMETRY_TOLERANCE = {".nii": 1e-6, ".nii.gz": 1e-6, ".nrrd": 1e-12, ".nhdr": 1e-12, ".mha": 0.0, ".mhd": 0.0}


def oblique_direction() -> tuple[float, ...]:
    return sitk.VersorTransform((0.3, -0.5, 0.8), 0.7).GetMatrix()


def make_volume(seed: int = 0, pixel: type = np.float32) -> sitk.Image:
    """A random asymmetric volume with non-trivial origin, spacing and direction."""
    rng = np.random.default_rng(seed)
    image = sitk.GetImageFromArray((rng.random(SIZE[::-1]) * 1000).astype(pixel))
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    image.SetDirection(oblique_direction())
    return image


def assert_same_geometry(a: sitk.Image, b: sitk.Image, tolerance: float = 0.0) -> None:
    assert a.GetSize() == b.GetSize()
    for get in ("GetOrigin", "GetSpacing", "GetDirection"):
        np.testing.assert_allclose(getattr(a, get)(), getattr(b, get)(), rtol=0, atol=tolerance, err_msg=get)


def cut(path: Path, fraction: float = 0.5) -> None:
    """Keep only the first ``fraction`` of a file's bytes, as an interrupted copy does."""
    content = path.read_bytes()
    path.write_bytes(content[:int(len(content) * fraction)])


def write_dicom_series(folder: Path, uid: str, description: str, slices: int, seed: int = 1,
                       tilt_mm: float = 0.0, direction: tuple[float, ...] = (1, 0, 0, 0, 1, 0, 0, 0, 1),
                       step_mm: float = 2.0, decimals: int = 17, moved: dict[int, tuple[float, ...]] | None = None
                       ) -> sitk.Image:
    """Write an int16 series of slices into ``folder``, each ``tilt_mm`` further along the columns than the one
    before (a gantry tilt), Image Positions rounded to ``decimals``, slice ``k`` shifted by ``moved[k]`` mm; returns
    the volume it holds."""
    rng = np.random.default_rng(seed)
    volume = sitk.GetImageFromArray(rng.integers(-500, 1500, (slices, 24, 20)).astype(np.int16))
    volume.SetSpacing((0.75, 0.5, step_mm))
    volume.SetOrigin((-10.0, 5.5, 30.0))
    volume.SetDirection(direction)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(slices):
        image = volume[:, :, k]
        position = np.add(volume.TransformIndexToPhysicalPoint((0, 0, k)), np.multiply(direction[1::3], k * tilt_mm))
        position = np.round(position + (moved or {}).get(k, 0.0), decimals)
        tags = {"0008|0060": "CT", "0020|000d": "1.2.826.0.1.3680043.2.1125.9", "0020|000e": uid,
                "0008|103e": description, "0008|0018": f"{uid}.{k + 1}", "0020|0013": str(k + 1),
                "0020|0032": "\\".join(map(str, position)),
                "0020|0037": "\\".join(map(str, (*direction[0::3], *direction[1::3]))), "0018|0050": str(step_mm)}
        for tag, value in tags.items():
            image.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"{uid}-{k:03d}.dcm"))
        writer.Execute(image)
    return volume


def edit_header(path: Path, old: bytes, new: bytes) -> None:
    content = path.read_bytes()
    assert old in content, content[:400]
    path.write_bytes(content.replace(old, new, 1))


@pytest.fixture
def volume() -> sitk.Image:
    return make_volume()


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

    def test_garbage_bytes(self, tmp_path):
        path = tmp_path / "garbage.nii.gz"
        path.write_bytes(os.urandom(3000))
        with pytest.raises(InputError, match=r"garbage\.nii\.gz: its content is in none of the formats read here "
                                             r"\(NIfTI .*\), whatever its name says"):
            io.read_image(path)
        path.write_bytes(b"")
        with pytest.raises(InputError, match=r"garbage\.nii\.gz: is empty \(0 bytes\); copy or export it again$"):
            io.read_image(path)

    @pytest.mark.parametrize("name,keep", [("v.nii.gz", 100), ("v.nii", 200)])
    def test_a_nifti_cut_inside_its_header_is_truncated(self, tmp_path, name, keep):
        """It was said to be in none of the formats read here, whatever its name says."""
        whole = tmp_path / f"whole{name[1:]}"
        noise = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)  # incompressible: 100 bytes cut it
        sitk.WriteImage(sitk.GetImageFromArray(noise), str(whole))
        (tmp_path / name).write_bytes(whole.read_bytes()[:keep])
        with pytest.raises(InputError, match=rf"{re.escape(name)}: is truncated \(its NIfTI header ends after \d+ of "
                                             r"348 bytes\); copy or export it again$"):
            io.read_image(tmp_path / name)

    def test_unsupported_format(self, tmp_path):
        path = tmp_path / "notes.xyz"
        path.write_text("not an image\n")
        with pytest.raises(InputError, match=r"notes\.xyz: not a readable image .*expected NIfTI"):
            io.read_image(path)

    @pytest.mark.parametrize(("name", "compress", "message"), [
        ("v.nii.gz", True, r"is truncated \(its compressed stream ends after"),
        ("v.nii", False, r"is truncated \(it holds 27,056 bytes, the header needs 54,112\)"),
        ("v.mha", False, r"is truncated \(it holds [\d,]+ voxel bytes, the header needs 53,760\)"),
        ("v.mha", True, r"is truncated \(its compressed voxel stream ends"),
        ("v.nrrd", False, r"cannot be read \(fread got only .*truncated or corrupt"),
        ("v.nrrd", True, r"cannot be read \(expected 53760 bytes but received .*truncated or corrupt"),
    ])
    def test_truncated(self, volume, tmp_path, name, compress, message):
        path = tmp_path / name
        sitk.WriteImage(volume, str(path), useCompression=compress)
        cut(path)
        with pytest.raises(InputError, match=message):
            io.read_image(path)

    def test_analyze_pair_with_a_cut_voxel_file(self, volume, tmp_path):
        """SimpleITK read it with half the voxels 0, and no error."""
        sitk.WriteImage(volume, str(tmp_path / "v.hdr"))
        cut(tmp_path / "v.img")
        assert sitk.GetArrayViewFromImage(sitk.ReadImage(str(tmp_path / "v.hdr"))).shape == SIZE[::-1]
        for name in ("v.hdr", "v.img"):
            with pytest.raises(InputError, match=r"v\.img: is truncated \(it holds [\d,]+ bytes, the header v\.hdr "
                                                 r"needs [\d,]+\)"):
                io.read_image(tmp_path / name)

    def test_a_plain_nifti_named_nii_gz(self, volume, tmp_path):
        """Called corrupt before, with the advice to copy it again: the copy is the same file."""
        sitk.WriteImage(volume, str(tmp_path / "v.nii"))
        (tmp_path / "v.nii").rename(tmp_path / "v.nii.gz")
        with pytest.raises(InputError, match=r"v\.nii\.gz: is not gzip-compressed although its name ends in \.gz "
                                             r".*; rename it to v\.nii$"):
            io.read_image(tmp_path / "v.nii.gz")

    def test_corrupt_compressed_mha(self, volume, tmp_path):
        """zlib's error escaped as an internal error."""
        path = tmp_path / "v.mha"
        sitk.WriteImage(volume, str(path), useCompression=True)
        data = bytearray(path.read_bytes())
        data[-20] ^= 0xFF
        path.write_bytes(bytes(data))
        with pytest.raises(InputError, match=r"v\.mha: the compressed voxel data is corrupt \(Error -3"):
            io.read_image(path)

    def test_nii_gz_truncated_inside_its_header(self, volume, tmp_path):
        # nibabel cannot read the header; SimpleITK alone returns this file zero-filled.
        path = tmp_path / "v.nii.gz"
        sitk.WriteImage(volume, str(path))
        path.write_bytes(path.read_bytes()[:300])
        assert sitk.GetArrayViewFromImage(sitk.ReadImage(str(path))).shape == SIZE[::-1]
        with pytest.raises(InputError, match=r"v\.nii\.gz: is truncated \(its compressed stream ends after \d+ bytes, "
                                             r"before the end of its header\)"):
            io.read_image(path)

    def test_truncation_message_counts_the_bytes_found(self, volume, tmp_path):
        path = tmp_path / "v.nii.gz"
        sitk.WriteImage(volume, str(path))
        cut(path)
        with pytest.raises(InputError) as caught:
            io.read_image(path)
        found = int(re.search(r"ends after ([\d,]+) bytes", str(caught.value)).group(1).replace(",", ""))
        assert 352 < found < 352 + 4 * math.prod(SIZE)

    def test_nifti_voxel_size_of_zero(self, volume, tmp_path):
        path = tmp_path / "v.nii"
        sitk.WriteImage(volume, str(path))
        content = bytearray(path.read_bytes())
        content[80:84] = np.float32(0).tobytes()  # pixdim[1]: NIfTI-1 keeps pixdim[8] at byte 76
        path.write_bytes(bytes(content))
        assert sitk.ReadImage(str(path)).GetSpacing()[0] == 1.0  # what SimpleITK alone makes of it
        with pytest.raises(InputError, match=r"v\.nii: its header gives voxel size \(0\.0, 1\.25, 2\.5\) mm"):
            io.read_image(path)

    def test_nifti_qform_and_sform_disagreeing(self, tmp_path):
        nibabel = pytest.importorskip("nibabel")
        data = np.zeros((20, 22, 24), np.float32)
        data[5:15, 6:16, 4:20] = 100.0
        qform = np.diag([2.0, 2.0, 2.0, 1.0])
        turned = qform.copy()
        turned[:3, :3] = np.array([[0.94, -0.342, 0], [0.342, 0.94, 0], [0, 0, 1]]) @ qform[:3, :3]  # 20 degrees
        for name, sform in (("same.nii.gz", qform), ("apart.nii.gz", turned)):
            image = nibabel.Nifti1Image(data, None)
            image.set_qform(qform, code=1)
            image.set_sform(sform, code=2)
            nibabel.save(image, tmp_path / name)
        assert io.read_image(tmp_path / "same.nii.gz").GetSize() == (20, 22, 24)
        with pytest.raises(InputError, match=r"apart\.nii\.gz: its header's qform \(code 1, scanner\) and sform "
                                             r"\(code 2, aligned\) place the volume up to 19\.7 mm apart"):
            io.read_image(tmp_path / "apart.nii.gz")

    def test_nifti_oblique_from_simpleitk(self, tmp_path):
        # Saved from LPS, a small tilt is a qform rotation near 180 degrees, whose float32 quaternion SimpleITK
        # itself rounds 0.8 mrad away from the sform: 0.3 mm at the far corner of this 358 x 358 x 300 mm grid.
        axis = np.array([-0.9576, 0.288, -0.0097])
        tilt = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(4.887)).as_matrix()
        image = sitk.GetImageFromArray(np.arange(20 * 32 * 32, dtype=np.int16).reshape(20, 32, 32))
        image.SetSpacing((11.2, 11.2, 15.0))
        image.SetOrigin((-180.0, -200.0, -150.0))
        image.SetDirection(tilt.ravel().tolist())
        sitk.WriteImage(image, str(tmp_path / "oblique.nii.gz"))
        read = io.read_image(tmp_path / "oblique.nii.gz")
        np.testing.assert_allclose(read.GetDirection(), tilt.ravel(), atol=2e-3)

    def test_sheared_axes(self, volume, tmp_path):
        path = tmp_path / "sheared.nrrd"
        volume.SetDirection((1, 0, 0, 0, 1, 0.3, 0, 0, 0.954))
        sitk.WriteImage(volume, str(path))
        with pytest.raises(InputError, match=r"sheared\.nrrd: its direction cosines .* are not orthonormal"):
            io.read_image(path)

    def test_nii_gz_truncated_inside_the_last_voxels(self, volume, tmp_path):
        # SimpleITK alone would return this file with its last voxels zero-filled.
        path = tmp_path / "v.nii.gz"
        sitk.WriteImage(volume, str(path))
        cut(path, 0.99)
        assert sitk.GetArrayFromImage(sitk.ReadImage(str(path))).shape == SIZE[::-1]
        with pytest.raises(InputError, match="is truncated"):
            io.read_image(path)

    @pytest.mark.parametrize("compress", [False, True], ids=["raw", "zraw"])
    def test_mhd_with_truncated_voxel_file(self, volume, tmp_path, compress):
        path = tmp_path / "v.mhd"
        sitk.WriteImage(volume, str(path), useCompression=compress)
        cut(tmp_path / ("v.zraw" if compress else "v.raw"))
        with pytest.raises(InputError, match=r"v\.mhd: is truncated"):
            io.read_image(path)

    def test_mhd_without_voxel_file(self, volume, tmp_path):
        path = tmp_path / "v.mhd"
        sitk.WriteImage(volume, str(path), useCompression=False)
        (tmp_path / "v.raw").unlink()
        with pytest.raises(InputError, match=r"its voxel file .*v\.raw is missing"):
            io.read_image(path)

    def test_nii_beside_nii_gz(self, volume, tmp_path):
        # Measured: ITK reads v.nii when asked for v.nii.gz if both exist.
        sitk.WriteImage(volume, str(tmp_path / "v.nii.gz"))
        sitk.WriteImage(volume * 0, str(tmp_path / "v.nii"))
        with pytest.raises(InputError, match=r"v\.nii lies beside it"):
            io.read_image(tmp_path / "v.nii.gz")

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

    def test_a_vector_image_of_one_component_is_refused(self, volume):
        with pytest.raises(InputError, match=r"^v: is a vector image of one component \(vector of 32-bit float\); "
                           "expected a scalar volume"):
            io.check_volume(sitk.Compose(sitk.Cast(volume, sitk.sitkFloat32)), "v")

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

    @pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".nrrd", ".mha"])
    @pytest.mark.parametrize("pixel", [np.float32, np.float64])
    def test_nan_and_infinite_voxels(self, tmp_path, suffix, pixel):
        # NIfTI needs its own scan: SimpleITK reads NaN and infinite NIfTI voxels as 0.
        array = sitk.GetArrayFromImage(make_volume(pixel=pixel))
        array[0, 0, :2] = np.nan
        array[-1, -1, -1] = -np.inf
        path = tmp_path / f"v{suffix}"
        sitk.WriteImage(sitk.GetImageFromArray(array), str(path))
        with pytest.raises(InputError, match=r"holds 2 NaN and 1 infinite voxels out of 13440"):
            io.read_image(path)

    @pytest.mark.parametrize("suffix", [".nii.gz", ".nii"])
    def test_nan_counted_across_chunk_boundaries(self, tmp_path, monkeypatch, suffix):
        monkeypatch.setattr(images, "_CHUNK", 999)  # neither the header nor the voxels fall on chunk boundaries
        array = sitk.GetArrayFromImage(make_volume())
        array.flat[[0, 249, 250, 5000, array.size - 1]] = (np.nan, np.nan, np.inf, np.nan, np.inf)
        path = tmp_path / f"v{suffix}"
        sitk.WriteImage(sitk.GetImageFromArray(array), str(path))
        with pytest.raises(InputError, match=r"holds 3 NaN and 2 infinite voxels out of 13440"):
            io.read_image(path)
        cut(path, 0.7)
        with pytest.raises(InputError, match="is truncated"):
            io.read_image(path)

    @pytest.mark.parametrize("suffix", [".mha", ".nii.gz"])
    def test_highly_compressed_file_is_not_called_truncated(self, tmp_path, monkeypatch, suffix):
        # 256 KB of zeros inflate from a few hundred bytes: many chunks of output per chunk of input.
        monkeypatch.setattr(images, "_CHUNK", 1000)
        path = tmp_path / f"zeros{suffix}"
        sitk.WriteImage(sitk.Image(40, 40, 40, sitk.sitkFloat32), str(path), useCompression=True)
        with pytest.raises(InputError, match="all voxels equal 0"):
            io.read_image(path)

    @pytest.mark.parametrize("value", [0, 7])
    def test_constant_volume(self, tmp_path, value):
        path = tmp_path / "blank.nrrd"
        sitk.WriteImage(sitk.GetImageFromArray(np.full(SIZE[::-1], value, np.int16)), str(path))
        with pytest.raises(InputError, match=rf"all voxels equal {value}; the volume is blank"):
            io.read_image(path)


class TestReadImageDicom:
    def test_series_folder(self, tmp_path):
        expected = write_dicom_series(tmp_path, "1.2.826.0.1.3680043.2.1125.1", "axial CT", slices=6)
        image = io.read_image(tmp_path)
        assert_same_geometry(image, expected, 1e-6)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(image), sitk.GetArrayFromImage(expected))

    def test_several_series_listed_and_chosen(self, tmp_path):
        write_dicom_series(tmp_path, "1.2.3.1", "axial CT", slices=6)
        write_dicom_series(tmp_path, "1.2.3.2", "scout", slices=4, seed=2)
        message = (rf"{re.escape(str(tmp_path))}: holds 2 DICOM series: 1\.2\.3\.1 \(6 files, 'axial CT'\); "
                   rf"1\.2\.3\.2 \(4 files, 'scout'\); choose one as {re.escape(str(tmp_path))}@UID")
        with pytest.raises(InputError, match=message):
            io.read_image(tmp_path)
        assert io.read_image(f"{tmp_path}@1.2.3.2").GetSize() == (20, 24, 4)
        assert io.read_image(f"{tmp_path}@1.2.3.1").GetSize() == (20, 24, 6)

    def test_unknown_series_uid(self, tmp_path):
        write_dicom_series(tmp_path, "1.2.3.1", "axial CT", slices=3)
        with pytest.raises(InputError, match=r"holds no DICOM series with UID 9\.9; it holds 1\.2\.3\.1 \(3 files"):
            io.read_image(f"{tmp_path}@9.9")

    def test_folder_without_dicom(self, tmp_path):
        (tmp_path / "readme.txt").write_text("hello")
        with pytest.raises(InputError, match=r"is a folder holding no DICOM series \(1 files\)"):
            io.read_image(tmp_path)

    def test_missing_slice(self, tmp_path):
        # ITK only warns ("Non uniform sampling or missing slices") and stretches the volume over the gap.
        write_dicom_series(tmp_path, "1.2.3.1", "axial CT", slices=6)
        next(tmp_path.glob("*-003.dcm")).unlink()
        with pytest.raises(InputError, match=r"its 5 slices are not evenly spaced along one line: 4 mm between "
                                             r"slices 3 and 4, 2 mm elsewhere .*a slice is missing"):
            io.read_image(tmp_path)

    def test_gantry_tilt(self, tmp_path):
        # ITK stacks tilted slices along the normal, unsheared, without a word.
        write_dicom_series(tmp_path, "1.2.3.1", "tilted CT", slices=6, tilt_mm=1.0)
        with pytest.raises(InputError, match=r"its slices are sheared, each 1 mm off the slice normal from the one "
                                             r"before \(a gantry tilt of 26\.6 degrees\).* misplaced by up to 5 mm"):
            io.read_image(tmp_path)

    def test_one_slice_out_of_line(self, tmp_path):
        write_dicom_series(tmp_path, "1.2.3.1", "axial CT", slices=8, moved={3: (3.0, 0.0, 0.0)})
        with pytest.raises(InputError, match=r"its 8 slices are not evenly spaced along one line: slice 4 lies "
                                             r"2\.61 mm from where an evenly spaced stack puts it; .*mixes "
                                             r"acquisitions"):
            io.read_image(tmp_path)

    def test_oblique_positions_rounded_to_hundredths(self, tmp_path):
        # Scanners often write Image Position to 0.01 mm: 0.017 mm of noise on each 1 mm step of this oblique series.
        turned = Rotation.from_euler("xyz", (17.0, -11.0, 23.0), degrees=True).as_matrix().ravel()
        written = write_dicom_series(tmp_path, "1.2.3.1", "oblique MR", slices=60, direction=tuple(turned),
                                     step_mm=1.0, decimals=2)
        read = io.read_image(tmp_path)
        np.testing.assert_allclose(read.GetDirection(), written.GetDirection(), atol=1e-3)

    def test_a_folder_holding_one_multi_frame_file(self, tmp_path):
        """Enhanced DICOM keeps a whole volume in one file: its folder read 4-D, and the memory check counted one
        frame."""
        volume = sitk.GetImageFromArray(np.random.default_rng(0).integers(0, 1000, (12, 24, 20), dtype=np.uint16))
        volume.SetSpacing((1.0, 1.0, 2.0))
        sitk.WriteImage(volume, str(tmp_path / "enhanced.dcm"))
        read = io.read_image(tmp_path)
        assert read.GetSize() == (20, 24, 12) and read.GetSpacing() == (1.0, 1.0, 2.0)
        with pytest.raises(InputError, match=r"size \(20, 24, 12\) \(5,760 voxels\) needs about"):
            io.read_image(tmp_path, max_bytes=50_000)
        shutil.copy(tmp_path / "enhanced.dcm", tmp_path / "copy.dcm")
        with pytest.raises(InputError, match=r"is 2 multi-frame files of 12 frames each .*; pass one file's path"):
            io.read_image(tmp_path)

    def test_single_slice_file(self, tmp_path):
        write_dicom_series(tmp_path, "1.2.3.1", "axial CT", slices=2)
        with pytest.raises(InputError, match="a single DICOM file is one slice: pass the folder"):
            io.read_image(next(tmp_path.glob("*.dcm")))


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

    def test_two_dimensional_mask(self, volume):
        with pytest.raises(InputError, match="moving mask: is 2-D"):
            io.check_mask(sitk.Image(20, 24, sitk.sitkUInt8), volume, "moving mask")

    # SimpleITK aborts the whole process (SIGABRT, "not supported for LabelMaps") when a label map's voxels are read
    # as an array, as both checks did before: each case runs in a child so an abort fails the test, not pytest.
    def test_label_map_volume_is_refused_before_reading_voxels(self):
        result = _run_child("""
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
        result = _run_child("""
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


def _run_child(body: str) -> subprocess.CompletedProcess:
    """``body`` in a fresh Python with ``sitk``, ``io`` and ``InputError`` imported; output captured."""
    code = "import SimpleITK as sitk\nfrom dpcn_med import io\nfrom dpcn_med.errors import InputError\n"
    return subprocess.run([sys.executable, "-c", code + textwrap.dedent(body)], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})


class TestReadCsv:
    def test_spreadsheet_byte_order_mark_and_spaced_header(self, tmp_path):
        path = tmp_path / "t.csv"
        path.write_bytes("\ufeffid, fixed ,moving\nx,a.nii,b.nii\n".encode())
        assert io.read_csv(path, {"fixed": str, "moving": str}) == [(2, {"id": "x", "fixed": "a.nii",
                                                                          "moving": "b.nii"})]

    def test_blank_lines_are_skipped_and_rows_carry_their_own_line(self, tmp_path):
        path = tmp_path / "t.csv"
        path.write_text('\n\nid,fixed\n\n \n"a\nb",x.nii\n,,\nc,y.nii\n')
        assert io.read_csv(path, {"fixed": str}) == [(7, {"id": "a\nb", "fixed": "x.nii"}),
                                                      (9, {"id": "c", "fixed": "y.nii"})]

    def test_a_short_row_has_none_for_its_missing_cells(self, tmp_path):
        (tmp_path / "t.csv").write_text("id,fixed,mask\na,x.nii\n")
        assert io.read_csv(tmp_path / "t.csv", {"fixed": str}) == [(2, {"id": "a", "fixed": "x.nii", "mask": None})]

    @pytest.mark.parametrize("text, message", [
        ("id,fixed,fixed\na,x,y\n", r"t\.csv: column 'fixed' appears more than once in the header"),
        ("fixed\nx.nii,y.nii\n", r"t\.csv: line 2: 2 cells under 1 columns \(a comma in a value needs the value in "
                                  r"double quotes\)"),
        ("id,fixed,fixed-mask\na,x,y\n", r"t\.csv: unknown column 'fixed-mask' \(the columns are fixed, id, "
                                         r"fixed_mask\)"),
    ])
    def test_refuses_a_header_or_row_that_would_lose_a_value(self, tmp_path, text, message):
        (tmp_path / "t.csv").write_text(text)
        with pytest.raises(InputError, match=message):
            io.read_csv(tmp_path / "t.csv", {"fixed": str}, allowed=("id", "fixed_mask"))

    def test_folder(self, tmp_path):
        with pytest.raises(InputError, match=r": is a folder; expected a file"):
            io.read_csv(tmp_path, {"fixed": str})


def similarity() -> sitk.Similarity3DTransform:
    transform = sitk.Similarity3DTransform()
    transform.SetParameters((0.1, -0.2, 0.3, 4.0, -5.5, 6.25, 1.1))
    transform.SetCenter((1.0, 2.0, 3.0))
    return transform


class TestReadTransform:
    @pytest.mark.parametrize("suffix", io.TRANSFORM_SUFFIXES)
    def test_round_trip(self, tmp_path, suffix):
        path = tmp_path / f"t{suffix}"
        sitk.WriteTransform(similarity(), str(path))
        transform = io.read_transform(path)
        assert isinstance(transform, sitk.Similarity3DTransform)
        np.testing.assert_allclose(transform.GetParameters(), similarity().GetParameters(), rtol=0, atol=1e-15)
        assert transform.GetFixedParameters() == similarity().GetFixedParameters()

    def test_missing(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"t\.tfm: not found"):
            io.read_transform(tmp_path / "t.tfm")

    def test_garbage(self, tmp_path):
        path = tmp_path / "t.tfm"
        path.write_text("hello\n")
        with pytest.raises(InputError, match=r"t\.tfm: not a readable transform \(Tags must be delimited by :\)"):
            io.read_transform(path)

    @pytest.mark.parametrize("suffix", [".tfm", ".h5"])
    def test_truncated(self, tmp_path, suffix):
        path = tmp_path / f"t{suffix}"
        sitk.WriteTransform(similarity(), str(path))
        cut(path, 0.6)
        with pytest.raises(InputError, match="not a readable transform"):
            io.read_transform(path)

    def test_two_dimensional(self, tmp_path):
        path = tmp_path / "t.tfm"
        sitk.WriteTransform(sitk.Euler2DTransform(), str(path))
        with pytest.raises(InputError, match="is a 2-D transform; expected a 3-D one"):
            io.read_transform(path)

    @pytest.mark.parametrize("parameters,message", [
        ("0 0 0 1 2", r"line 4: Euler3DTransform_double_3_3 takes 6 Parameters, the file gives 5"),
        ("0 0 0 1 2 3 4", r"line 4: Euler3DTransform_double_3_3 takes 6 Parameters, the file gives 7"),
        ("0 0 0 nan 0 0", r"line 4: Parameters holds a value that is not a finite number \('0 0 0 nan 0 0'\)"),
        ("0 0 0 1 2 abc", r"line 4: Parameters holds a value that is not a finite number \('0 0 0 1 2 abc'\)"),
    ])
    def test_parameters_itk_would_misread(self, tmp_path, parameters, message):
        """ITK stops at 'nan' or 'abc' and keeps the values before; with too few it read past them, and the process
        died of heap corruption (or went on with garbage)."""
        path = tmp_path / "t.tfm"
        path.write_text("#Insight Transform File V1.0\n#Transform 0\nTransform: Euler3DTransform_double_3_3\n"
                        f"Parameters: {parameters}\nFixedParameters: 0 0 0 0\n")
        with pytest.raises(InputError, match=rf"t\.tfm: {message}; compute and write the transform again"):
            io.read_transform(path)

    @pytest.mark.parametrize("transform", [sitk.AffineTransform(2), sitk.TranslationTransform(2)],
                             ids=lambda t: t.GetName())
    def test_a_two_dimensional_text_file_is_named_as_such(self, tmp_path, transform):
        """Counted as its 3-D class, an AffineTransform_double_2_2 was said to lack parameters."""
        sitk.WriteTransform(transform, str(tmp_path / "t.tfm"))
        with pytest.raises(InputError, match="is a 2-D transform; expected a 3-D one"):
            io.read_transform(tmp_path / "t.tfm")

    def test_a_class_simpleitk_cannot_read_back_is_named(self, tmp_path):
        """A raw KeyError from SimpleITK's Downcast before: an internal error."""
        sitk.WriteTransform(sitk.ComposeScaleSkewVersor3DTransform(), str(tmp_path / "t.tfm"))
        with pytest.raises(InputError, match=r"t\.tfm: holds a transform class SimpleITK cannot read back .*write it "
                                             r"as an AffineTransform$"):
            io.read_transform(tmp_path / "t.tfm")

    def test_a_comment_line_first_does_not_hide_misread_parameters(self, tmp_path):
        path = tmp_path / "t.tfm"
        path.write_text("# written by hand\n#Insight Transform File V1.0\n#Transform 0\n"
                        "Transform: Euler3DTransform_double_3_3\nParameters: 0 0 0 1 2\nFixedParameters: 0 0 0 0\n")
        with pytest.raises(InputError, match=r"line 5: Euler3DTransform_double_3_3 takes 6 Parameters, the file "
                                             r"gives 5"):
            io.read_transform(path)

    def test_a_file_that_cannot_be_opened_is_an_input_error(self, tmp_path):
        """A socket (or an unreadable file) escaped as a raw OSError, an internal error."""
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(tmp_path / "t.tfm"))
        try:
            with pytest.raises(InputError, match=r"t\.tfm: cannot be read \("):
                io.read_transform(tmp_path / "t.tfm")
        finally:
            server.close()

    def test_text_files_of_every_linear_kind_and_composites_still_read(self, tmp_path):
        for number, transform in enumerate([sitk.AffineTransform(3), sitk.TranslationTransform(3, (1.0, 2.0, 3.0)),
                                            sitk.Euler3DTransform(), sitk.VersorRigid3DTransform(),
                                            sitk.ScaleSkewVersor3DTransform(), sitk.ScaleTransform(3),
                                            sitk.CompositeTransform([similarity(), sitk.Euler3DTransform()])]):
            sitk.WriteTransform(transform, str(tmp_path / f"t{number}.tfm"))
            assert io.read_transform(tmp_path / f"t{number}.tfm").GetName() == transform.GetName()

    def test_non_finite_parameters(self, tmp_path):
        # HDF5 stores the NaN as it is; ITK's text parser would refuse it already.
        path = tmp_path / "t.h5"
        sitk.WriteTransform(sitk.TranslationTransform(3, (1.0, math.nan, 3.0)), str(path))
        with pytest.raises(InputError, match="holds NaN or infinite parameters"):
            io.read_transform(path)


class TestAtomicOutput:
    def test_temporary_beside_with_full_suffix(self, tmp_path):
        target = tmp_path / "x.nii.gz"
        with io.atomic_output(target) as temporary:
            assert temporary.parent == tmp_path and re.fullmatch(r"\.x\.tmp[0-9a-f]{8}\.nii\.gz", temporary.name)
            temporary.write_text("done")
        assert target.read_text() == "done" and os.listdir(tmp_path) == ["x.nii.gz"]

    @pytest.mark.parametrize("stem", ["a" * 248, "é" * 124])  # 255 bytes with .nii.gz, 2 bytes a character
    def test_a_name_at_the_length_limit(self, tmp_path, stem):
        """The temporary name ran 14 bytes past the target's: 'File name too long'."""
        volume = sitk.Image(4, 4, 4, sitk.sitkUInt8)
        volume[1, 2, 3] = 7
        target = tmp_path / f"{stem}.nii.gz"
        io.write_image(volume, target)
        assert os.listdir(tmp_path) == [target.name] and io.read_image(target).GetSize() == (4, 4, 4)

    def test_failure_leaves_nothing(self, tmp_path):
        with pytest.raises(KeyError), io.atomic_output(tmp_path / "x.json") as temporary:
            temporary.write_text("half")
            raise KeyError("interrupted")
        assert os.listdir(tmp_path) == []

    def test_existing_file_replaced_only_on_success(self, tmp_path):
        target = tmp_path / "report.json"
        target.write_text("old")
        with pytest.raises(RuntimeError), io.atomic_output(target) as temporary:
            temporary.write_text("new")
            raise RuntimeError("disk on fire")
        assert target.read_text() == "old" and os.listdir(tmp_path) == ["report.json"]
        with io.atomic_output(target) as temporary:
            temporary.write_text("new")
        assert target.read_text() == "new" and os.listdir(tmp_path) == ["report.json"]

    def test_missing_folder(self, tmp_path):
        with pytest.raises(InputError, match=r"folder .*absent does not exist; create it first"):
            with io.atomic_output(tmp_path / "absent" / "x.txt"):
                pass


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


class TestWriteTransform:
    @pytest.mark.parametrize("suffix", io.TRANSFORM_SUFFIXES)
    def test_round_trip(self, tmp_path, suffix):
        path = tmp_path / f"t{suffix}"
        io.write_transform(similarity(), path)
        np.testing.assert_allclose(sitk.ReadTransform(str(path)).GetParameters(), similarity().GetParameters(),
                                   rtol=0, atol=1e-15)
        assert os.listdir(tmp_path) == [path.name]

    def test_two_dimensional(self, tmp_path):
        transform = sitk.Euler2DTransform((1.0, 2.0), 0.3, (4.0, 5.0))
        io.write_transform(transform, tmp_path / "t.tfm")
        assert sitk.ReadTransform(str(tmp_path / "t.tfm")).GetParameters() == pytest.approx(transform.GetParameters())

    def test_unknown_suffix(self, tmp_path):
        with pytest.raises(InputError, match=r"t\.mat: cannot write a transform with this suffix; use \.tfm"):
            io.write_transform(similarity(), tmp_path / "t.mat")

    def test_upper_case_suffixes_and_nan_parameters_write_nothing(self, tmp_path, volume):
        """SimpleITK picks a writer by the suffix as spelt: .MHA left two temporary files, .TFM raised from ITK."""
        with pytest.raises(InputError, match=r"t\.TFM: cannot write a transform with this suffix; use .* in lower "):
            io.write_transform(similarity(), tmp_path / "t.TFM")
        with pytest.raises(InputError, match=r"a\.MHA: cannot write an image with this suffix; use .* in lower case"):
            io.write_image(volume, tmp_path / "a.MHA")
        with pytest.raises(InputError, match=r"t\.tfm: the transform holds NaN or infinite parameters"):
            io.write_transform(sitk.TranslationTransform(3, (float("nan"), 0, 0)), tmp_path / "t.tfm")
        assert os.listdir(tmp_path) == []


@pytest.mark.skipif(sys.platform == "win32", reason="file-size limits (RLIMIT_FSIZE) are POSIX")
class TestShortWrite:
    """A file-size limit makes ITK's NIfTI and text-transform writers stop short and return as if all went well."""

    # Not .h5: the HDF5 writer raises, but its library then crashes the process at exit under the limit (measured).
    @pytest.mark.parametrize("name", ["out.nii.gz", "out.nii", "out.mha", "out.nrrd", "bspline.tfm"])
    def test_refused_and_nothing_left(self, tmp_path, name):
        result = _run_child(f"""
            import os, resource
            import numpy as np
            os.chdir({str(tmp_path)!r})
            image = sitk.GetImageFromArray(np.random.default_rng(0).random((64, 64, 64)).astype(np.float32))
            bspline = sitk.BSplineTransform(3)
            bspline.SetTransformDomainMeshSize([30] * 3)  # about 100,000 parameters, 2 MB of text
            resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
            try:
                if {name!r}.startswith("bspline"):
                    io.write_transform(bspline, {name!r})
                else:
                    io.write_image(image, {name!r})
            except (OSError, RuntimeError) as error:  # the writers that notice raise RuntimeError themselves
                print(type(error).__name__, error)
            print(sorted(os.listdir(".")))
            """)
        assert result.returncode == 0, result.stderr[-500:]
        if name.endswith((".nii.gz", ".nii", ".tfm")):  # the writers that report on stderr only
            assert result.stdout.startswith(f"OSError {name}: writing it failed: the file came out incomplete"), \
                result.stdout
        assert result.stdout.endswith("[]\n"), result.stdout  # no temporary, no partial file


class TestWriteJson:
    def test_numpy_values_and_paths(self, tmp_path):
        path = tmp_path / "report.json"
        io.write_json({"matrix": np.eye(2), "score": np.float32(0.5), "count": np.int64(3), "ok": np.bool_(True),
                       "input": Path("a/b.nii.gz"), "shape": (1, 2)}, path)
        text = path.read_text()
        assert json.loads(text) == {"matrix": [[1.0, 0.0], [0.0, 1.0]], "score": 0.5, "count": 3, "ok": True,
                                    "input": "a/b.nii.gz", "shape": [1, 2]}
        assert text.startswith('{\n  "matrix": [\n') and text.endswith("}\n")

    def test_unserialisable_leaves_nothing(self, tmp_path):
        with pytest.raises(TypeError, match="set is not JSON serialisable"):
            io.write_json({"bad": {1, 2}}, tmp_path / "report.json")
        assert os.listdir(tmp_path) == []


class TestWriteText:
    def test_exact_content(self, tmp_path):
        path = tmp_path / "summary.csv"
        io.write_text("id,status\nα,ok\n", path)
        assert path.read_bytes() == "id,status\nα,ok\n".encode()


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


class TestTensors:
    def test_round_trip_and_atomic(self, tmp_path):
        import torch

        tensors = {"a": torch.arange(6.0).reshape(2, 3), "b": torch.ones(4, dtype=torch.int64)}
        io.write_tensors(tensors, tmp_path / "t.safetensors", metadata={"format": "x"})
        read = io.read_tensors(tmp_path / "t.safetensors")
        assert set(read) == {"a", "b"} and all(torch.equal(read[k], tensors[k]) for k in tensors)
        assert [p.name for p in tmp_path.iterdir()] == ["t.safetensors"]

    def test_permissions_follow_the_umask(self, tmp_path):
        import torch

        mask = os.umask(0o027)
        try:
            io.write_tensors({"a": torch.zeros(2)}, tmp_path / "t.safetensors")
            io.write_json({}, tmp_path / "t.json")
        finally:
            os.umask(mask)
        modes = [(tmp_path / name).stat().st_mode & 0o777 for name in ("t.safetensors", "t.json")]
        assert modes == [0o640, 0o640]  # safetensors alone would make its file 0600

    def test_refuses_pickles_and_garbage(self, tmp_path):
        import torch

        torch.save({"a": torch.zeros(1)}, tmp_path / "w.pt")
        with pytest.raises(InputError, match=r"w\.pt: a pickled file; dpcn_med only reads \.safetensors"):
            io.read_tensors(tmp_path / "w.pt")
        (tmp_path / "g.safetensors").write_bytes(b"\x00" * 40)
        with pytest.raises(InputError, match=r"g\.safetensors: not a readable \.safetensors file"):
            io.read_tensors(tmp_path / "g.safetensors")
        with pytest.raises(InputNotFoundError, match=r"none\.safetensors: not found"):
            io.read_tensors(tmp_path / "none.safetensors")
        with pytest.raises(InputError, match=r"x\.npy: tensors are written as \.safetensors"):
            io.write_tensors({}, tmp_path / "x.npy")


class TestReadJson:
    def test_reads_and_names_the_problem(self, tmp_path):
        (tmp_path / "a.json").write_text('{"k": [1, 2]}')
        assert io.read_json(tmp_path / "a.json") == {"k": [1, 2]}
        (tmp_path / "b.json").write_text("{not json")
        with pytest.raises(InputError, match=r"b\.json: not a JSON file"):
            io.read_json(tmp_path / "b.json")
        with pytest.raises(InputNotFoundError, match=r"c\.json: not found"):
            io.read_json(tmp_path / "c.json")

    # Before: RecursionError and a ValueError of Python's limit on integer digits, as internal errors.
    def test_json_python_cannot_hold_is_refused(self, tmp_path):
        (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
        with pytest.raises(InputError, match=r"deep\.json: JSON nested too deeply to read"):
            io.read_json(tmp_path / "deep.json")
        (tmp_path / "digits.json").write_text('{"bandwidth": ' + "1" * 5000 + "}")
        with pytest.raises(InputError, match=r"digits\.json: unreadable JSON \(Exceeds the limit"):
            io.read_json(tmp_path / "digits.json")


class TestReadText:
    def test_reads_and_names_the_problem(self, tmp_path):
        (tmp_path / "a.txt").write_text("Point 1\n")
        assert io.read_text(tmp_path / "a.txt") == "Point 1\n"
        (tmp_path / "b.txt").write_bytes(b"\xff\xfe\x00")
        with pytest.raises(InputError, match=r"b\.txt: not a utf-8 text file"):
            io.read_text(tmp_path / "b.txt")
        assert io.read_text(tmp_path / "b.txt", encoding="latin-1") == "\xff\xfe\x00"
        (tmp_path / "pairs.csv").write_bytes(gzip.compress(b"\x00\xff" * 100))  # a .nii.gz given for the pairs file
        with pytest.raises(InputError, match=r"^\S*pairs\.csv: is a gzip-compressed \(\.gz\) file, not text$"):
            io.read_text(tmp_path / "pairs.csv")
        with pytest.raises(InputNotFoundError, match=r"c\.txt: not found"):
            io.read_text(tmp_path / "c.txt")


class TestCsv:
    def test_header_from_the_first_row_or_the_columns_given(self, tmp_path):
        rows = [{"id": "a", "tre_mm": 0.5, "note": "x"}, {"id": "b", "tre_mm": 2.0, "note": "y"}]
        io.write_csv(rows, tmp_path / "all.csv")
        assert (tmp_path / "all.csv").read_bytes() == b"id,tre_mm,note\na,0.5,x\nb,2.0,y\n"
        io.write_csv(rows, tmp_path / "some.csv", ["tre_mm", "id"])
        assert (tmp_path / "some.csv").read_text() == "tre_mm,id\n0.5,a\n2.0,b\n"

    def test_no_rows(self, tmp_path):
        io.write_csv([], tmp_path / "empty.csv", ["id", "tre_mm"])
        assert (tmp_path / "empty.csv").read_text() == "id,tre_mm\n"
        with pytest.raises(ValueError, match=r"none\.csv: no rows and no columns"):  # was an IndexError
            io.write_csv([], tmp_path / "none.csv")
        assert not (tmp_path / "none.csv").exists()

    def test_read_back_with_the_types_given(self, tmp_path):
        rows = [{"id": "a", "trial": 0, "tre_mm": 0.5}, {"id": "b", "trial": 1, "tre_mm": 2.25}]
        io.write_csv(rows, tmp_path / "rows.csv")
        assert io.read_csv(tmp_path / "rows.csv", {"trial": int, "tre_mm": float}) == list(zip([2, 3], rows))
        assert io.read_csv(tmp_path / "rows.csv", {"tre_mm": float})[1][1]["trial"] == "1"  # other columns: strings
        with pytest.raises(InputError, match=r"rows\.csv: no column seconds, method: its header row is 'id,trial,"
                                             r"tre_mm'; expected a header row naming trial, seconds, method"):
            io.read_csv(tmp_path / "rows.csv", {"trial": int, "seconds": float, "method": str})
        (tmp_path / "semicolons.csv").write_text("fixed;moving\na.nii;b.nii\n")  # a spreadsheet's other separator
        with pytest.raises(InputError, match=r"no column fixed, moving: its header row is 'fixed;moving'; expected a "
                                             r"header row naming fixed, moving, cells separated by commas$"):
            io.read_csv(tmp_path / "semicolons.csv", {"fixed": str, "moving": str})
        (tmp_path / "bad.csv").write_text("id,trial\na,0\nb,one\n")
        with pytest.raises(InputError, match=r"bad\.csv: line 3: invalid literal for int"):
            io.read_csv(tmp_path / "bad.csv", {"trial": int})
        with pytest.raises(InputNotFoundError, match=r"none\.csv: not found"):
            io.read_csv(tmp_path / "none.csv", {"trial": int})
        (tmp_path / "huge.csv").write_text("id,trial\n" + "a" * 200_000 + ",0\n")  # over csv's field size limit
        with pytest.raises(InputError, match=r"huge\.csv: not a readable CSV file \(field larger than field limit"):
            io.read_csv(tmp_path / "huge.csv", {"trial": int})

    def test_a_row_with_an_unknown_key_leaves_no_file(self, tmp_path):
        with pytest.raises(ValueError, match="fields not in fieldnames"):
            io.write_csv([{"id": "a"}, {"id": "b", "other": 1}], tmp_path / "bad.csv")
        assert list(tmp_path.iterdir()) == []
