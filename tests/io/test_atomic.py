"""Tests for dpcn_med.io.atomic: files appear complete or not at all."""

from __future__ import annotations

import os
import re
import sys

import pytest
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError
from tests.io.conftest import run_child


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


@pytest.mark.skipif(sys.platform == "win32", reason="file-size limits (RLIMIT_FSIZE) are POSIX")
class TestShortWrite:
    """A file-size limit makes ITK's NIfTI and text-transform writers stop short and return as if all went well."""

    # Not .h5: the HDF5 writer raises, but its library then crashes the process at exit under the limit (measured).
    @pytest.mark.parametrize("name", ["out.nii.gz", "out.nii", "out.mha", "out.nrrd", "bspline.tfm"])
    def test_refused_and_nothing_left(self, tmp_path, name):
        result = run_child(f"""
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
