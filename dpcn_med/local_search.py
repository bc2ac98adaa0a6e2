"""The refinement's local search in torch: an image pyramid, fixed samples, and a regular-step gradient descent of
Mattes mutual information (:mod:`dpcn_med.mutual_information`) over many poses at once, on any torch device.

:func:`dpcn_med.refine.choose_and_refine` runs it: every start on the coarsest level in one batch, the best on the
finer ones. It follows SimpleITK's ``ImageRegistrationMethod`` with ``SetOptimizerAsRegularStepGradientDescent`` and
``SetOptimizerScalesFromPhysicalShift``, as :func:`dpcn_med.refine.refine_transform` sets it up, but batched over
poses and on the GPU where the solver runs (why our own: docs/design_notes/registration.md).

Convention:
    Physical points are LPS mm. A pose maps fixed points to moving ones (ITK's resampling direction): the start's
    ``(4, 4)`` matrix composed with a residual ``D(x) = exp(s) R (x - c) + c + t`` that the descent moves, ``c`` the
    start's centre. The residual's parameters are ``(K, 6)`` (rigid: rotation vector, translation) or ``(K, 7)``
    (and log scale), every one in mm of the largest shift it causes on the level's image (ITK's physical-shift
    scales): the rotation vector and the log scale are multiplied by the level's radius.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.geometry import axis_angle_to_matrix, sample_points
from dpcn_med.lc2 import MIN_WINDOW_SHARE, WINDOW, negative_lc2
from dpcn_med.mutual_information import fixed_bins, negative_mutual_information

MIN_SMOOTHING_VOXELS = 0.2
"""A Gaussian narrower than this (in voxels) is skipped: its kernel would be a single tap."""


@dataclass(frozen=True)
class Volume:
    """An image on a torch device: ``values`` ``(1, 1, z, y, x)`` float32 and its geometry (ITK's: ``origin`` and
    ``spacing`` in mm as ``(x, y, z)``, ``direction`` ``(3, 3)`` with the axes as columns)."""

    values: Tensor
    origin: np.ndarray
    spacing: np.ndarray
    direction: np.ndarray

    @property
    def size(self) -> np.ndarray:
        """Voxels along ``(x, y, z)``."""
        return np.asarray(self.values.shape[:1:-1])

    def index_to_physical(self) -> np.ndarray:
        """``(4, 4)``: voxel index ``(x, y, z)`` to physical point."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.direction * self.spacing
        matrix[:3, 3] = self.origin
        return matrix

    def physical_to_normalised(self) -> np.ndarray:
        """``(4, 4)``: physical point to ``grid_sample``'s coordinates (``align_corners=True``: -1 and 1 are the
        centres of the first and last voxels)."""
        to_grid = np.eye(4)
        to_grid[:3, :3] = np.diag(2 / np.maximum(self.size - 1, 1))
        to_grid[:3, 3] = -1
        return to_grid @ np.linalg.inv(self.index_to_physical())

    def corners(self) -> np.ndarray:
        """``(8, 3)``: the physical points of the corner voxels' centres."""
        ends = (self.size - 1) * np.array(list(np.ndindex(2, 2, 2)))
        return ends @ self.index_to_physical()[:3, :3].T + self.origin


def volume(image: sitk.Image, device: torch.device) -> Volume:
    """``image`` (3-D, any pixel type) as a float32 :class:`Volume` on ``device``."""
    values = torch.from_numpy(sitk.GetArrayFromImage(image).astype(np.float32, copy=False))
    return Volume(values=values[None, None].to(device), origin=np.asarray(image.GetOrigin()),
                  spacing=np.asarray(image.GetSpacing()), direction=np.reshape(image.GetDirection(), (3, 3)))


