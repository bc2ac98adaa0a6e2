"""Ground truth in physical space: known similarity transforms applied to real volumes, and the target registration
error of an estimate against them (tests, benchmarks, the demo)."""

from __future__ import annotations

import math

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike

from dpcn_med.arguments import shown
from dpcn_med.errors import InputError
from dpcn_med.geometry import homogeneous_matrix, scale_and_rotation
from dpcn_med.preprocess import bounding_box, foreground_mask

SUCCESS_DEGREES, SUCCESS_VOXELS = 5.0, 2.0
"""A global estimate is right within 5 degrees and 2 voxels of its canonical grid: the solver's own criterion (the
learning issue's), which training, the held-out benchmark and the full benchmark's global column share. A grid of
7-10 mm voxels cannot meet a 2 mm TRE."""


def random_similarity(rng: np.random.Generator, centre: np.ndarray, *, max_shift_mm: float = 40.0,
                      scale_range: tuple[float, float] = (1.0, 1.0)) -> sitk.Similarity3DTransform:
    """A random ``fixed_to_moving`` similarity about ``centre`` (LPS, mm): rotation uniform over SO(3), shift of
    uniform direction and length up to ``max_shift_mm``, scale uniform in ``scale_range``.

    Raises:
        ValueError: ``centre`` not 3 finite numbers, ``max_shift_mm`` negative or not finite, or ``scale_range`` not
            ``0 < low <= high`` (finite).
    """
    centre = np.asarray(centre, dtype=np.float64)
    low, high = scale_range
    if centre.shape != (3,) or not np.isfinite(centre).all():
        raise ValueError(f"centre must be 3 finite numbers (LPS, mm), got {centre.tolist()}")
    if not (math.isfinite(max_shift_mm) and max_shift_mm >= 0):
        raise ValueError(f"max_shift_mm must be finite and >= 0, got {max_shift_mm}")
    if not (math.isfinite(high) and 0 < low <= high):
        raise ValueError(f"scale_range must be (low, high) with 0 < low <= high, got {scale_range}")
    quaternion = rng.normal(size=4)
    quaternion /= np.linalg.norm(quaternion)
    if quaternion[3] < 0:  # (x, y, z, w) and its negative are the same rotation; a versor wants w >= 0
        quaternion = -quaternion
    direction = rng.normal(size=3)
    shift = direction / np.linalg.norm(direction) * rng.uniform(0.0, max_shift_mm)
    transform = sitk.Similarity3DTransform()
    transform.SetCenter(tuple(float(c) for c in centre))
    transform.SetRotation(tuple(float(q) for q in quaternion))
    transform.SetScale(float(rng.uniform(*scale_range)))
    transform.SetTranslation(shift.tolist())
    return transform


def moved_copy(image: sitk.Image, fixed_to_moving: sitk.Transform) -> sitk.Image:
    """The same voxels placed so that ``moved(T(x)) = image(x)`` for every physical point ``x``, ``T`` a similarity.

    Exact and lossless: a similarity maps the voxel lattice to a lattice, so only the origin, direction and spacing
    change (``origin' = T(origin)``, ``direction' = R direction``, ``spacing' = mu spacing``); nothing leaves the
    field of view, whatever the rotation.
    """
    scale, rotation = scale_and_rotation(homogeneous_matrix(fixed_to_moving)[:3, :3])
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    moved = sitk.Image(image)
    moved.SetOrigin(fixed_to_moving.TransformPoint(image.GetOrigin()))
    moved.SetDirection((rotation @ direction).flatten().tolist())
    moved.SetSpacing([scale * s for s in image.GetSpacing()])
    return moved


def foreground_corners(image: sitk.Image, mask: sitk.Image | None = None) -> np.ndarray:
    """``(8, 3)`` LPS corners (mm) of the bounding box of ``image``'s foreground (or of ``mask``), in voxel space.

    Raises:
        InputError: the foreground (or ``mask``) is empty.
    """
    box = bounding_box(foreground_mask(image) if mask is None else mask)
    if box is None:
        raise InputError("mask is empty (no voxel > 0); give a mask with foreground" if mask is not None else
                         "image has no foreground (it is blank or constant); corners need an object to surround")
    start, size = (values.astype(np.float64) for values in box)
    corners = [start - 0.5 + size * np.array(c) for c in np.ndindex(2, 2, 2)]
    grid = image if mask is None else mask  # the box is in the mask's voxels, whatever its grid
    return np.array([grid.TransformContinuousIndexToPhysicalPoint(c.tolist()) for c in corners])


def target_registration_error(estimate: sitk.Transform, truth: sitk.Transform, points: ArrayLike) -> float:
    """Mean distance (mm) between where ``estimate`` and ``truth`` send ``points`` (both fixed to moving).

    Args:
        estimate: the transform under test.
        truth: the ground truth.
        points: ``(K, 3)`` LPS mm, an array or a list of points.

    Raises:
        InputError: ``points`` is not ``(K, 3)`` with ``K >= 1``, or holds NaN or Inf.
    """
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):  # ragged lists, strings
        raise InputError(f"points is {shown(points)}; expected (K, 3) numbers") from None
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] == 0:
        raise InputError(f"points has shape {array.shape}; expected (K, 3) with at least one point")
    if not np.isfinite(array).all():
        raise InputError(f"points holds {int((~np.isfinite(array)).any(1).sum())} points with NaN or Inf "
                         "coordinates; expected finite LPS millimetres")
    return float(np.mean([np.linalg.norm(np.subtract(estimate.TransformPoint(p.tolist()),
                                                     truth.TransformPoint(p.tolist()))) for p in array]))


def rotation_error(estimate: sitk.Transform, truth: sitk.Transform) -> float:
    """The angle (degrees, in ``[0, 180]``) between the rotations of two linear transforms (both fixed to moving).

    Each rotation is the one nearest its transform's linear part (polar decomposition), so a scale, or the small
    shear an affine tool leaves, does not count; a reflection is taken with its sign flipped, as the nearest proper
    rotation.

    Raises:
        ValueError: a transform that is not linear (:func:`dpcn_med.geometry.homogeneous_matrix`).
    """
    rotations = []
    for transform in (estimate, truth):
        left, _, right = np.linalg.svd(homogeneous_matrix(transform)[:3, :3])
        rotations.append(left @ np.diag([1.0, 1.0, np.sign(np.linalg.det(left @ right))]) @ right)
    relative = rotations[0] @ rotations[1].T
    # atan2 of the angle's sine (from the skew part) and cosine (from the trace), not acos of the cosine alone:
    # acos loses half the digits near 0 degrees (1e-16 in the trace is 1e-6 degrees out).
    skew = relative - relative.T
    sine = math.hypot(skew[2, 1], skew[0, 2], skew[1, 0]) / 2.0
    return math.degrees(math.atan2(sine, (np.trace(relative) - 1.0) / 2.0))
