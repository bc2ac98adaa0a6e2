"""An ultrasound image simulated from a CT image in physical space: where its voxels lie, the craniotomy, the errors."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.synth import UltrasoundConfig
from dpcn_med.synth.ultrasound import B_MODE_FLOOR
from dpcn_med.synth.ultrasound_image import DYNAMIC_RANGE_DB, Craniotomy, ultrasound_image

DOWN = (0.0, 0.0, -1.0)  # beams from above (LPS +z) into the head
SCATTER = UltrasoundConfig(half_angle_degrees=(30.0, 30.0), depth_range=(0.6, 0.6), reflection_gain=0.0,
                           scatter_gain=1.0, attenuation=0.0, bone_attenuation=0.0)
"""Diffuse backscatter only, no absorption: every echo is the windowed CT times speckle."""


def _head(*, skull: bool = True, block: bool = True) -> sitk.Image:
    """A ball of brain (25 HU) of radius 60 mm in air, with a 6 mm skull (1500 HU) and a dense block (90 HU) in its
    upper half; 3 x 2.5 x 2 mm voxels and a rotated direction, so that the image's own frame is not the world's."""
    size = np.array([50, 60, 70])
    spacing = np.array([3.0, 2.5, 2.0])
    z, y, x = np.meshgrid(*[(np.arange(n) - n / 2 + 0.5) * s for n, s in zip(size[::-1], spacing[::-1])],
                          indexing="ij")
    radius = np.sqrt(x ** 2 + y ** 2 + z ** 2)
    hu = np.full(radius.shape, -1000.0)
    hu[radius < 60] = 25.0
    if skull:
        hu[(radius >= 54) & (radius < 60)] = 1500.0
    if block:
        hu[(abs(x - 10) < 12) & (abs(y + 8) < 10) & (z > 10) & (z < 30)] = 90.0
    image = sitk.GetImageFromArray(hu.astype(np.float32))
    image.SetSpacing(spacing.tolist())
    image.SetOrigin((-(size * spacing) / 2 + spacing / 2).tolist())
    return image


def _rotated(image: sitk.Image) -> sitk.Image:
    """``image`` resampled into a frame turned 30 degrees about z (same physical content)."""
    turn = sitk.VersorRigid3DTransform()
    turn.SetRotation((0.0, 0.0, 1.0), np.radians(30.0))
    reference = sitk.Image(image.GetSize(), sitk.sitkFloat32)
    reference.SetSpacing(image.GetSpacing())
    reference.SetDirection(np.asarray(turn.GetMatrix()).ravel().tolist())
    reference.SetOrigin(turn.TransformPoint(image.GetOrigin()))
    return sitk.Resample(image, reference, sitk.Transform(), sitk.sitkLinear, -1000.0)


def _correlation(first: np.ndarray, second: np.ndarray, where: np.ndarray) -> float:
    return float(np.corrcoef(first[where], second[where])[0, 1])


class TestUltrasoundImage:
    def test_a_cone_on_an_isotropic_grid_with_nothing_outside_it(self):
        ultrasound, cone = ultrasound_image(_head(), DOWN, seed=1, spacing=4.0, config=SCATTER)
        assert ultrasound.GetSpacing() == cone.GetSpacing() == (4.0, 4.0, 4.0)
        assert ultrasound.GetDirection() == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        assert ultrasound.GetOrigin() == cone.GetOrigin() and ultrasound.GetSize() == cone.GetSize()
        echoes, inside = sitk.GetArrayFromImage(ultrasound), sitk.GetArrayFromImage(cone).astype(bool)
        assert echoes.min() >= 0 and echoes.max() <= 1 and (echoes[~inside] == 0).all()
        # Cropped to the cone: every face of the box touches it.
        for axis in range(3):
            assert inside.take(0, axis=axis).any() and inside.take(-1, axis=axis).any()
        # Looking down: the apex above the ball (top at z = 60 mm), the cone below it.
        top = ultrasound.GetOrigin()[2] + (ultrasound.GetSize()[2] - 1) * 4.0
        assert 60.0 < top < 60.0 + 0.05 * 2 * 120 * np.sqrt(3) + 8.0

    def test_echoes_lie_where_the_anatomy_is_in_any_input_frame(self):
        head = _rotated(_head(skull=False))
        ultrasound, cone = ultrasound_image(head, DOWN, seed=2, spacing=4.0, config=SCATTER)
        echoes, inside = sitk.GetArrayFromImage(ultrasound), sitk.GetArrayFromImage(cone).astype(bool)

        def block_on_cone_grid(shift_mm: tuple[float, float, float]) -> np.ndarray:
            moved = sitk.TranslationTransform(3, shift_mm)
            return sitk.GetArrayFromImage(sitk.Resample(head, ultrasound, moved, sitk.sitkLinear, -1000.0))

        aligned = _correlation(echoes, block_on_cone_grid((0.0, 0.0, 0.0)), inside)
        shifted = [_correlation(echoes, block_on_cone_grid(shift), inside)
                   for shift in itertools.product((-8.0, 0.0, 8.0), repeat=3) if any(shift)]
        assert aligned > 0.3 and aligned > max(shifted)

    def test_the_craniotomy_opens_the_skull_to_the_probe(self):
        shadowed = UltrasoundConfig(half_angle_degrees=(30.0, 30.0), depth_range=(0.6, 0.6), bone_attenuation=200.0)
        results = {}
        for radius in (0.0, 40.0):
            ultrasound, cone = ultrasound_image(_head(block=False), DOWN, seed=3, spacing=4.0, config=shadowed,
                                                craniotomy=Craniotomy(radius_mm=radius))
            inner = sitk.Resample(sitk.Cast(_head(skull=False, block=False) > 0, sitk.sitkFloat32), ultrasound,
                                  sitk.Transform(), sitk.sitkNearestNeighbor, 0.0)
            # the brain well inside the skull, within the cone
            deep = sitk.GetArrayFromImage(sitk.BinaryErode(sitk.Cast(inner, sitk.sitkUInt8), [3, 3, 3])) > 0
            deep &= sitk.GetArrayFromImage(cone) > 0
            results[radius] = float(sitk.GetArrayFromImage(ultrasound)[deep].mean())
        assert results[40.0] > 5 * results[0.0]

    @pytest.mark.parametrize(("kwargs", "message"), [
        ({"probe": (0.0, 0.0, 0.0)}, re.escape("probe is (0, 0, 0)")),
        ({"probe": (0.0, 1.0)}, "probe"),
        ({"spacing": 0.0}, "spacing"),
        ({"seed": -1}, "seed"),
    ])
    def test_malformed_arguments_are_refused(self, kwargs, message):
        arguments = {"probe": DOWN, **kwargs}
        with pytest.raises(InputError, match=message):
            ultrasound_image(_head(), arguments.pop("probe"), **arguments)

    def test_a_two_dimensional_image_is_refused(self):
        with pytest.raises(InputError, match="3-D scalar CT"):
            ultrasound_image(sitk.Image([8, 8], sitk.sitkFloat32), DOWN)

    @pytest.mark.parametrize(("kwargs", "message"), [
        ({"radius_mm": -1.0}, "radius_mm"),
        ({"fill_hu": 400.0}, "fill_hu"),
        ({"window": (100.0, -50.0)}, "window"),
    ])
    def test_craniotomy_settings_are_checked(self, kwargs, message):
        with pytest.raises(InputError, match=message):
            Craniotomy(**kwargs)


class TestBModeImage:
    def test_the_image_is_log_compressed_by_default_and_raw_on_request(self):
        raw, cone = ultrasound_image(_head(), DOWN, seed=1, spacing=4.0, dynamic_range_db=None)
        shown, same_cone = ultrasound_image(_head(), DOWN, seed=1, spacing=4.0)
        inside = sitk.GetArrayFromImage(cone).astype(bool)
        assert (sitk.GetArrayFromImage(same_cone) == sitk.GetArrayFromImage(cone)).all()
        expected = np.clip(10 * np.log10(np.maximum(sitk.GetArrayFromImage(raw), 1e-30)) / DYNAMIC_RANGE_DB + 1,
                           B_MODE_FLOOR, 1.0)
        np.testing.assert_allclose(sitk.GetArrayFromImage(shown)[inside], expected[inside], atol=1e-5)
        assert (sitk.GetArrayFromImage(shown)[~inside] == 0).all() and (sitk.GetArrayFromImage(shown)[inside] > 0).all()

    def test_a_bad_range_is_refused_before_simulating(self):
        with pytest.raises(InputError, match="dynamic_range_db"):
            ultrasound_image(_head(), DOWN, dynamic_range_db=0.0)
