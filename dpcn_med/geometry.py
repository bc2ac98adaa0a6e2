"""Frames, rotations and resampling: the one home of the project's conventions.

Conventions (everything else imports them from here):

* **Volumes.** Torch volumes are ``(B, C, D, H, W)`` = ``(.., z, y, x)``; images are ``(B, C, H, W)`` =
  ``(.., y, x)``. A numpy array of a SimpleITK image is indexed ``[z, y, x]`` as well.
* **Voxel coordinates.** A point ``p`` is written ``(x, y, z)`` (``(x, y)`` in 2-D), in voxels, measured from the grid
  centre, the voxel of index ``size // 2`` along every axis. That is also where ``torch.fft.fftshift`` puts the zero
  frequency, so rotations of a volume and of its spectrum share one centre.
* **Rotations.** Active rotation matrices acting on column vectors ``(x, y, z)``. Euler angles are ZYZ:
  ``R = Rz(alpha) @ Ry(beta) @ Rz(gamma)``, ``alpha, gamma`` in ``[0, 2 pi)``, ``beta`` in ``[0, pi]``.
* **Resampling direction.** :func:`warp` pulls: ``out(p) = volume(matrix @ p + translation)``. The solver's contract
  ``fixed(p) ~ moving(scale * rotation @ p + translation)`` therefore reads ``fixed ~ warp(moving, scale * rotation,
  translation)``: the matrix maps fixed voxels to moving voxels (``fixed_to_moving``), ITK's direction.
* **Physical space.** ITK's LPS, in millimetres. A registration result is a SimpleITK transform ``fixed_to_moving``
  mapping fixed physical points to moving ones, so ``sitk.Resample(moving, fixed, fixed_to_moving)`` puts the
  moving image on the fixed grid. A solver pose ``v = mu R u + tau`` on two canonical grids (voxel offsets ``u``,
  ``v`` from the fixed and moving grid centres ``c_f``, ``c_m``, shared spacing ``h``) is the physical
  ``T(x) = mu R (x - c_f) + c_m + h tau`` (:func:`physical_transform`).
* **Slicer.** Slicer models in RAS: a transform node's to-parent matrix is ``inv(F T F)`` with
  ``F = diag(-1, -1, 1, 1)`` (:func:`slicer_to_parent_ras`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.arguments import check_integer, check_real, check_sequence
from dpcn_med.errors import InputError

RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""Homogeneous ``(4, 4)`` change of frame from RAS to LPS."""

LPS_TO_RAS = RAS_TO_LPS
"""Homogeneous ``(4, 4)`` change of frame from LPS to RAS: the same flip, its own inverse."""

SIMILARITY_TOLERANCE = 1e-4
"""Relative spread of singular values (and, for a rigid transform, deviation of the scale from 1) still taken for a
similarity (why this value: docs/design_notes/geometry.md)."""


def grid_centre(size: int) -> int:
    """Index of the grid centre along an axis of ``size`` voxels (the zero frequency after ``fftshift``)."""
    return size // 2


@dataclass(frozen=True)
class CanonicalGrid:
    """The solver's grid in physical space: a cube of ``size^3`` voxels, isotropic ``spacing`` (mm), identity
    direction, voxel ``size // 2`` at ``centre`` (LPS, mm).

    Both volumes of a pair share ``size`` and ``spacing``, so a rotation of the grid is a rotation in LPS space and a
    scale is physical; the centres differ (each volume's foreground centre).
    """

    size: int
    spacing: float
    centre: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", check_integer("size", self.size, minimum=2))
        object.__setattr__(self, "spacing", check_real("spacing", self.spacing, minimum=0.0, above=True))
        object.__setattr__(self, "centre", tuple(check_real(f"centre[{axis}]", value) for axis, value
                                                 in enumerate(check_sequence("centre", self.centre, length=3))))

    @property
    def origin(self) -> tuple[float, float, float]:
        """Physical position (LPS, mm) of voxel ``(0, 0, 0)``, as SimpleITK's ``origin``."""
        offset = grid_centre(self.size) * self.spacing
        return tuple(c - offset for c in self.centre)


def rotation_z(angle: Tensor) -> Tensor:
    """Rotation about z by ``angle``: ``(...,)`` radians -> ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1).unflatten(-1, (3, 3))


def rotation_y(angle: Tensor) -> Tensor:
    """Rotation about y by ``angle``: ``(...,)`` radians -> ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1).unflatten(-1, (3, 3))


