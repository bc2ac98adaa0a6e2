"""CT-like volumes in Hounsfield units simulated from a T1 MR and tissue masks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from dpcn_med.arguments import check_integer, check_real, check_sequence
from dpcn_med.errors import InputError
from dpcn_med.preprocess import foreground_mask, normalize_intensity


@dataclass(frozen=True)
class CTTissues:
    """Hounsfield units and acquisition of a pseudo-CT; the defaults are typical of a head CT.

    Attributes:
        air: outside the head.
        soft_tissue: HU of the darkest and of the brightest MR in the head outside brain and bone (on T1 the
            brightest is fat, the least dense).
        csf, grey_matter, white_matter: HU of the brain's tissues.
        t1_ratios: T1 intensities of CSF, grey and white matter relative to white matter, the anchors of the
            brain's intensity map (T1 contrast assumed): positive and increasing.
        bone_surface, bone_core: HU of cortical bone on the surface voxels of the bone mask and deep inside it
            (diploe).
        cortex_mm: depth in mm over which bone falls from ``bone_surface`` to ``bone_core`` (e-folding), above 0.
        blur_mm: Gaussian sigma of the scanner's resolution, mm, at least 0.
        noise_hu: standard deviation of the added white noise, HU, at least 0.
    """

    air: float = -1000.0
    soft_tissue: tuple[float, float] = (60.0, 20.0)
    csf: float = 10.0
    grey_matter: float = 40.0
    white_matter: float = 25.0
    t1_ratios: tuple[float, float, float] = (0.3, 0.75, 1.0)
    bone_surface: float = 1800.0
    bone_core: float = 750.0
    cortex_mm: float = 1.5
    blur_mm: float = 0.6
    noise_hu: float = 10.0

    def __post_init__(self) -> None:
        """Refuse what would make a blank or wrong CT (docs/design_notes/synth.md), naming the field.

        Raises:
            InputError: a value that is not finite or out of its range, or T1 ratios not increasing.
        """
        for name in ("air", "csf", "grey_matter", "white_matter", "bone_surface", "bone_core"):
            check_real(name, getattr(self, name))
        for index, value in enumerate(check_sequence("soft_tissue", self.soft_tissue, length=2)):
            check_real(f"soft_tissue[{index}]", value)
        ratios = tuple(check_real(f"t1_ratios[{index}]", value, minimum=0.0, above=True)
                       for index, value in enumerate(check_sequence("t1_ratios", self.t1_ratios, length=3)))
        if not ratios[0] < ratios[1] < ratios[2]:  # np.interp needs increasing anchors
            raise InputError(f"t1_ratios is {ratios!r}; expected CSF < grey matter < white matter (T1 contrast)")
        check_real("cortex_mm", self.cortex_mm, minimum=0.0, above=True)
        check_real("blur_mm", self.blur_mm, minimum=0.0)
        check_real("noise_hu", self.noise_hu, minimum=0.0)


HEAD_CT = CTTissues()

# CT scanners store HU as int16 from -1024 (the air calibration floor) up.
_HU_RANGE = (-1024, 3071)


def _mask_array(name: str, mask: sitk.Image, mr: sitk.Image) -> np.ndarray:
    """A mask as a boolean ``[z, y, x]`` array, after checking that it lies on the MR's grid."""
    same_grid = (mask.GetSize() == mr.GetSize() and np.allclose(mask.GetSpacing(), mr.GetSpacing(), atol=1e-4)
                 and np.allclose(mask.GetOrigin(), mr.GetOrigin(), atol=1e-3)
                 and np.allclose(mask.GetDirection(), mr.GetDirection(), atol=1e-5))
    if not same_grid:
        raise InputError(f"{name} mask (size {mask.GetSize()}, origin {mask.GetOrigin()}) is not on the MR's grid "
                         f"(size {mr.GetSize()}, origin {mr.GetOrigin()}); resample it onto the MR with "
                         "nearest-neighbour interpolation first")
    return sitk.GetArrayViewFromImage(mask) > 0


def _white_matter_level(brain_values: np.ndarray) -> float:
    """Median of the brightest of three Otsu classes (CSF, grey, white matter on T1) of the brain's intensities."""
    otsu = sitk.OtsuMultipleThresholdsImageFilter()
    otsu.SetNumberOfThresholds(2)
    # Otsu takes no mask: threshold the brain's voxels alone, as a one-row image.
    otsu.Execute(sitk.GetImageFromArray(brain_values[None, None, :]))
    brightest = brain_values[brain_values > otsu.GetThresholds()[-1]]
    return float(np.median(brightest)) if brightest.size else float(brain_values.max())


