"""Built-in sample volumes that need no download: the MNI152 2009a templates shipped inside the nilearn wheel."""

from __future__ import annotations

import SimpleITK as sitk


def mni152_t1() -> sitk.Image:
    """The MNI152 ICBM 2009a symmetric T1 template at 1 mm (197 x 233 x 189), as a SimpleITK image in LPS.

    Fonov et al., NeuroImage 2011; redistributed with nilearn under its licence.
    """
    from nilearn.datasets import MNI152_FILE_PATH  # imported here: nilearn takes seconds to import

    return sitk.ReadImage(str(MNI152_FILE_PATH))