def pyramid_level(image: Volume, factors: Sequence[int], sigma_mm: float) -> Volume:
    """``image`` shrunk by ``factors`` ``(x, y, z)`` and smoothed to a Gaussian of ``sigma_mm`` overall.

    The shrink averages blocks (SimpleITK's ``BinShrink``: an axis keeps ``size // factor`` voxels, the block's
    centre as its position); the block average is a box of variance ``(f^2 - 1) / 12`` voxels squared, and a
    Gaussian on the shrunk grid makes up the rest of ``sigma_mm``. Smoothing the shrunk image costs a fraction of
    smoothing the whole one first (ITK's pyramid), and the levels agree to within the box's shape.
    """
    factors = np.asarray(factors)
    values = image.values
    if (factors > 1).any():
        values = F.avg_pool3d(values, kernel_size=tuple(int(f) for f in factors[::-1]))
    spacing = image.spacing * factors
    origin = image.origin + image.direction @ ((factors - 1) / 2 * image.spacing)
    if sigma_mm > 0:
        remaining = np.sqrt(np.maximum(sigma_mm ** 2 - (factors ** 2 - 1) / 12 * image.spacing ** 2, 0)) / spacing
        values = _gaussian(values, remaining)
    return Volume(values=values.contiguous(), origin=origin, spacing=spacing, direction=image.direction)


def _gaussian(values: Tensor, sigmas: np.ndarray) -> Tensor:
    """Separable Gaussian of ``sigmas`` voxels ``(x, y, z)`` on ``(1, 1, z, y, x)``, edges replicated (torch has no
    3-D Gaussian filter; MONAI's ``GaussianFilter`` pads with zeros, which darkens the edges of a cropped head)."""
    for axis, sigma in enumerate(sigmas):  # axis 0 is x, the tensor's last dimension
        if sigma < MIN_SMOOTHING_VOXELS:
            continue
        radius = max(1, math.ceil(3 * sigma))
        taps = torch.arange(-radius, radius + 1, dtype=values.dtype, device=values.device)
        kernel = torch.exp(-0.5 * (taps / float(sigma)) ** 2)
        kernel = kernel / kernel.sum()
        shape = [1, 1, 1, 1, 1]
        shape[4 - axis] = kernel.numel()
        padding = [0] * 6
        padding[2 * axis:2 * axis + 2] = [radius, radius]
        values = F.conv3d(F.pad(values, padding, mode="replicate"), kernel.view(shape))
    return values


@dataclass(frozen=True)
class Samples:
    """Fixed-image samples of one level: ``points`` ``(N, 3)`` physical (float32, on the device), ``bins`` ``(N,)``
    their fixed histogram bins, the level's ``radius`` (mm, the farthest corner of its image from the centre: the
    scale of a rotation's shift) and its voxel ``spacing`` (mm, ``(x, y, z)``)."""

    points: Tensor
    bins: Tensor
    radius: float
    spacing: np.ndarray

    @property
    def count(self) -> int:
        return int(self.points.shape[0])


MIN_SAMPLES = 10_000
"""Samples of a level whose mask holds fewer voxels: drawn with replacement, each off its voxel's centre, they
resolve the histogram that a few hundred voxels cannot (on a 4 x 4 x 4 coarsest level of a small mask, mutual
information on the 64 voxels alone ranked every pose alike)."""