def pseudo_ct(mr: sitk.Image, *, bone: sitk.Image, brain: sitk.Image | None = None, head: sitk.Image | None = None,
              seed: int = 0, tissues: CTTissues = HEAD_CT) -> sitk.Image:
    """A CT-like volume in Hounsfield units simulated from a T1 MR and tissue masks on its grid.

    Air outside the head; soft tissue whose density falls as the MR brightens (fat); in the brain a non-monotonic
    map of the MR (CSF dark, grey matter denser than white matter although darker on T1); bone brightest at the
    surface of its mask (cortical) and darker inside (diploe); then the scanner's blur and noise. Bone is bright
    where the MR is dark, as in real CT-MR pairs.

    Args:
        mr: 3-D T1-weighted MR, any pixel type; magnitude image (no signal is 0).
        bone: binary mask of the skull (nonzero is bone) on the MR's grid.
        brain: binary brain mask on the MR's grid; without it the brain is treated as soft tissue.
        head: binary head mask on the MR's grid; defaults to :func:`dpcn_med.preprocess.foreground_mask` of ``mr``.
        seed: seed of the noise, at least 0 (the same seed gives the same image).
        tissues: Hounsfield units and acquisition.

    Returns:
        int16 image in HU with the MR's size, origin, spacing and direction.

    Raises:
        InputError: ``mr`` is not a 3-D scalar volume, a mask is not on its grid, the MR is not positive in the
            brain mask, or ``seed`` is not an integer >= 0.
    """
    seed = check_integer("seed", seed, minimum=0)
    if mr.GetDimension() != 3 or mr.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"mr is a {mr.GetDimension()}-D image with {mr.GetNumberOfComponentsPerPixel()} components "
                         "per voxel; expected a 3-D scalar volume")
    head = foreground_mask(mr) if head is None else head
    bone_mask = _mask_array("bone", bone, mr)
    brain_mask = (np.zeros_like(bone_mask) if brain is None else _mask_array("brain", brain, mr)) & ~bone_mask
    # Brain and bone belong to the head even where a foreground mask misses them (an MR whose field of view cuts
    # the head leaves its dark skull and CSF open to the border, and hole filling cannot close them).
    head_mask = _mask_array("head", head, mr) | bone_mask | brain_mask
    scaled = sitk.GetArrayFromImage(normalize_intensity(mr, mask=head))
    hu = np.full(scaled.shape, tissues.air, dtype=np.float32)
    hu[head_mask] = np.interp(scaled[head_mask], (0.0, 1.0), tissues.soft_tissue)
    values = sitk.GetArrayViewFromImage(mr)[brain_mask].astype(np.float32)
    if values.size:
        level = _white_matter_level(values)
        if not level > 0:  # values / 0 was NaN, blurred over the skull and cast to 0 HU without a word
            raise InputError(f"brain mask: the MR's white matter level inside it is {level:g}; expected a positive "
                             "T1 magnitude (is the mask on the MR's background, or the MR not a magnitude image?)")
        hu[brain_mask] = np.interp(values / level, tissues.t1_ratios,
                                   (tissues.csf, tissues.grey_matter, tissues.white_matter))
    # Depth below the surface voxels, from the distance to the nearest voxel outside the bone: Maurer's values inside
    # a mask are distances to its 26-connected surface voxels, which leave almost no inside to a thin shell.
    # Squared distances skip a square root over the whole volume.
    outside_squared = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(
        bone == 0, insideIsPositive=False, squaredDistance=True, useImageSpacing=True))
    depth_mm = np.sqrt(outside_squared[bone_mask]) - min(mr.GetSpacing())
    hu[bone_mask] = tissues.bone_core + (tissues.bone_surface - tissues.bone_core) * np.exp(
        -depth_mm / tissues.cortex_mm)
    # scipy's truncated kernel is several times faster here than SimpleITK's Gaussian filters.
    blurred = ndimage.gaussian_filter(hu, tissues.blur_mm / np.asarray(mr.GetSpacing())[::-1], truncate=3.0)
    blurred += tissues.noise_hu * np.random.default_rng(seed).standard_normal(blurred.shape, dtype=np.float32)
    ct = sitk.GetImageFromArray(np.clip(np.rint(blurred), *_HU_RANGE).astype(np.int16))
    ct.CopyInformation(mr)
    return ct
