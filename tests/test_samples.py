"""Built-in samples: the MNI152 T1, its head, brain and skull masks, and its pseudo-CT."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.samples import mni152_head_t1, mni152_masks, mni152_pseudo_ct, mni152_t1


@pytest.fixture(scope="module")
def t1() -> sitk.Image:
    return mni152_t1()


@pytest.fixture(scope="module")
def masks() -> dict[str, np.ndarray]:
    """The masks, checked to be uint8 on the T1's grid, as boolean arrays."""
    reference = mni152_t1()
    arrays = {}
    for name, mask in mni152_masks().items():
        assert mask.GetPixelID() == sitk.sitkUInt8, name
        assert (mask.GetSize(), mask.GetOrigin(), mask.GetSpacing(), mask.GetDirection()) == \
            (reference.GetSize(), reference.GetOrigin(), reference.GetSpacing(), reference.GetDirection()), name
        arrays[name] = sitk.GetArrayFromImage(mask)
    return arrays


@pytest.fixture(scope="module")
def ct() -> sitk.Image:
    return mni152_pseudo_ct(seed=0)


def _millilitres(mask: np.ndarray) -> float:
    return mask.sum() / 1000.0  # 1 mm voxels


class TestMni152T1:
    def test_template_grid(self, t1):
        assert t1.GetSize() == (197, 233, 189)
        assert t1.GetSpacing() == (1.0, 1.0, 1.0)


class TestMni152Masks:
    def test_binary_with_the_expected_keys(self, masks):
        assert set(masks) == {"head", "brain", "bone"}
        assert all(set(np.unique(mask)) == {0, 1} for mask in masks.values())

    def test_plausible_volumes(self, masks):
        # The template's brain is larger than an average adult's (about 1.75 l of grey and white matter).
        assert 1000 <= _millilitres(masks["brain"]) <= 1900
        assert 300 <= _millilitres(masks["bone"]) <= 900
        assert _millilitres(masks["head"]) > _millilitres(masks["brain"]) + _millilitres(masks["bone"])

    def test_bone_surrounds_the_brain_inside_the_head(self, masks, t1):
        brain, bone, head = (masks[name].astype(bool) for name in ("brain", "bone", "head"))
        assert not (bone & brain).any()
        assert not (bone & ~head).any() and not (brain & ~head).any()
        # Where the skull-stripped T1 has no signal.
        assert np.median(sitk.GetArrayViewFromImage(t1)[bone]) == 0
        # Through the brain's centre: bone on both sides along x and y (a ring in the axial slice) and above it.
        z, y, x = (int(round(c)) for c in np.argwhere(brain).mean(axis=0))
        for bone_line, brain_line in ((bone[z, y, :], brain[z, y, :]), (bone[z, :, x], brain[z, :, x])):
            bone_at, brain_at = np.flatnonzero(bone_line), np.flatnonzero(brain_line)
            assert bone_at[0] < brain_at[0] and brain_at[-1] < bone_at[-1]
        assert np.flatnonzero(brain[:, y, x])[-1] < np.flatnonzero(bone[:, y, x])[-1]


class TestMni152PseudoCT:
    def test_geometry_and_type_follow_the_t1(self, ct, t1):
        assert ct.GetPixelID() == sitk.sitkInt16
        assert (ct.GetSize(), ct.GetOrigin(), ct.GetSpacing(), ct.GetDirection()) == \
            (t1.GetSize(), t1.GetOrigin(), t1.GetSpacing(), t1.GetDirection())

    def test_densities(self, ct, masks):
        hu = sitk.GetArrayViewFromImage(ct)
        assert np.median(hu[masks["head"] == 0]) < -900
        assert np.median(hu[masks["bone"] > 0]) > 600
        assert 15 <= np.median(hu[masks["brain"] > 0]) <= 60

    def test_bone_to_brain_contrast_is_reversed(self, ct, t1, masks):
        def contrast(image: sitk.Image) -> float:
            values = sitk.GetArrayViewFromImage(image)
            return float(np.median(values[masks["bone"] > 0])) - float(np.median(values[masks["brain"] > 0]))

        assert contrast(t1) < 0 < contrast(ct)


class TestMni152HeadT1:
    def test_t1_contrast_of_the_modelled_layers(self, t1, masks):
        head = mni152_head_t1(seed=0)
        assert head.GetSize() == t1.GetSize() and head.GetOrigin() == t1.GetOrigin()
        array = sitk.GetArrayFromImage(head)
        brain, bone, inside = (masks[k] > 0 for k in ("brain", "bone", "head"))
        scalp = inside & ~bone & ~brain & (sitk.GetArrayFromImage(t1) == 0)
        # the template's brain is kept as it is; bone is dark, the outer scalp (fat) bright, air stays 0
        np.testing.assert_array_equal(array[brain], sitk.GetArrayFromImage(t1)[brain])
        assert np.median(array[bone]) < 0.2 * np.median(array[brain]) < np.median(array[scalp])
        assert array[~inside].max() == 0.0
        # between brain and skull, CSF is dark (it was painted scalp-bright before)
        near_brain = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(  # in voxels: 1 mm
            sitk.GetImageFromArray(masks["brain"]), insideIsPositive=False, squaredDistance=False))
        csf = inside & ~bone & ~brain & (sitk.GetArrayFromImage(t1) == 0) & (near_brain > 0) & (near_brain <= 2.0)
        assert csf.sum() > 10_000 and np.median(array[csf]) < 0.25 * np.median(array[brain]), np.median(array[csf])
