"""Synthetic data with exact ground truth: known poses, simulated modalities and training pairs.

====================== ====================================================================================
module                 contents
====================== ====================================================================================
``poses``              :class:`Pose`, :func:`random_poses`: known similarity transforms in voxel units
``pseudo_ct``          :func:`pseudo_ct`: a CT in Hounsfield units from a T1 MR and tissue masks (SimpleITK)
``contrast``           random intensity maps, bias field, blur, thick slices, noise: :func:`random_modality`
``ultrasound``         :func:`simulated_ultrasound`: 3-D ultrasound from a CT-like volume
``ultrasound_image``   :func:`ultrasound_image`: the same from a CT image, in its physical space, through a craniotomy
``anatomy``            :func:`deformed_anatomy`: a random smooth deformation of a base volume (new heads)
``pairs``              :func:`synthetic_pairs`: fixed, moving and their :class:`~dpcn_med.solver.PoseTarget`
====================== ====================================================================================

The torch modules (``contrast``, ``ultrasound``, ``anatomy``, ``pairs``) work on batches ``(B, 1, N, N, N)`` on any
device and draw from a ``torch.Generator``, so a seed reproduces a batch.
"""

from dpcn_med.synth.anatomy import AnatomyConfig, deformed_anatomy
from dpcn_med.synth.contrast import (
    ContrastConfig,
    bias_field,
    blur,
    noise,
    random_intensity_map,
    random_modality,
    resolution_loss,
)
from dpcn_med.synth.pairs import PAIR_MODALITIES, PairConfig, slab_mask, synthetic_pairs
from dpcn_med.synth.poses import Pose, random_poses
from dpcn_med.synth.pseudo_ct import HEAD_CT, CTTissues, pseudo_ct
from dpcn_med.synth.ultrasound import UltrasoundConfig, simulated_ultrasound
from dpcn_med.synth.ultrasound_image import Craniotomy, ultrasound_image

__all__ = ["HEAD_CT", "PAIR_MODALITIES", "AnatomyConfig", "CTTissues", "ContrastConfig", "Craniotomy", "PairConfig",
           "Pose", "UltrasoundConfig", "bias_field", "blur", "deformed_anatomy", "noise", "pseudo_ct",
           "random_intensity_map", "random_modality", "random_poses", "resolution_loss", "simulated_ultrasound",
           "slab_mask", "synthetic_pairs", "ultrasound_image"]