def fixed_samples(fixed: Volume, mask: sitk.Image | None, count: int, bins: int, centre: np.ndarray,
                  generator: torch.Generator) -> Samples:
    """Random points of ``fixed`` inside ``mask`` (any grid, the fixed image's physical space; ``None``:
    everywhere), drawn with ``generator`` (on the CPU, so that every device draws the same), as :class:`Samples`
    with their values binned over the samples' range into ``bins`` bins (zero-order Parzen window).

    ``min(count, max(MIN_SAMPLES, V))`` voxels of the ``V`` inside the mask are drawn with replacement, and each
    point moves off its voxel's centre by up to half a voxel along each axis.
    """
    if mask is None:
        inside = torch.arange(int(fixed.values.numel()))
    else:
        reference = sitk.Image([int(length) for length in fixed.size], sitk.sitkUInt8)
        reference.SetOrigin(fixed.origin.tolist())
        reference.SetSpacing(fixed.spacing.tolist())
        reference.SetDirection(fixed.direction.flatten().tolist())
        on_level = sitk.Resample(mask, reference, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
        inside = torch.from_numpy(np.flatnonzero(sitk.GetArrayViewFromImage(on_level)))
    drawn = min(count, max(MIN_SAMPLES, len(inside)))
    index = inside[torch.randint(len(inside), (drawn,), generator=generator)] if len(inside) else inside
    # Each sample moves off its voxel's centre by up to half a voxel, as ITK's random sampling does: on the voxel
    # centres, mutual information prefers poses that align the two grids (interpolation blurs the others).
    jitter = torch.rand(len(index), 3, generator=generator, dtype=torch.float64) - 0.5
    # The same samples in raster order: mapped by a pose, neighbours stay neighbours in the moving image, whose reads
    # then hit the cache (the metric's sampling took half the refinement in random order).
    order = torch.argsort(index, stable=True)
    index, jitter = index[order], jitter[order]
    size = fixed.size
    voxel = torch.stack([index % size[0], (index // size[0]) % size[1], index // (size[0] * size[1])], dim=1)
    to_physical = torch.as_tensor(fixed.index_to_physical())
    points = ((voxel.double() + jitter) @ to_physical[:3, :3].T + to_physical[:3, 3]).float()
    points = points.to(fixed.values.device)
    values = sample(fixed, points.unsqueeze(0))[0][0]
    low, high = (float(values.min()), float(values.max())) if len(values) else (0.0, 1.0)
    radius = float(np.linalg.norm(fixed.corners() - centre, axis=1).max())
    return Samples(points=points, bins=fixed_bins(values, low, high, bins), radius=radius, spacing=fixed.spacing)


def sample(image: Volume, points: Tensor, *, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    """``image`` at ``points`` ``(K, N, 3)`` physical (float32): ``(values, inside)``, both ``(K, N)``. As ITK's
    linear interpolator: the image spans half a voxel beyond its edge voxels' centres, where the edge value holds;
    outside that ``inside`` is false. Differentiable in ``points`` (``mode="bilinear"`` is trilinear on a
    volume)."""
    grid, inside = _normalised(image, points)
    return _sample_normalised(image, grid, mode), inside


def _normalised(image: Volume, points: Tensor) -> tuple[Tensor, Tensor]:
    """``points`` ``(K, N, 3)`` physical in ``grid_sample``'s coordinates of ``image``, and whether each lies inside
    it (within half a voxel beyond its edge voxels' centres, as ITK's linear interpolator reads)."""
    matrix = torch.as_tensor(image.physical_to_normalised(), dtype=points.dtype, device=points.device)
    grid = points @ matrix[:3, :3].T + matrix[:3, 3]
    half_voxel = torch.as_tensor(1 / np.maximum(image.size - 1, 1), dtype=grid.dtype, device=grid.device)
    return grid, (grid.detach().abs() <= 1 + half_voxel).all(-1)


def with_gradient(image: Volume) -> Volume:
    """``image`` with its central-difference gradient as three more channels, ``(1, 4, z, y, x)``, in units of
    :func:`sample`'s normalised coordinates: :func:`sample` then interpolates the gradient at each point, as ITK's
    metric does, instead of differentiating the trilinear interpolant, whose derivative jumps at every voxel face."""
    values = image.values[0, 0]
    scale = np.maximum(image.size - 1, 1) / 2  # d(index)/d(normalised) along x, y, z
    # Central differences inside, one-sided at the edges (torch.gradient's), written straight into the four channels:
    # torch.gradient and a stack allocated and copied three more volumes, a tenth of a second on a 1 mm head.
    # Channels last: the four values a sample reads at each corner sit side by side in memory (a third faster).
    channels = torch.empty((1, 4, *values.shape), dtype=values.dtype, device=values.device,
                           memory_format=torch.channels_last_3d)
    channels[0, 0] = values
    for axis in range(3):  # x, y, z: the tensor's dimensions 2, 1, 0
        dim = 2 - axis
        out = channels[0, 1 + axis]
        if values.shape[dim] < 2:
            out.zero_()
            continue
        length = values.shape[dim]
        inner, low, high = (out.narrow(dim, 1, length - 2), out.narrow(dim, 0, 1), out.narrow(dim, length - 1, 1))
        torch.sub(values.narrow(dim, 2, length - 2), values.narrow(dim, 0, length - 2), out=inner)
        inner.mul_(0.5 * float(scale[axis]))
        torch.sub(values.narrow(dim, 1, 1), values.narrow(dim, 0, 1), out=low)
        torch.sub(values.narrow(dim, length - 1, 1), values.narrow(dim, length - 2, 1), out=high)
        low.mul_(float(scale[axis]))
        high.mul_(float(scale[axis]))
    return Volume(values=channels, origin=image.origin, spacing=image.spacing, direction=image.direction)


class _SmoothGradientSample(torch.autograd.Function):
    """Trilinear samples of channel 0 of a :func:`with_gradient` volume at ``grid`` ``(M, 3)``, whose derivative
    with respect to ``grid`` is the interpolated gradient channels."""

    @staticmethod
    def forward(ctx, volume: Tensor, grid: Tensor) -> Tensor:
        sampled = sample_points(volume, grid, padding_mode="border")
        ctx.save_for_backward(sampled[1:])
        return sampled[0]

    @staticmethod
    def backward(ctx, upstream: Tensor) -> tuple[None, Tensor]:
        gradients, = ctx.saved_tensors
        return None, (gradients * upstream).T


def _sample_normalised(image: Volume, grid: Tensor, mode: str) -> Tensor:
    poses, count = grid.shape[:2]
    if image.values.shape[1] == 4 and mode == "bilinear":
        return _SmoothGradientSample.apply(image.values, grid.reshape(-1, 3)).reshape(poses, count)
    # One batch of K * N points (split over the CPU's threads by sample_points).
    values = sample_points(image.values[:, :1], grid.reshape(-1, 3), mode=mode, padding_mode="border")
    return values.reshape(poses, count)


def residual_matrices(parameters: Tensor, centre: np.ndarray, radius: float) -> Tensor:
    """``(K, 4, 4)`` float64 residual transforms ``D(x) = exp(s) R (x - c) + c + t`` of ``parameters`` ``(K, 6)`` or
    ``(K, 7)`` in mm (module docstring), about ``centre``."""
    parameters = parameters.double()
    rotation = axis_angle_to_matrix(parameters[:, :3] / radius)
    if parameters.shape[1] == 7:
        rotation = rotation * torch.exp(parameters[:, 6] / radius).view(-1, 1, 1)
    c = torch.as_tensor(centre, dtype=torch.float64, device=parameters.device)
    matrix = torch.zeros(len(parameters), 4, 4, dtype=torch.float64, device=parameters.device)
    matrix[:, :3, :3] = rotation
    matrix[:, :3, 3] = c - rotation @ c + parameters[:, 3:6]
    matrix[:, 3, 3] = 1
    return matrix


@dataclass(frozen=True)
class Level:
    """One level of the search: the fixed :class:`Samples`, the moving image and mask, the histogram's bins, and the
    moving intensities' range ``(low, high)`` that they span (the moving image's)."""

    samples: Samples
    moving: Volume
    moving_mask: Volume | None
    bins: int
    moving_range: tuple[float, float]

    def metric(self, starts: Tensor, parameters: Tensor, centre: np.ndarray) -> Tensor:
        """``-MI`` ``(K,)`` of the poses ``starts @ D(parameters)`` (``starts`` ``(K, 4, 4)`` float64)."""
        poses = (starts @ residual_matrices(parameters, centre, self.samples.radius)).float()
        mapped = self.samples.points.unsqueeze(0) @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3]
        values, valid = sample(self.moving, mapped)
        if self.moving_mask is not None:
            in_mask, inside = sample(self.moving_mask, mapped.detach(), mode="nearest")
            valid = valid & inside & (in_mask > 0.5)
        return negative_mutual_information(self.samples.bins, values, valid, self.moving_range, self.bins)


@dataclass(frozen=True)
class CorrelationLevel:
    """One level of the search where one image is ultrasound, scored by LC2 (:mod:`dpcn_med.lc2`) in windows that
    tile the ultrasound's grid, whichever side it is.

    Attributes:
        samples: the fixed image's :class:`Samples` of the level, for the step's scale (its radius and spacing) and
            for telling poses apart, as on a mutual-information :class:`Level`.
        ultrasound: ``(1, T, V)`` the ultrasound in ``T`` windows of ``V`` voxels, scaled to ``[0, 1]`` inside.
        inside: ``(1, T, V)`` bool, where the ultrasound holds data (its cone, within its mask).
        points: ``(T * V, 3)`` float32 physical points of those voxels (the ultrasound's space).
        other: ``(1, 2, z, y, x)`` the other image's intensity and gradient magnitude on its level, each scaled to
            ``[0, 1]``.
        other_mask: the other image's mask, or ``None``.
        ultrasound_fixed: whether the ultrasound is the fixed image (a pose maps its points to the other image) or
            the moving one (the pose's inverse does).
    """

    samples: Samples
    ultrasound: Tensor
    inside: Tensor
    points: Tensor
    other: Volume
    other_mask: Volume | None
    ultrasound_fixed: bool

    def metric(self, starts: Tensor, parameters: Tensor, centre: np.ndarray) -> Tensor:
        """``-LC2`` ``(K,)`` of the poses ``starts @ D(parameters)`` (``starts`` ``(K, 4, 4)`` float64)."""
        poses = starts @ residual_matrices(parameters, centre, self.samples.radius)
        if not self.ultrasound_fixed:
            poses = torch.linalg.inv(poses)
        poses = poses.float()
        mapped = self.points.unsqueeze(0) @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3]
        grid, valid = _normalised(self.other, mapped)
        values = sample_points(self.other.values, grid.reshape(-1, 3), padding_mode="border").reshape(2, *valid.shape)
        if self.other_mask is not None:
            in_mask, inside = sample(self.other_mask, mapped.detach(), mode="nearest")
            valid = valid & inside & (in_mask > 0.5)
        shape = (len(poses), *self.inside.shape[1:])
        valid = valid.reshape(shape) & self.inside
        return negative_lc2(self.ultrasound, values[0].reshape(shape), values[1].reshape(shape), valid)


def correlation_level(ultrasound: Volume, inside: Tensor, other: Volume, other_mask: Volume | None,
                      samples: Samples, ultrasound_fixed: bool, window: int = WINDOW) -> CorrelationLevel:
    """A :class:`CorrelationLevel` from the two images' levels (:func:`pyramid_level`): ``ultrasound`` and
    ``inside`` ``(1, 1, Z, Y, X)`` bool (where it holds data) on one grid, and ``other``. The windows are cubes of
    ``window`` voxels from the first voxel of ``inside``'s box on; those at least :data:`MIN_WINDOW_SHARE` inside
    are kept."""
    inside = inside[0, 0]
    where = inside.nonzero()
    low = where.min(0).values if len(where) else torch.zeros(3, dtype=torch.long, device=inside.device)
    counts = ((where.max(0).values + 1 - low + window - 1) // window) if len(where) else torch.ones(
        3, dtype=torch.long, device=inside.device)
    size = counts * window
    padded = torch.zeros(tuple(int(n) for n in size), dtype=torch.bool, device=inside.device)
    values = torch.zeros(padded.shape, dtype=ultrasound.values.dtype, device=inside.device)
    available = torch.minimum(size, torch.as_tensor(inside.shape, device=inside.device) - low)
    box = tuple(slice(int(a), int(a + n)) for a, n in zip(low, available, strict=True))
    region = tuple(slice(0, int(n)) for n in available)
    padded[region], values[region] = inside[box], ultrasound.values[0, 0][box]
    inside_tiles, value_tiles = _tiles(padded, counts, window), _tiles(values, counts, window)
    kept = inside_tiles.sum(1) >= MIN_WINDOW_SHARE * window ** 3
    inside_tiles, value_tiles = inside_tiles[kept], value_tiles[kept]
    inner = value_tiles[inside_tiles]
    low_value, high_value = (float(inner.min()), float(inner.max())) if len(inner) else (0.0, 1.0)
    scaled = ((value_tiles - low_value) / max(high_value - low_value, 1e-12)).clamp(0, 1)
    index = torch.stack(torch.meshgrid(*[torch.arange(int(n), dtype=torch.float64) for n in size],
                                       indexing="ij"), dim=-1) + low.cpu().double()  # (z, y, x) indices
    index = _tiles(index, counts.cpu(), window)[kept.cpu()].reshape(-1, 3).flip(-1)  # (x, y, z)
    to_physical = torch.as_tensor(ultrasound.index_to_physical())
    points = (index @ to_physical[:3, :3].T + to_physical[:3, 3]).float()
    return CorrelationLevel(samples=samples, ultrasound=scaled.unsqueeze(0), inside=inside_tiles.unsqueeze(0),
                            points=points.to(inside.device), other=_intensity_and_gradient(other),
                            other_mask=other_mask, ultrasound_fixed=ultrasound_fixed)


def _tiles(volume: Tensor, counts: Tensor, window: int) -> Tensor:
    """``volume`` ``(Z, Y, X, ...)``, ``counts * window`` voxels along its first three axes, as ``(T, window ** 3,
    ...)``: its ``T`` cubes of ``window`` voxels in raster order, each cube's voxels in raster order."""
    z, y, x = (int(n) for n in counts)
    rest = tuple(volume.shape[3:])
    order = (0, 2, 4, 1, 3, 5, *range(6, 6 + len(rest)))
    return volume.reshape(z, window, y, window, x, window, *rest).permute(order).reshape(z * y * x, window ** 3, *rest)


def _intensity_and_gradient(image: Volume) -> Volume:
    """``image`` ``(1, 1, z, y, x)`` as ``(1, 2, z, y, x)``: its intensity and its gradient magnitude (central
    differences in mm), each scaled to ``[0, 1]`` over the image."""
    values = image.values[0, 0]
    spacing = [float(length) for length in image.spacing[::-1]]  # z, y, x
    gradient = torch.stack([torch.gradient(values, spacing=length, dim=dim)[0] if values.shape[dim] > 1
                            else torch.zeros_like(values) for dim, length in enumerate(spacing)]).norm(dim=0)

    def unit(channel: Tensor) -> Tensor:
        low, high = channel.min(), channel.max()
        return (channel - low) / (high - low).clamp_min(1e-12)

    channels = torch.stack([unit(values), unit(gradient)]).unsqueeze(0).contiguous()
    return Volume(values=channels, origin=image.origin, spacing=image.spacing, direction=image.direction)


PACE_STEPS = 5
"""Steps over which :func:`regular_step_descent` measures a pose's pace, to tell one closing in on the leader from
one wandering behind it."""


def itk_step_weights(count: int, radius: float, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(norm, gain)`` of :func:`regular_step_descent` for ``count`` (6 or 7) residual parameters (module docstring)
    that take the steps SimpleITK's registration method takes with ``VersorRigid3DTransform`` (or
    ``Similarity3DTransform``) and ``SetOptimizerScalesFromPhysicalShift``, ``radius`` the level's.

    ITK divides the gradient by the squared physical shift of each parameter and normalises the step by the norm of
    that: a rotation's component weighs ``1 / radius`` of a translation's in the norm. Its versor transform also
    differentiates with respect to versor components (half the angle) and takes the update as an axis and angle,
    which doubles the rotation's step. So a translation moves by the step, and a rotation by about twice the step
    times its gradient over the translation's: rotations far off close in a few steps (docs/design_notes)."""
    norm = [2 / radius] * 3 + [1.0] * 3 + [1 / radius] * (count - 6)
    gain = [2.0] * 3 + [1.0] * 3 + [1.0] * (count - 6)
    return (torch.tensor(norm, dtype=torch.float64, device=device),
            torch.tensor(gain, dtype=torch.float64, device=device))


def regular_step_descent(metric: Callable[[Tensor, Tensor], Tensor], parameters: Tensor, first_step: float,
                         iterations: int, *, min_step: float = 1e-2, relaxation: float = 0.5,
                         gradient_tolerance: float = 1e-6, settle: float | None = None,
                         weights: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Minimise ``metric`` from ``parameters`` ``(K, P)``, each pose on its own (ITK's
    ``RegularStepGradientDescentOptimizerv4``): a step of ``first_step`` along the normalised gradient, multiplied
    by ``relaxation`` whenever the gradient turns back (negative dot product with the last), until it is below
    ``min_step``, the gradient's norm below ``gradient_tolerance``, the metric not finite, or ``iterations`` steps.

    Args:
        metric: ``metric(parameters, poses)``: the values ``(k,)`` of the poses of indices ``poses`` ``(k,)`` at
            ``parameters`` ``(k, P)``; only the poses still moving are evaluated.
        weights: ``(norm, gain)``, each ``(P,)``: the step is ``first_step * gain * g / |norm * g|`` for a gradient
            ``g`` (default: both 1, a step of ``first_step`` along the gradient); :func:`itk_step_weights` gives
            ITK's.
        settle: once the pose with the lowest metric has stopped, with a negative metric ``m``, every pose above
            ``settle * m`` stops too unless, at its pace over the last :data:`PACE_STEPS` steps, it would get below
            that within the steps left (``None``: each runs to its own end). The metric is ``-MI``: with ``0.5``, the
            poses that share less than half the leader's information, and are not closing in on it, stop when it
            does.

    Returns:
        ``(parameters, metric)``: the last parameters and the metric at them, ``(K, P)`` and ``(K,)`` (detached).
    """
    parameters = parameters.detach().clone()
    poses = torch.arange(len(parameters), device=parameters.device)
    step = torch.full((len(parameters),), float(first_step), dtype=parameters.dtype, device=parameters.device)
    previous = torch.zeros_like(parameters)
    latest = torch.full((len(parameters),), float("inf"), dtype=torch.float64, device=parameters.device)
    history: list[Tensor] = []  # latest, after each step
    active = poses
    for iteration in range(iterations):
        current = parameters[active].clone().requires_grad_(True)
        value = metric(current, active)
        finite = torch.isfinite(value)
        gradient, = torch.autograd.grad(value.masked_fill(~finite, 0).sum(), current)
        if iteration > 0:
            step[active] = torch.where((gradient * previous[active]).sum(1) < 0, step[active] * relaxation,
                                       step[active])
        norm = (gradient * weights[0]).norm(dim=1) if weights is not None else gradient.norm(dim=1)
        moving = finite & (step[active] >= min_step) & (norm > gradient_tolerance)
        latest[active] = value.detach().masked_fill(~finite, float("inf")).to(latest.dtype)
        history.append(latest.clone())
        if settle is not None and len(history) > PACE_STEPS:
            leader = int(latest.argmin())
            if float(latest[leader]) < 0 and not bool(moving[active == leader].any()):
                behind = latest[active] - settle * latest[leader]
                pace = (history[-1 - PACE_STEPS][active] - latest[active]) / PACE_STEPS
                moving &= (behind <= 0) | (behind < pace * (iterations - iteration - 1))
        if not bool(moving.any()):
            break
        gradient, norm, active = gradient[moving], norm[moving], active[moving]
        parameters[active] -= (step[active] / norm).unsqueeze(1) * gradient * (weights[1] if weights is not None else 1)
        previous[active] = gradient
    with torch.no_grad():
        return parameters, metric(parameters, poses)
