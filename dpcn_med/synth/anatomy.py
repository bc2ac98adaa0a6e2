"""New anatomy from old: a random smooth deformation of a base volume, applied before both sides of a pair are made.

A handful of real heads is too few to learn features that carry over to heads never seen (docs/learning.md): the
networks learn the training anatomy. Deforming each base volume (per-axis stretch, shear and a smooth displacement
field) gives every pair a head of its own, while both sides of the pair still share it, so the pose stays exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.arguments import check_integer, check_real
from dpcn_med.geometry import affine_points, sample
from dpcn_med.synth._common import check_volumes, normal, uniform


@dataclass(frozen=True)
class AnatomyConfig:
    """How :func:`deformed_anatomy` reshapes a base volume (all off by default: ``probability`` 0).

    Attributes:
        probability: chance that a base volume is deformed at all.
        stretch: each axis is scaled by a factor uniform in ``[1 - stretch, 1 + stretch]``, about the grid centre.
        shear: each off-diagonal entry of the linear map is uniform in ``[-shear, shear]``.
        displacement: standard deviation, in voxels, of the smooth displacement at the control points.
        control_points: control points per axis of the displacement (trilinear between them); more gives a finer,
            more local deformation.

    Raises:
        InputError: a value out of range.
    """

    probability: float = 0.0
    stretch: float = 0.1
    shear: float = 0.05
    displacement: float = 1.5
    control_points: int = 5

    def __post_init__(self) -> None:
        check_real("probability", self.probability, minimum=0.0, maximum=1.0, note=" (a probability)")
        check_real("stretch", self.stretch, minimum=0.0, maximum=0.5, note=" (a fraction of each axis' length)")
        check_real("shear", self.shear, minimum=0.0, maximum=0.5)
        check_real("displacement", self.displacement, minimum=0.0, note=" (voxels)")
        check_integer("control_points", self.control_points, minimum=2)


def deformed_anatomy(volumes: Tensor, generator: torch.Generator, config: AnatomyConfig = AnatomyConfig()
                     ) -> Tensor:
    """Each volume of a batch, deformed with probability ``config.probability`` (the others returned unchanged).

    The map is ``out(p) = volume(M p + u(p))``, ``p`` voxels ``(x, y, z)`` from the grid centre (the convention of
    :mod:`dpcn_med.geometry`, whose resampling it uses): ``M`` a random stretch-and-shear near the identity, ``u`` a
    displacement drawn at ``control_points^3`` control points and interpolated trilinearly; trilinear resampling,
    zero outside the grid, so intensities stay in the input's range.

    Written here rather than with MONAI's ``Rand3DElastic``: it deforms a whole batch at once on the training device
    and draws from the run's torch generator, so a run stays reproducible and resumable on any device.

    Args:
        volumes: ``(B, 1, D, H, W)`` float32 or float64.
        generator: source of randomness (any device).
        config: how much to deform.

    Returns:
        ``(B, 1, D, H, W)`` on ``volumes``' device and dtype.

    Raises:
        InputError: ``volumes`` is not a floating batch of volumes.
    """
    check_volumes("volumes", volumes)
    batch, sizes = volumes.shape[0], volumes.shape[2:]
    if config.probability == 0.0:  # no draws: the generator's stream, and every run made before, stay as they were
        return volumes
    chosen = uniform(generator, (batch,), 0.0, 1.0, like=volumes) < config.probability
    linear = torch.eye(3, dtype=volumes.dtype, device=volumes.device).repeat(batch, 1, 1)
    linear = linear * uniform(generator, (batch, 3, 1), 1.0 - config.stretch, 1.0 + config.stretch, like=volumes)
    off_diagonal = 1.0 - torch.eye(3, dtype=volumes.dtype, device=volumes.device)
    linear = linear + off_diagonal * uniform(generator, (batch, 3, 3), -config.shear, config.shear, like=volumes)
    points = affine_points(tuple(sizes), linear)  # (B, D, H, W, 3) voxels (x, y, z) from the grid centre
    count = config.control_points
    coarse = normal(generator, (batch, 3, count, count, count), like=volumes) * config.displacement
    points = points + F.interpolate(coarse, size=tuple(sizes), mode="trilinear", align_corners=True
                                    ).permute(0, 2, 3, 4, 1)
    deformed = sample(volumes, points)
    return torch.where(chosen[:, None, None, None, None], deformed, volumes)
