"""Tests for dpcn_med.io.dicom: DICOM series read from their folder."""

from __future__ import annotations

import locale
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from dpcn_med import io
from dpcn_med.errors import InputError
from tests.io.conftest import assert_same_geometry


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
    # GDCM's writer leaves the process's locale at "C" (measured), and text read later in the default encoding
    # would then decode as ASCII (another test file's report with an en dash failed so): set it back.
    saved = locale.setlocale(locale.LC_ALL)
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
    locale.setlocale(locale.LC_ALL, saved)
    return volume


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
