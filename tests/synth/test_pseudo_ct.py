"""Pseudo-CT from a T1 MR and tissue masks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.synth import CTTissues, pseudo_ct
from tests.conftest import shared_path


def _phantom() -> dict[str, sitk.Image]:
    """A T1-like head of nested spheres, 2 mm voxels: white matter inside grey, a CSF core, a dark skull, a scalp."""
    radius = np.linalg.norm(np.mgrid[:40, :40, :40] - 19.5, axis=0)
    shells = {"csf": radius < 3, "white": (radius >= 3) & (radius < 8), "grey": (radius >= 8) & (radius < 12),
              "bone": (radius >= 13) & (radius < 16), "scalp": (radius >= 16) & (radius < 18)}
    t1 = {"csf": 60.0, "white": 200.0, "grey": 150.0, "bone": 10.0, "scalp": 180.0}
    mr = np.zeros(radius.shape, np.float32)
    for name, inside in shells.items():
        mr[inside] = t1[name]
    images = {"mr": sitk.GetImageFromArray(mr), "bone": sitk.GetImageFromArray(shells["bone"].astype(np.uint8)),
              "brain": sitk.GetImageFromArray((radius < 12).astype(np.uint8)),
              **{name: sitk.GetImageFromArray(inside.astype(np.uint8)) for name, inside in shells.items()
                 if name != "bone"}}
    for image in images.values():
        image.SetSpacing((2.0, 2.0, 2.0))
        image.SetOrigin((-40.0, 10.0, 3.0))
    return images


def _median(ct: sitk.Image, mask: sitk.Image) -> float:
    return float(np.median(sitk.GetArrayViewFromImage(ct)[sitk.GetArrayViewFromImage(mask) > 0]))


@pytest.fixture(scope="module")
def seg3d() -> dict[str, sitk.Image]:
    """The shared T1 with its skull and brain masks, and its pseudo-CT."""
    images = {name: sitk.ReadImage(str(shared_path(f"seg3d/{name}.nii.gz")))
              for name in ("MR", "skull_mask", "brain_mask")}
    images["CT"] = pseudo_ct(images["MR"], bone=images["skull_mask"], brain=images["brain_mask"], seed=0)
    return images


class TestPseudoCT:
    def test_tissue_densities_on_a_phantom(self):
        images = _phantom()
        ct = pseudo_ct(images["mr"], bone=images["bone"], brain=images["brain"], seed=1)
        hu = {name: _median(ct, images[name]) for name in ("csf", "white", "grey", "bone", "scalp")}
        # Grey matter is denser than white matter although darker on T1: the map is not monotonic.
        assert hu["csf"] < hu["white"] < hu["grey"]
        assert 5 <= hu["csf"] <= 20 and 20 <= hu["white"] <= 30 and 35 <= hu["grey"] <= 45
        assert hu["bone"] > 700 and 15 <= hu["scalp"] <= 65
        assert sitk.GetArrayViewFromImage(ct)[0, 0, 0] < -900

    def test_bone_is_brightest_at_its_surface(self):
        images = _phantom()
        ct = sitk.GetArrayFromImage(pseudo_ct(images["mr"], bone=images["bone"], seed=0, head=images["brain"]))
        radius = np.linalg.norm(np.mgrid[:40, :40, :40] - 19.5, axis=0)
        # Voxels at the inner table, the middle of the shell and the outer table.
        inner, middle, outer = (np.median(ct[np.abs(radius - r) < 0.5]) for r in (13.3, 14.5, 15.6))
        assert middle < min(inner, outer) - 200

    def test_seeded_noise(self):
        images = _phantom()
        first, again, other = (sitk.GetArrayFromImage(pseudo_ct(images["mr"], bone=images["bone"], seed=seed))
                               for seed in (3, 3, 4))
        np.testing.assert_array_equal(first, again)
        assert 5 < np.std(first[:5, :5, :5].astype(float) - other[:5, :5, :5]) / math.sqrt(2) < 20

    def test_an_mr_without_signal_in_the_brain_mask_is_refused(self):
        """The white matter level was 0: values / 0 became 0 HU over the skull and half the air, silently."""
        images = _phantom()
        mr = images["mr"] * sitk.Cast(images["brain"] == 0, images["mr"].GetPixelID())
        with pytest.raises(InputError, match=r"^brain mask: the MR's white matter level inside it is 0; expected a "
                                             r"positive T1 magnitude"):
            pseudo_ct(mr, bone=images["bone"], brain=images["brain"])

    def test_negative_seed_is_refused(self):
        images = _phantom()
        with pytest.raises(InputError, match="^seed is -1; expected an integer >= 0$"):
            pseudo_ct(images["mr"], bone=images["bone"], seed=-1)

    @pytest.mark.parametrize("options,message", [
        ({"noise_hu": math.nan}, "^noise_hu is nan; expected a finite number >= 0$"),
        ({"noise_hu": -5.0}, "^noise_hu is -5.0; expected a finite number >= 0$"),
        ({"cortex_mm": math.nan}, "^cortex_mm is nan; expected a finite number > 0$"),
        ({"cortex_mm": 0.0}, "^cortex_mm is 0.0; expected a finite number > 0$"),
        ({"blur_mm": -1.0}, "^blur_mm is -1.0; expected a finite number >= 0$"),
        ({"air": -math.inf}, "^air is -inf; expected a finite number$"),
        ({"bone_core": math.nan}, "^bone_core is nan; expected a finite number$"),
        ({"soft_tissue": (60.0, math.nan)}, r"^soft_tissue\[1\] is nan; expected a finite number$"),
        ({"soft_tissue": 60.0}, r"^soft_tissue is 60.0 \(float\); expected a tuple of 2 values$"),
        ({"t1_ratios": (0.3, 1.0)}, r"^t1_ratios is \(0.3, 1.0\): 2 values; expected 3$"),
        ({"t1_ratios": (0.0, 0.75, 1.0)}, r"^t1_ratios\[0\] is 0.0; expected a finite number > 0$"),
        ({"t1_ratios": (0.75, 0.3, 1.0)}, r"^t1_ratios is \(0.75, 0.3, 1.0\); expected CSF < grey matter < white"),
    ])
    def test_invalid_tissues(self, options, message):
        with pytest.raises(InputError, match=message):
            CTTissues(**options)

    def test_mask_off_the_grid_is_refused(self):
        images = _phantom()
        shifted = sitk.Image(images["bone"])
        shifted.SetOrigin((0.0, 0.0, 0.0))
        with pytest.raises(InputError, match="bone mask .* is not on the MR's grid"):
            pseudo_ct(images["mr"], bone=shifted)

    @pytest.mark.shared_data
    def test_geometry_and_type_follow_the_mr(self, seg3d):
        ct, mr = seg3d["CT"], seg3d["MR"]
        assert ct.GetPixelID() == sitk.sitkInt16
        assert (ct.GetSize(), ct.GetOrigin(), ct.GetSpacing(), ct.GetDirection()) == \
            (mr.GetSize(), mr.GetOrigin(), mr.GetSpacing(), mr.GetDirection())

    @pytest.mark.shared_data
    def test_densities_of_a_real_head(self, seg3d):
        # Air: where the MR has no signal, mostly outside the head.
        background = sitk.GetArrayViewFromImage(seg3d["MR"]) == 0
        assert np.median(sitk.GetArrayViewFromImage(seg3d["CT"])[background]) < -900
        assert _median(seg3d["CT"], seg3d["skull_mask"]) > 600
        assert 15 <= _median(seg3d["CT"], seg3d["brain_mask"]) <= 60

    @pytest.mark.shared_data
    def test_bone_to_brain_contrast_is_reversed(self, seg3d):
        def contrast(image: sitk.Image) -> float:
            return _median(image, seg3d["skull_mask"]) - _median(image, seg3d["brain_mask"])

        assert contrast(seg3d["MR"]) < 0 < contrast(seg3d["CT"])
