"""Built-in sample volumes that need no download: the MNI152 2009a templates shipped inside the nilearn wheel."""

from __future__ import annotations

from importlib.resources import as_file, files

import numpy as np
import SimpleITK as sitk

from dpcn_med.synth import pseudo_ct

# Found among nilearn's package data without importing nilearn.datasets, which takes seconds.
_TEMPLATE = "mni_icbm152_{}_tal_nlin_sym_09a_converted.nii.gz"

# The template is skull-stripped: skull and scalp are modelled as shells around a smooth hull of the brain, like the
# inner table of the skull bridging sulci and fissures. Distances in mm; about 3 mm of CSF, 6 mm of bone (an adult
# calvarium's mean thickness) and 6 mm of scalp.
_BRAIN_PROBABILITY = 0.5
_HULL_CLOSING_MM = 8.0
_BONE_FROM_HULL_MM = (3.0, 9.0)
_SCALP_FROM_HULL_MM = 15.0
# T1-weighted intensities of the modelled layers, as fractions of white matter: CSF and cortical bone dark, scalp fat
# bright (typical ratios at 1.5-3 T).
_T1_RATIOS = {"csf": 0.15, "bone": 0.05, "scalp": 0.9}
_T1_NOISE = 0.02


def _template(kind: str) -> sitk.Image:
    """One of the ICBM 2009a symmetric templates at 1 mm in nilearn's package data: "t1", "gm" or "wm"."""
    with as_file(files("nilearn") / "datasets" / "data" / _TEMPLATE.format(kind)) as path:
        return sitk.ReadImage(str(path))


def _distance_outside(mask: sitk.Image) -> sitk.Image:
    """Signed distance in mm to the mask's surface: positive outside, negative inside."""
    return sitk.SignedMaurerDistanceMap(mask, insideIsPositive=False, squaredDistance=False, useImageSpacing=True)


def _hull_distance(brain: sitk.Image) -> sitk.Image:
    """Signed distance in mm to the brain closed by a ``_HULL_CLOSING_MM`` ball, positive outside, on its grid."""
    # Closing through distance maps (dilate, then erode by the same radius) is far faster than with a ball kernel of
    # this size; outside the hull, the distance to the dilated brain plus the radius is the distance to the hull.
    # Computed at 2 mm (8 times fewer voxels) and interpolated back: a distance map is smooth, linear is enough.
    coarse = sitk.BinShrink(sitk.Cast(brain, sitk.sitkFloat32), [2, 2, 2]) > 0.5
    dilated = _distance_outside(coarse) <= _HULL_CLOSING_MM
    # Maurer's values inside a mask are distances to its 26-connected surface voxels, up to sqrt(3) voxels short of
    # the distance to the outside; the complement's outside values are exact.
    outside = sitk.Clamp(_distance_outside(dilated), lowerBound=0.0)
    inside = sitk.Clamp(_distance_outside(dilated == 0), lowerBound=0.0)
    hull = outside - inside + _HULL_CLOSING_MM
    far_outside_mm = 1e3
    return sitk.Resample(hull, brain, sitk.Transform(), sitk.sitkLinear, far_outside_mm)


def mni152_t1() -> sitk.Image:
    """The MNI152 ICBM 2009a symmetric T1 template at 1 mm (197 x 233 x 189), as a SimpleITK image in LPS.

    Fonov et al., NeuroImage 2011; redistributed with nilearn under its licence. Skull-stripped: brain and CSF.
    """
    return _template("t1")


def mni152_masks() -> dict[str, sitk.Image]:
    """Head, brain and skull masks for the MNI152 T1 template, on its grid.

    The brain is where the grey plus white matter probability exceeds one half, holes (the ventricles) filled. The
    template has no skull or scalp, so both are modelled from the brain's hull (the brain closed by an 8 mm ball):
    bone from 3 to 9 mm outside the hull, where the T1 is 0, and the head up to 15 mm outside it.

    Returns:
        ``{"head", "brain", "bone"}``: uint8 images (0 or 1) on the T1's grid; bone and brain are disjoint.
    """
    probability = sitk.Cast(_template("gm"), sitk.sitkFloat32) + sitk.Cast(_template("wm"), sitk.sitkFloat32)
    brain = sitk.BinaryFillhole(probability > _BRAIN_PROBABILITY * 255)  # probabilities are stored as 0..255
    hull_mm = _hull_distance(brain)
    near, far = _BONE_FROM_HULL_MM
    # Guard against the 2 mm hull's rounding: bone never takes brain.
    bone = (hull_mm > near) & (hull_mm <= far) & (brain == 0)
    return {"head": hull_mm <= _SCALP_FROM_HULL_MM, "brain": brain, "bone": bone}


def mni152_pseudo_ct(seed: int = 0) -> sitk.Image:
    """A CT-like head on the MNI152 T1's grid: :func:`dpcn_med.synth.pseudo_ct` of the T1 with :func:`mni152_masks`.

    Args:
        seed: seed of the CT noise.

    Returns:
        int16 image in Hounsfield units, same geometry as :func:`mni152_t1`.
    """
    t1, masks = mni152_t1(), mni152_masks()
    # The template's nonzero voxels are brain and CSF: mapped as brain tissue, the CSF gets its own density rather
    # than soft tissue's.
    intracranial = masks["brain"] | (t1 > 0)
    return pseudo_ct(t1, bone=masks["bone"], brain=intracranial, head=masks["head"], seed=seed)


def mni152_head_t1(seed: int = 0) -> sitk.Image:
    """A T1-weighted head on the MNI152 T1's grid: the template's brain with modelled CSF, skull and scalp around it.

    The template is skull-stripped; this gives it the outer layers that a clinical T1 has (dark CSF and bone, bright
    scalp fat) from :func:`mni152_masks`, so that it pairs with :func:`mni152_pseudo_ct` like a real MR with a CT of
    the same head.

    Args:
        seed: seed of the Rician-like noise added to the modelled layers.

    Returns:
        float32 image, same geometry as :func:`mni152_t1`.
    """
    t1, masks = mni152_t1(), mni152_masks()
    brain = sitk.GetArrayFromImage(t1).astype(np.float32)
    head, bone = sitk.GetArrayFromImage(masks["head"]) > 0, sitk.GetArrayFromImage(masks["bone"]) > 0
    intracranial = (brain > 0) | (sitk.GetArrayFromImage(masks["brain"]) > 0)
    white = float(np.percentile(brain[brain > 0], 99))
    # Outside the skull by the hull's distance, as the bone was placed: the distance to bone or brain is positive in
    # the CSF between them too, which would paint it scalp-bright.
    outside_bone = sitk.GetArrayFromImage(_hull_distance(masks["brain"])) > _BONE_FROM_HULL_MM[1]
    layers = np.zeros_like(brain)
    layers[head & ~intracranial] = _T1_RATIOS["csf"] * white
    layers[bone] = _T1_RATIOS["bone"] * white
    layers[head & outside_bone & ~bone & ~intracranial] = _T1_RATIOS["scalp"] * white
    noise = np.random.default_rng(seed).normal(0.0, _T1_NOISE * white, brain.shape).astype(np.float32)
    array = np.where(intracranial, brain, np.abs(layers + noise * head))
    image = sitk.GetImageFromArray(array)
    image.CopyInformation(t1)
    return image
