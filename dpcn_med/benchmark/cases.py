"""The benchmark's pairs: aligned volumes (built-in or under ../shared/data) and the poses that move them."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
"""``../shared/data`` beside the checkout: the real volumes of the cases other than MNI's."""


def _shared(relative: str) -> sitk.Image:
    path = SHARED_DATA / relative
    if not path.exists():
        raise InputError(f"{path}: not found; this case needs ../shared/data beside the checkout")
    return sitk.ReadImage(str(path))


def _seg3d_pseudo_ct() -> tuple[sitk.Image, sitk.Image]:
    from dpcn_med.synth import pseudo_ct

    mr = _shared("seg3d/MR.nii.gz")
    return mr, pseudo_ct(mr, bone=_shared("seg3d/skull_mask.nii.gz"), brain=_shared("seg3d/brain_mask.nii.gz"))


def _mni_pair(moving: str) -> tuple[sitk.Image, sitk.Image]:
    from dpcn_med import samples

    if moving == "mni":
        image = sitk.BinShrink(samples.mni152_t1(), [2, 2, 2])
        return image, image
    return (sitk.BinShrink(samples.mni152_head_t1(), [2, 2, 2]),
            sitk.BinShrink(samples.mni152_pseudo_ct(), [2, 2, 2]))


CASES: dict[str, tuple[str, bool, Callable[[], tuple[sitk.Image, sitk.Image]]]] = {
    "mni": ("MNI152 T1 (2 mm) to itself", True, lambda: _mni_pair("mni")),
    "mni-pseudo-ct": ("MNI152 head T1 to its pseudo-CT (2 mm)", False, lambda: _mni_pair("pseudo-ct")),
    "seg3d": ("seg3d head T1 to itself", True, lambda: (_shared("seg3d/MR.nii.gz"),) * 2),
    "seg3d-pseudo-ct": ("seg3d head T1 to its pseudo-CT", False, _seg3d_pseudo_ct),
    "t1-flair": ("stroke T1 to FLAIR", False, lambda: (_shared("stroke/T1.nii.gz"), _shared("stroke/FLAIR.nii.gz"))),
}
"""name: (description, homogeneous, loader of the aligned ``(fixed, moving)`` images)."""


def rotation_in_bin(rng: np.random.Generator, low: float, high: float, centre: np.ndarray,
                    max_shift_mm: float) -> sitk.VersorRigid3DTransform:
    """A fixed-to-moving rigid transform about ``centre``: angle uniform in ``[low, high)`` degrees about a uniform
    axis, shift of uniform direction and length up to ``max_shift_mm``."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    transform = sitk.VersorRigid3DTransform()
    transform.SetCenter(centre.tolist())
    transform.SetRotation((axis / np.linalg.norm(axis)).tolist(), math.radians(rng.uniform(low, high)))
    transform.SetTranslation((direction / np.linalg.norm(direction) * rng.uniform(0, max_shift_mm)).tolist())
    return transform
