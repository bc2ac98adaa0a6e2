"""Tests for dpcn_med.io.integrity: truncated and corrupt files named as such, and file_sha256."""

from __future__ import annotations

import hashlib
import math
import re

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from dpcn_med import io
from dpcn_med.errors import InputError
from dpcn_med.io import integrity
from tests.io.conftest import SIZE, cut, make_volume


class TestReadImageIntegrity:
    """read_image refuses a file that holds less than its header promises, or voxels SimpleITK would misread."""

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
        monkeypatch.setattr(integrity, "_CHUNK", 999)  # neither the header nor the voxels fall on chunk boundaries
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
        monkeypatch.setattr(integrity, "_CHUNK", 1000)
        path = tmp_path / f"zeros{suffix}"
        sitk.WriteImage(sitk.Image(40, 40, 40, sitk.sitkFloat32), str(path), useCompression=True)
        with pytest.raises(InputError, match="all voxels equal 0"):
            io.read_image(path)


class TestFileSha256:
    def test_known_digest(self, tmp_path):
        (tmp_path / "abc.txt").write_bytes(b"abc")  # FIPS 180-2's example
        assert io.file_sha256(tmp_path / "abc.txt") == ("ba7816bf8f01cfea414140de5dae2223"
                                                        "b00361a396177a9cb410ff61f20015ad")

    def test_a_file_of_several_blocks(self, tmp_path):
        content = np.random.default_rng(0).bytes(3 * (1 << 20) + 12345)  # three 1 MiB blocks and part of a fourth
        (tmp_path / "w.safetensors").write_bytes(content)
        assert io.file_sha256(str(tmp_path / "w.safetensors")) == hashlib.sha256(content).hexdigest()

    @pytest.mark.parametrize("size", [0, 6, 7, 8, 50])
    def test_block_boundaries(self, tmp_path, monkeypatch, size):
        monkeypatch.setattr(integrity, "_CHUNK", 7)
        content = bytes(range(size))
        (tmp_path / "f").write_bytes(content)
        assert io.file_sha256(tmp_path / "f") == hashlib.sha256(content).hexdigest()

    def test_errors_are_oserrors(self, tmp_path):
        with pytest.raises(FileNotFoundError, match=r"none\.bin"):
            io.file_sha256(tmp_path / "none.bin")
        with pytest.raises(IsADirectoryError):
            io.file_sha256(tmp_path)
