"""Tests for dpcn_med.io.transforms: ITK transform files read and written."""

from __future__ import annotations

import math
import os
import socket

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError
from tests.io.conftest import cut


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
