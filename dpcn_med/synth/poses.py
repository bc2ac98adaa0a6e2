"""Known poses in voxel units: the ground truth of synthetic pairs (tests, benchmarks, the demo)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.arguments import check_flag, check_integer, check_pair, check_real
from dpcn_med.geometry import geodesic_distance, random_rotation, rotation_2d, warp


@dataclass
class Pose:
    """A similarity transform in voxel units: ``fixed(p) = moving(scale * rotation @ p + translation)``.

    Attributes:
        rotation: ``(d, d)`` ``fixed_to_moving`` rotation, ``d`` 2 or 3.
        scale: isotropic scale.
        translation: ``(d,)`` voxels ``(x, y[, z])``.
    """

    rotation: Tensor
    scale: float
    translation: Tensor

    def moving_from(self, fixed: Tensor) -> Tensor:
        """The moving grid this pose maps onto ``fixed``: ``moving(q) = fixed(A^-1 (q - t))``, ``A = scale R``.

        Args:
            fixed: ``(B, C, N, N, N)`` or ``(B, C, N, N)``, any device and dtype (the pose's tensors move there).

        Returns:
            Same shape, device and dtype; content leaving the grid is lost, new content is zero.
        """
        inverse = torch.linalg.inv_ex(self.scale * self.rotation.to(fixed)).inverse  # inv: a host sync on CUDA
        offset = -(inverse @ self.translation.to(fixed))
        return warp(fixed, inverse.expand(fixed.shape[0], -1, -1), offset.expand(fixed.shape[0], -1))

    def errors(self, rotation: Tensor, scale: Tensor | float, translation: Tensor) -> tuple[float, float, float]:
        """Errors of an estimate: (rotation in degrees, translation in voxels, relative scale).

        Args:
            rotation: ``(d, d)``.
            scale: scalar.
            translation: ``(d,)``.
        """
        truth = self.rotation.double()
        if truth.shape[-1] == 3:
            angle = geodesic_distance(rotation.double(), truth).item()
        else:
            relative = rotation.double().T @ truth
            angle = abs(math.atan2(relative[1, 0].item(), relative[0, 0].item()))
        return (math.degrees(angle), (translation.double() - self.translation.double()).norm().item(),
                abs(float(scale) / self.scale - 1.0))


def random_poses(count: int, size: int, seed: int, *, similarity: bool = True, dim: int = 3,
                 scale_range: tuple[float, float] = (0.8, 1.2), max_shift: float | None = None) -> list[Pose]:
    """Random poses from a fixed seed.

    Args:
        count: how many, at least 0.
        size: grid size ``N``, at least 1; shifts default to at most ``0.2 N``.
        seed: seed of the generator, in ``[0, 2^63)`` (the same seed gives the same poses).
        similarity: draw a scale in ``scale_range`` (True) or keep 1.
        dim: 3 (rotation uniform over SO(3)) or 2 (angle uniform in ``[0, 2 pi)``).
        scale_range: scale interval, ``0 < low <= high``.
        max_shift: largest shift length in voxels, at least 0 (direction uniform, length uniform in
            ``[0, max_shift]``).

    Returns:
        ``count`` float64 :class:`Pose` objects.

    Raises:
        InputError: an argument is outside the range above, or not finite.
    """
    count = check_integer("count", count, minimum=0)
    size = check_integer("size", size, minimum=1)
    similarity = check_flag("similarity", similarity)
    dim = check_integer("dim", dim, minimum=2, maximum=3)
    scale_range = check_pair("scale_range", scale_range, minimum=0.0, above=True, equal=True)
    generator = torch.Generator().manual_seed(check_integer("seed", seed, minimum=0, maximum=2 ** 63 - 1))
    limit = 0.2 * size if max_shift is None else check_real("max_shift", max_shift, minimum=0.0)
    poses = []
    for _ in range(count):
        if dim == 3:
            rotation = random_rotation(1, generator)[0]
        else:
            rotation = rotation_2d(torch.rand((), generator=generator, dtype=torch.float64) * 2 * math.pi)
        scale = float(torch.empty((), dtype=torch.float64).uniform_(*scale_range, generator=generator)) \
            if similarity else 1.0
        direction = torch.randn(dim, generator=generator, dtype=torch.float64)
        length = float(torch.rand((), generator=generator, dtype=torch.float64)) * limit
        poses.append(Pose(rotation, scale, direction / direction.norm() * length))
    return poses
