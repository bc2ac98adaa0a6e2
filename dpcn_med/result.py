"""What a registration found: :class:`RegistrationResult`, and transforms described as JSON."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med.geometry import CanonicalGrid, homogeneous_matrix, rotation_angle, scale_and_rotation

SIMILARITY_NAMES = {"mattes": "Mattes mutual information", "lc2": "LC2 (linear correlation of linear combination)"}
"""What the refinement's similarity is, by :attr:`RegistrationResult.similarity`, in words."""

SIMILARITY_KEYS = {"mattes": "mattes_mutual_information", "lc2": "negative_lc2"}
"""The report's key of its values (``candidate_`` before it for the candidates'): the key names what they are."""


@dataclass
class RegistrationResult:
    """What :func:`register` found.

    Attributes:
        fixed_to_moving: the final transform (refined unless refinement was off or did not improve the metric), LPS
            mm, fixed points to moving points: ``sitk.Resample(moving, fixed, fixed_to_moving)`` aligns them. A
            ``VersorRigid3DTransform`` (rigid) or ``Similarity3DTransform`` (similarity), centred at the fixed grid's
            centre.
        moving_to_fixed: its inverse.
        dpc_transform: the start that the refinement kept (before refinement): a global estimate, or the identity
            when ``start`` is ``"stored pose"``.
        confidence: the solver's confidence in that start, in ``[0, 1]``: the mass of its translation peak (for the
            stored pose, of the translation correlation at the stored orientation, :func:`stored_pose_confidence`).
        candidate: which start that is, chosen by :func:`dpcn_med.refine.refine_candidates`: 0 for the solver's own
            choice, ``k`` for its ``k``-th runner-up; the stored pose is the last (``len(candidate_metrics) - 1``).
        start: ``"phase correlation"`` (one of the solver's candidates) or ``"stored pose"``
            (:attr:`dpcn_med.refine.Refinement.stored_start`).
        candidate_metrics: each start's metric after the coarsest refinement level, on that level's images (empty
            without refinement), in the order of ``candidate``.
        mode: ``"rigid"`` or ``"similarity"``.
        bandwidth: ``B``; the canonical grids are ``(2B)^3``.
        fixed_grid: canonical cube of the fixed volume.
        moving_grid: canonical cube of the moving volume (same spacing).
        modalities: ``(fixed, moving)`` modality used for intensity normalisation.
        metric: the refinement's similarity (lower is better: Mattes mutual information with SimpleITK's sign, or
            ``-LC2`` where one image is ultrasound; ``similarity`` says which) at ``"stored"`` (identity), ``"dpc"``
            and ``"refined"`` (``None`` without refinement, or where the pose leaves no overlap).
        refined: whether ``fixed_to_moving`` is the refined transform.
        overlap: share of the fixed foreground that ``fixed_to_moving`` maps inside the moving image's field of view
            (:func:`field_of_view_overlap`).
        similarity: ``"mattes"`` or ``"lc2"`` (:data:`SIMILARITY_NAMES`).
        fixed_entropy: entropy (nats) of the fixed samples over the metric's bins, the scale of ``metric`` (``None``
            without refinement).
        success_probability: how likely the result is right, by the quality model
            (:func:`dpcn_med.quality.shipped_model`; ``None`` without refinement).
        timings: wall-clock seconds per step (``read``, ``preprocess``, ``solve``, ``refine``, ``resample``) and
            per solver stage (``solver.*``).
        device: the torch device the solver ran on.
        model: ``"learning-free"`` or the path of the learned model used.
        fixed_image: the fixed input as read.
        moving_image: the moving input as read.
        resampled: the moving image on the fixed grid, when asked for.
        fixed_foreground, moving_foreground: the foregrounds preprocessing found (binary, within a user's mask), on
            each input's grid or a coarser one over the same space.
    """

    fixed_to_moving: sitk.Transform
    moving_to_fixed: sitk.Transform
    dpc_transform: sitk.Transform
    confidence: float
    mode: str
    bandwidth: int
    fixed_grid: CanonicalGrid
    moving_grid: CanonicalGrid
    modalities: tuple[str, str]
    metric: dict[str, float | None]
    refined: bool
    candidate: int = 0
    start: str = "phase correlation"
    candidate_metrics: list[float | None] = field(default_factory=list)
    overlap: float = 1.0
    fixed_entropy: float | None = None
    similarity: str = "mattes"
    success_probability: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    device: str = "cpu"
    model: str = "learning-free"
    fixed_image: sitk.Image | None = None
    moving_image: sitk.Image | None = None
    resampled: sitk.Image | None = None
    fixed_foreground: sitk.Image | None = None
    moving_foreground: sitk.Image | None = None

    def to_dict(self) -> dict:
        """JSON-ready summary: both estimates as 4x4 matrices and parameters, confidence, metric, timings."""
        return {
            "mode": self.mode, "bandwidth": self.bandwidth, "device": self.device, "model": self.model,
            "confidence": self.confidence, "modalities": {"fixed": self.modalities[0], "moving": self.modalities[1]},
            "canonical_grid": {"size": self.fixed_grid.size, "spacing_mm": self.fixed_grid.spacing,
                               "fixed_centre_lps": list(self.fixed_grid.centre),
                               "moving_centre_lps": list(self.moving_grid.centre)},
            "dpc": describe_transform(self.dpc_transform),
            "final": describe_transform(self.fixed_to_moving),
            "refined": self.refined, "candidate": self.candidate, "start": self.start,
            "similarity": SIMILARITY_NAMES[self.similarity],
            f"candidate_{SIMILARITY_KEYS[self.similarity]}": self.candidate_metrics, "overlap_fraction": self.overlap,
            SIMILARITY_KEYS[self.similarity]: self.metric, "fixed_entropy_nats": self.fixed_entropy,
            "success_probability": self.success_probability,
            "timings_s": self.timings,
        }


def describe_transform(fixed_to_moving: sitk.Transform) -> dict:
    """A transform as JSON: ITK name, parameters, centre, the 4x4 LPS matrix, its rotation angle, scale and
    ``translation_mm``, the matrix's offset (where the LPS origin goes; ITK's translation parameters are about the
    centre)."""
    matrix = homogeneous_matrix(fixed_to_moving)
    scale, rotation = scale_and_rotation(matrix[:3, :3])
    angle = float(np.degrees(rotation_angle(torch.from_numpy(rotation)).item()))
    return {"type": fixed_to_moving.GetName(), "parameters": list(fixed_to_moving.GetParameters()),
            "fixed_parameters": list(fixed_to_moving.GetFixedParameters()),
            "fixed_to_moving_lps": matrix.tolist(), "rotation_degrees": angle, "scale": scale,
            "translation_mm": matrix[:3, 3].tolist()}