def rotation_2d(angle: Tensor) -> Tensor:
    """Counter-clockwise rotation of ``(x, y)`` by ``angle``: ``(...,)`` radians -> ``(..., 2, 2)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack([c, -s, s, c], dim=-1).unflatten(-1, (2, 2))


def euler_zyz_to_matrix(angles: Tensor) -> Tensor:
    """ZYZ Euler angles to rotation matrices.

    Args:
        angles: ``(..., 3)`` radians ``(alpha, beta, gamma)``.

    Returns:
        ``(..., 3, 3)`` active rotations ``Rz(alpha) @ Ry(beta) @ Rz(gamma)``.
    """
    alpha, beta, gamma = angles.unbind(-1)
    return rotation_z(alpha) @ rotation_y(beta) @ rotation_z(gamma)


def matrix_to_euler_zyz(rotation: Tensor) -> Tensor:
    """Inverse of :func:`euler_zyz_to_matrix`.

    Args:
        rotation: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` angles, ``alpha, gamma`` in ``[0, 2 pi)`` and ``beta`` in ``[0, pi]``. At the gimbal poles
        (``beta`` 0 or ``pi``) only ``alpha +- gamma`` is defined; ``gamma`` is then set to 0.
    """
    r = rotation
    sin_beta = torch.sqrt(r[..., 0, 2] ** 2 + r[..., 1, 2] ** 2)
    beta = torch.atan2(sin_beta, r[..., 2, 2])  # accurate near the poles, where acos(r22) loses half the digits
    # alpha from (r02, r12) = sin beta (cos alpha, sin alpha); gamma from alpha + gamma (towards beta = 0) or
    # alpha - gamma (towards pi), read from the upper-left block, where they come times (1 +- cos beta): exact where
    # the rotation depends on them. Read from r20, r21, as sin beta times rounding near a pole, gamma was up to 180
    # degrees off (identity with r02 = 1e-8; products of float32 rotations).
    alpha = torch.atan2(r[..., 1, 2], r[..., 0, 2])
    total = torch.atan2(r[..., 1, 0] - r[..., 0, 1], r[..., 0, 0] + r[..., 1, 1])
    difference = torch.atan2(-r[..., 1, 0] - r[..., 0, 1], r[..., 1, 1] - r[..., 0, 0])
    gamma = torch.where(r[..., 2, 2] >= 0, total - alpha, alpha - difference)
    regular = sin_beta > 1e-12
    alpha = torch.where(regular, alpha, torch.atan2(r[..., 1, 0], r[..., 0, 0]))
    gamma = torch.where(regular, gamma, torch.zeros_like(beta))
    # At beta = pi, R = Rz(alpha) diag(-1, 1, -1) Rz(gamma); with gamma = 0, alpha = atan2(-r10, -r00).
    at_south = (~regular) & (r[..., 2, 2] < 0)
    alpha = torch.where(at_south, torch.atan2(-r[..., 1, 0], -r[..., 0, 0]), alpha)
    two_pi = 2 * math.pi
    return torch.stack([torch.remainder(alpha, two_pi), beta, torch.remainder(gamma, two_pi)], dim=-1)


def skew(vector: Tensor) -> Tensor:
    """Cross-product matrices: ``(..., 3)`` -> ``(..., 3, 3)`` with ``skew(v) @ w = v x w``."""
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).unflatten(-1, (3, 3))


def axis_angle_to_matrix(rotation_vector: Tensor) -> Tensor:
    """Rotation vectors (axis times angle in radians) ``(..., 3)`` to matrices ``(..., 3, 3)``."""
    return torch.linalg.matrix_exp(skew(rotation_vector))


def rotation_angle(rotation: Tensor) -> Tensor:
    """Angle in radians of rotations ``(..., 3, 3)`` -> ``(...,)``, in ``[0, pi]``.

    Uses ``atan2(|R - R^T| / 2, (trace - 1) / 2)``, accurate at small and large angles alike (``acos`` of the trace
    loses half the digits near 0).
    """
    trace = rotation.diagonal(dim1=-2, dim2=-1).sum(-1)
    antisym = rotation - rotation.transpose(-1, -2)
    sin_norm = torch.stack([antisym[..., 2, 1], antisym[..., 0, 2], antisym[..., 1, 0]], -1).norm(dim=-1) / 2
    return torch.atan2(sin_norm, (trace - 1) / 2)


def geodesic_distance(rotation_a: Tensor, rotation_b: Tensor) -> Tensor:
    """Angle in radians of ``rotation_a^T @ rotation_b`` (both ``(..., 3, 3)``) -> ``(...,)``."""
    return rotation_angle(rotation_a.transpose(-1, -2) @ rotation_b)


@functools.lru_cache(maxsize=8)
def half_turns(device: torch.device, dtype: torch.dtype) -> Tensor:
    """The identity and the 180-degree rotations about x, y and z: ``(4, 3, 3)``, cached per device and dtype."""
    signs = ((1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))
    return torch.stack([torch.diag(torch.tensor(d, dtype=dtype)) for d in signs]).to(device)


def random_rotation(count: int, generator: torch.Generator | None = None, *, dtype: torch.dtype = torch.float64
                    ) -> Tensor:
    """Rotations drawn uniformly (Haar measure) over SO(3): ``(count, 3, 3)``.

    Normalised Gaussian quaternions are uniform on the 3-sphere, hence Haar-uniform on SO(3).
    """
    q = torch.randn(count, 4, generator=generator, dtype=torch.float64)
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    matrix = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], dim=-1).unflatten(-1, (3, 3))
    return matrix.to(dtype)


def project_to_rotation(matrix: Tensor, iterations: int = 12) -> Tensor:
    """Nearest orthogonal matrix to ``matrix`` ``(..., d, d)`` by Newton's polar iteration ``X <- (X + X^-T) / 2``.

    The result keeps the sign of the determinant: it is a rotation when ``det(matrix) > 0``, as for a weighted mean of
    nearby rotations, the use here (why not an SVD: docs/design_notes/geometry.md).

    References:
        Higham, "Computing the polar decomposition, with applications", SIAM J. Sci. Stat. Comput. 1986.
    """
    x = matrix
    for _ in range(iterations):
        # inv_ex, not inv: inv checks for singular input, a host sync on CUDA at each of the iterations.
        x = 0.5 * (x + torch.linalg.inv_ex(x).inverse.transpose(-1, -2))
    return x


def voxel_to_normalized(points: Tensor, sizes: tuple[int, ...]) -> Tensor:
    """Voxel coordinates from the grid centre to ``grid_sample``'s normalised ones (``align_corners=True``).

    Args:
        points: ``(..., d)`` coordinates ``(x, y[, z])`` in voxels from the grid centre.
        sizes: the grid's shape in torch order, ``(D, H, W)`` or ``(H, W)``.

    Returns:
        ``(..., d)`` normalised coordinates in ``[-1, 1]`` inside the grid.
    """
    # Per axis with Python scalars: a small tensor built from a list would be a host-to-device copy on CUDA.
    sizes_xyz = sizes[::-1]
    return torch.stack([(points[..., i] + grid_centre(n)) * (2.0 / (n - 1)) - 1.0 for i, n in enumerate(sizes_xyz)],
                       dim=-1)


def squared_distance_from_centre(sizes: tuple[int, ...], *, device: torch.device | None = None,
                                 dtype: torch.dtype | None = None) -> Tensor:
    """``|p|^2`` of every voxel, ``p`` from the grid centre: ``sizes``-shaped (a broadcast sum, no coordinate grid)."""
    return sum(((torch.arange(n, device=device, dtype=dtype) - grid_centre(n)) ** 2).reshape(
        [-1 if a == axis else 1 for a in range(len(sizes))]) for axis, n in enumerate(sizes))


def sample_points(volume: Tensor, grid: Tensor, *, mode: str = "bilinear", padding_mode: str = "zeros") -> Tensor:
    """``grid_sample`` (``align_corners=True``) of one volume ``(1, C, D, H, W)`` at ``grid`` ``(M, 3)`` normalised
    points ``(x, y, z)``: ``(C, M)``, the same values as one ``grid_sample`` call, bit for bit.

    On the CPU the points are split into one chunk per torch thread, each sampled against a stride-0 view of the
    volume (no copy): PyTorch's CPU ``grid_sample`` parallelises over the batch only (the measurements:
    docs/design_notes/geometry.md). Differentiable in ``grid`` (and in ``volume``, whose gradient then sums over the
    chunks)."""
    count = len(grid)
    chunks = max(1, min(torch.get_num_threads() if volume.device.type == "cpu" else 1, count))
    per_chunk = -(-count // chunks)
    if per_chunk * chunks != count:  # the last chunk padded with copies of the last point, dropped below
        grid = torch.cat([grid, grid[-1:].expand(per_chunk * chunks - count, 3)])
    values = F.grid_sample(volume.expand(chunks, *volume.shape[1:]), grid.reshape(chunks, 1, 1, per_chunk, 3),
                           mode=mode, padding_mode=padding_mode, align_corners=True)
    return values[:, :, 0, 0].transpose(0, 1).reshape(volume.shape[1], -1)[:, :count]


def _grid_sample(volume: Tensor, grid: Tensor) -> Tensor:
    """``grid_sample`` (trilinear, zero outside) at normalised coordinates ``grid (B, *S, d)`` -> ``(B, C, *S)``."""
    dim = volume.dim() - 2
    batch, sample_shape = grid.shape[0], grid.shape[1:-1]
    if batch == 1 and dim == 3:  # one volume: its points split over the CPU's threads
        return sample_points(volume, grid.reshape(-1, dim)).reshape(1, volume.shape[1], *sample_shape)
    grid = grid.reshape(batch, -1, *([1] * (dim - 1)), dim)
    values = F.grid_sample(volume, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return values.reshape(batch, volume.shape[1], *sample_shape)


def sample(volume: Tensor, points: Tensor) -> Tensor:
    """Values of a volume at arbitrary voxel coordinates, by (tri)linear interpolation, zero outside.

    Args:
        volume: ``(B, C, D, H, W)`` or ``(B, C, H, W)``.
        points: ``(B, *S, d)`` voxel coordinates ``(x, y[, z])`` from the grid centre, any sample shape ``S``; moved
            to the volume's device and dtype, as :func:`warp` does.

    Returns:
        ``(B, C, *S)`` values.
    """
    points = points.to(device=volume.device, dtype=volume.dtype)
    return _grid_sample(volume, voxel_to_normalized(points, tuple(volume.shape[2:])))


def affine_points(sizes: tuple[int, ...], matrix: Tensor, translation: Tensor | None = None) -> Tensor:
    """Images of every voxel under ``p -> matrix @ p + translation``.

    Args:
        sizes: grid shape in torch order, ``(D, H, W)`` or ``(H, W)``.
        matrix: ``(B, *K, d, d)`` acting on ``(x, y[, z])``.
        translation: ``(B, *K, d)`` voxels, or ``None``.

    Returns:
        ``(B, *K, *sizes, d)`` voxel coordinates, ready for :func:`sample`.
    """
    dim = len(sizes)
    lead = matrix.shape[:-2]
    mapped = translation.reshape(*lead, *([1] * dim), dim) if translation is not None else 0.0
    # Sum of one broadcast term per axis: the same as matrix @ p for every voxel, without materialising p.
    for axis, n in enumerate(sizes):  # torch axis order; coordinate index dim - 1 - axis
        ticks = torch.arange(n, device=matrix.device, dtype=matrix.dtype) - grid_centre(n)
        column = matrix[..., :, dim - 1 - axis]  # (*lead, d)
        shape = [n if a == axis else 1 for a in range(dim)]
        mapped = mapped + ticks.reshape(*shape, 1) * column.reshape(*lead, *([1] * dim), dim)
    return mapped


def warp(volume: Tensor, matrix: Tensor, translation: Tensor | None = None) -> Tensor:
    """Resample a volume under an affine map of voxel coordinates: ``out(p) = volume(matrix @ p + translation)``.

    Args:
        volume: ``(B, C, D, H, W)`` (or ``(B, C, H, W)`` for 2-D).
        matrix: ``(B, *K, d, d)`` ``fixed_to_moving`` linear part, acting on ``(x, y[, z])``; ``K`` optional
            extra axes (one resampled volume per entry, e.g. per candidate). Moved to ``volume``'s device and dtype,
            as is ``translation``.
        translation: ``(B, *K, d)`` voxels, or ``None`` for zero.

    Returns:
        ``(B, C, *K, *S)`` on ``volume``'s device and dtype, ``S`` its spatial shape; trilinear (bilinear)
        interpolation, zero outside the input grid.

    Convention:
        Pull resampling about the grid centre, as in the module docstring.
    """
    sizes = tuple(volume.shape[2:])
    matrix = matrix.to(volume)
    translation = matrix.new_zeros(matrix.shape[:-1]) if translation is None else translation.to(volume)
    # Fold grid_sample's normalisation into the map (per axis, with Python scalars): the grid comes out normalised in
    # one pass instead of three over every voxel.
    scale = [2.0 / (n - 1) for n in sizes[::-1]]
    centre = [grid_centre(n) for n in sizes[::-1]]
    normalised_matrix = torch.stack([matrix[..., i, :] * scale[i] for i in range(len(sizes))], -2)
    normalised_translation = torch.stack([(translation[..., i] + centre[i]) * scale[i] - 1.0
                                          for i in range(len(sizes))], -1)
    return _grid_sample(volume, affine_points(sizes, normalised_matrix, normalised_translation))


def physical_transform(rotation: Tensor, scale: float | None, translation: Tensor, fixed_grid: CanonicalGrid,
                       moving_grid: CanonicalGrid) -> sitk.Transform:
    """The physical ``fixed_to_moving`` transform of a solver pose on two canonical grids.

    Args:
        rotation: ``(3, 3)`` ``fixed_to_moving`` rotation on the grids (identity direction, so also in LPS).
        scale: isotropic scale ``mu`` (a ``Similarity3DTransform``), or ``None`` for a rigid pose (a
            ``VersorRigid3DTransform``).
        translation: ``(3,)`` voxels ``(x, y, z)``, the solver's ``tau``.
        fixed_grid: the fixed volume's grid (centre ``c_f``, spacing ``h``).
        moving_grid: the moving volume's grid (centre ``c_m``, the same spacing).

    Returns:
        ``T(x) = mu R (x - c_f) + c_m + h tau`` (``mu = 1`` when rigid) with its ITK centre at ``c_f``.

    Convention:
        LPS millimetres, fixed to moving (ITK's resampling direction), as in this module's header.
    """
    if not math.isclose(fixed_grid.spacing, moving_grid.spacing, rel_tol=1e-9):
        raise ValueError(f"grids must share one spacing, got {fixed_grid.spacing} and {moving_grid.spacing} mm")
    mu = 1.0 if scale is None else float(scale)
    centre = np.asarray(fixed_grid.centre, dtype=np.float64)
    matrix = np.eye(4)
    # Project the solver's float32 rotation before the translation is computed from it: the ITK transform keeps the
    # projected rotation, and c_f must still land on c_m + h tau (an unprojected R moved it by (R - R') c_f).
    matrix[:3, :3] = mu * scale_and_rotation(rotation.detach().double().cpu().numpy(), "the solver's rotation")[1]
    matrix[:3, 3] = (np.asarray(moving_grid.centre) + fixed_grid.spacing * translation.detach().double().cpu().numpy()
                     - matrix[:3, :3] @ centre)
    return similarity_transform(matrix, centre, rigid=scale is None)


def scale_and_rotation(linear: np.ndarray, name: str = "matrix") -> tuple[float, np.ndarray]:
    """Split the ``(3, 3)`` linear part ``mu R`` of a similarity into ``mu`` and the rotation nearest to ``R``.

    The rotation is projected in float64 (SVD): ITK checks orthogonality to 1e-10.

    Args:
        linear: ``(3, 3)`` ``mu R``, ``mu > 0``, ``R`` a proper rotation.
        name: what messages call it.

    Raises:
        InputError: non-finite, singular, a reflection (determinant < 0), or shear or anisotropic scale (singular
            values differing by more than :data:`SIMILARITY_TOLERANCE`, relative).
    """
    linear = np.asarray(linear, dtype=np.float64)
    if linear.shape != (3, 3) or not np.isfinite(linear).all():
        raise InputError(f"{name} is {linear.tolist()}; expected a finite (3, 3) linear part mu R")
    singular = np.linalg.svd(linear, compute_uv=False)
    shown = ", ".join(f"{value:.6g}" for value in singular)
    if singular[-1] <= np.finfo(np.float64).eps * singular[0]:
        problem = f"is singular (singular values {shown})"
    elif np.linalg.det(linear) < 0:
        problem = f"reflects (determinant {np.linalg.det(linear):.6g} < 0)"
    elif singular[0] > singular[-1] * (1.0 + SIMILARITY_TOLERANCE):
        problem = f"has shear or anisotropic scale (singular values {shown})"
    else:
        mu = float(np.cbrt(np.linalg.det(linear)))
        u, _, vt = np.linalg.svd(linear / mu)
        return mu, u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    raise InputError(f"{name} is not a similarity: its linear part {problem}; expected mu R (a rotation times an "
                     "isotropic scale)")


def similarity_transform(matrix: np.ndarray, centre: np.ndarray, *, rigid: bool, name: str = "matrix"
                         ) -> sitk.Transform:
    """A ``(4, 4)`` similarity matrix as an ITK transform with the given centre (the matrix is unchanged).

    Args:
        matrix: ``[x', 1] = matrix [x, 1]``, its linear part ``mu R``, R a rotation (see :func:`scale_and_rotation`).
        centre: ``(3,)`` rotation centre, same frame as ``x``.
        rigid: a ``VersorRigid3DTransform`` (``mu`` must be 1) or a ``Similarity3DTransform``.
        name: what messages call ``matrix``.

    Raises:
        InputError: ``matrix`` is not a similarity (:func:`scale_and_rotation`), or ``rigid`` and ``mu`` differs
            from 1 by more than :data:`SIMILARITY_TOLERANCE` (a rigid transform would drop the scale).
    """
    mu, rotation = scale_and_rotation(matrix[:3, :3], name)
    if rigid and abs(mu - 1.0) > SIMILARITY_TOLERANCE:
        raise InputError(f"{name} scales by {mu:.6g}; a rigid transform has scale 1 (use rigid=False to keep it)")
    transform = sitk.VersorRigid3DTransform() if rigid else sitk.Similarity3DTransform()
    transform.SetCenter(tuple(float(c) for c in centre))
    transform.SetMatrix(rotation.flatten().tolist())
    if not rigid:
        transform.SetScale(mu)
    transform.SetTranslation((matrix[:3, 3] + mu * rotation @ centre - centre).tolist())
    return transform


def homogeneous_matrix(transform: sitk.Transform) -> np.ndarray:
    """``(4, 4)`` matrix of a linear 3-D SimpleITK transform (identity, translation, rigid, versor, scale,
    similarity, affine; composites flattened), same frames as the transform: ``[x', 1] = H [x, 1]``.

    Raises:
        ValueError: the transform is not linear (a displacement field, a B-spline) or not 3-D.
    """
    linear = np.eye(4)
    for part in _linear_parts(transform):
        linear = linear @ _part_matrix(part)  # ITK composites apply the last-added transform first
    return linear


def _part_matrix(part: sitk.Transform) -> np.ndarray:
    """One linear transform as ``(4, 4)``: from its matrix, centre and translation where it has them (exact), else
    from the images of the origin and the unit vectors (a translation, a versor or a scale has no translation or no
    matrix to read, and the identity neither)."""
    step = np.eye(4)
    if all(hasattr(part, name) for name in ("GetMatrix", "GetCenter", "GetTranslation")):
        matrix = np.asarray(part.GetMatrix(), dtype=np.float64).reshape(3, 3)
        centre = np.asarray(part.GetCenter(), dtype=np.float64)
        step[:3, :3] = matrix
        step[:3, 3] = np.asarray(part.GetTranslation(), dtype=np.float64) + centre - matrix @ centre
        return step
    origin = np.asarray(part.TransformPoint((0.0, 0.0, 0.0)), dtype=np.float64)
    step[:3, :3] = np.column_stack([np.asarray(part.TransformPoint(tuple(axis)), dtype=np.float64) - origin
                                    for axis in np.eye(3)])
    step[:3, 3] = origin
    return step


def _linear_parts(transform: sitk.Transform) -> list[sitk.Transform]:
    if transform.GetDimension() != 3:
        raise ValueError(f"{transform.GetName()} is {transform.GetDimension()}-D; expected a 3-D transform")
    if transform.GetName() == "CompositeTransform":
        composite = sitk.CompositeTransform(transform)
        return [part for i in range(composite.GetNumberOfTransforms())
                for part in _linear_parts(composite.GetNthTransform(i))]
    if not transform.IsLinear():
        raise ValueError(f"{transform.GetName()} is not a linear transform")
    return [transform.Downcast()]


def slicer_to_parent_ras(fixed_to_moving: sitk.Transform) -> np.ndarray:
    """``(4, 4)`` to-parent matrix in RAS of the Slicer transform node equivalent to ``fixed_to_moving`` (LPS).

    Slicer models the moving volume's motion (to parent, RAS); ITK stores the resampling direction (fixed to moving,
    LPS): ``inv(F T F)``, ``F = diag(-1, -1, 1, 1)``. This is what Slicer builds when it reads the transform file.
    """
    return np.linalg.inv(LPS_TO_RAS @ homogeneous_matrix(fixed_to_moving) @ RAS_TO_LPS)
