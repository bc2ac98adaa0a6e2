"""3-D ultrasound simulated from a CT-like volume, in the CT's frame (exact ground truth for CT-US pairs)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from dpcn_med.arguments import check_pair, check_real
from dpcn_med.errors import InputError
from dpcn_med.geometry import affine_points, grid_centre, sample
from dpcn_med.synth._common import check_volumes, normal, uniform


@dataclass(frozen=True)
class UltrasoundConfig:
    """Probe, field of view and tissue acoustics of :func:`simulated_ultrasound`; the defaults are a head-sized
    phased array on a canonical grid (the object spans about half of it).

    Attributes:
        half_angle_degrees: half-angle of the cone of view, uniform in this interval inside ``[5, 89]``.
        depth_range: reach of the beams beyond the standoff, fraction of the grid side ``N``, uniform in this interval
            inside ``[0.1, 2]`` (the grid's diagonal is ``1.73 N``).
        standoff: the apex lies this fraction of ``N`` before the object's first voxel along the probe direction, in
            ``[0, 1]``.
        impedance_gain: acoustic impedance ``exp(impedance_gain * ct)`` (relative; monotonic in the CT value), in
            ``[0, 30]``.
        attenuation: absorption of tissue per grid side, times the CT value, in ``[0, 100]``.
        bone_level: CT value from which absorption rises towards that of bone (reached at 1).
        bone_attenuation: extra absorption of bone per grid side (a skull casts an acoustic shadow), in
            ``[0, 1000]``.
        reflection_gain: weight of the specular echoes at impedance changes.
        scatter_gain: weight of the diffuse backscatter of tissue, proportional to its CT value (this or
            ``reflection_gain`` positive; only their ratio matters).
    """

    half_angle_degrees: tuple[float, float] = (30.0, 45.0)
    depth_range: tuple[float, float] = (0.4, 0.8)
    standoff: float = 0.05
    impedance_gain: float = 3.0
    attenuation: float = 1.0
    bone_level: float = 0.75
    bone_attenuation: float = 60.0
    reflection_gain: float = 1.0
    scatter_gain: float = 0.2

    def __post_init__(self) -> None:
        """Refuse what would make NaN or blank volumes, naming the field (the bounds: docs/design_notes/synth.md).

        Raises:
            InputError: a value out of its range, or both gains 0.
        """
        check_pair("half_angle_degrees", self.half_angle_degrees, minimum=5.0, maximum=89.0, equal=True)
        # A reach far past the grid spends the beam's N range samples outside it: (100, 100) gave a blank volume.
        check_pair("depth_range", self.depth_range, minimum=0.1, maximum=2.0, equal=True,
                   note=" (fractions of the grid side N)")
        check_real("standoff", self.standoff, minimum=0.0, maximum=1.0)
        check_real("impedance_gain", self.impedance_gain, minimum=0.0, maximum=30.0)
        check_real("attenuation", self.attenuation, minimum=0.0, maximum=100.0)
        check_real("bone_attenuation", self.bone_attenuation, minimum=0.0, maximum=1000.0)
        for name in ("reflection_gain", "scatter_gain"):
            check_real(name, getattr(self, name), minimum=0.0)
        if self.reflection_gain == 0 and self.scatter_gain == 0:
            raise InputError("reflection_gain and scatter_gain are both 0: every echo would be 0; make one positive")
        check_real("bone_level", self.bone_level, minimum=0.0, maximum=1.0, below=True)


def _probe_directions(probe: Tensor | None, batch: int, generator: torch.Generator, like: Tensor) -> Tensor:
    """Unit beam directions ``(B, 3)``: ``probe`` normalised, or uniform on the sphere."""
    if probe is None:
        probe = normal(generator, (batch, 3), like=like)
    probe = torch.as_tensor(probe, device=like.device, dtype=like.dtype)
    if probe.shape not in ((3,), (batch, 3)):
        raise InputError(f"probe has shape {tuple(probe.shape)}; expected (3,) or ({batch}, 3) directions (x, y, z)")
    if not bool(torch.isfinite(probe).all()):
        raise InputError("probe contains a NaN or infinite value; a beam direction must be finite")
    length = probe.norm(dim=-1, keepdim=True)
    if not bool((length > 0).all()):
        raise InputError("probe contains a zero vector; a beam direction must be nonzero")
    return (probe / length).expand(batch, 3)


def _lateral_axes(direction: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors ``(B, 3)`` completing ``direction`` ``(B, 3)`` to a right-handed orthonormal frame."""
    helper = torch.zeros_like(direction)
    helper[:, 0] = 1.0
    helper = torch.where(direction[:, :1].abs() > 0.9, helper.roll(1, dims=1), helper)  # never parallel
    first = torch.linalg.cross(helper, direction)
    first = first / first.norm(dim=-1, keepdim=True)
    return first, torch.linalg.cross(direction, first)


def _echoes(ct_fan: Tensor, step: Tensor, config: UltrasoundConfig) -> Tensor:
    """Echo strength along the beams of a fan ``(B, 1, R, V, U)`` (range first), ``step`` ``(B,)`` grid sides."""
    # Intensity reflection coefficient ((Z - Z') / (Z + Z'))^2 of the impedance change Z' -> Z = exp(gain * ct)
    # between consecutive samples along the beam, written as tanh(gain * (ct - ct') / 2)^2: the same quantity, without
    # the exponential, which overflowed float32 from a gain of 89 (inf / inf, NaN).
    change = torch.diff(ct_fan, dim=2, prepend=ct_fan[:, :, :1])
    reflection = torch.tanh(0.5 * config.impedance_gain * change) ** 2
    transmitted = torch.cumprod(1.0 - reflection, 2)
    transmitted = torch.cat([torch.ones_like(transmitted[:, :, :1]), transmitted[:, :, :-1]], 2)
    bone = ((ct_fan - config.bone_level) / (1.0 - config.bone_level)).clamp(0.0, 1.0)
    absorption = (config.attenuation * ct_fan + config.bone_attenuation * bone) * step.reshape(-1, 1, 1, 1, 1)
    # Exclusive sum (the absorbers before each sample), shifted rather than cumsum - absorption: inf - inf is NaN.
    optical_depth = torch.cat([torch.zeros_like(absorption[:, :, :1]), torch.cumsum(absorption, 2)[:, :, :-1]], 2)
    # Round trip: an echo from range r crosses every interface and absorber before r on its way in and out.
    two_way = (transmitted * torch.exp(-optical_depth)) ** 2
    # The gains relative to the larger: only their ratio survives the normalisation below, and 1e308 is inf in float32.
    largest = max(config.reflection_gain, config.scatter_gain)
    echo = two_way * (config.reflection_gain / largest * reflection + config.scatter_gain / largest * ct_fan)
    return echo / echo.flatten(1).amax(-1).clamp_min(torch.finfo(echo.dtype).tiny).reshape(-1, 1, 1, 1, 1)


def simulated_ultrasound(ct: Tensor, generator: torch.Generator, *, probe: Tensor | None = None,
                         config: UltrasoundConfig = UltrasoundConfig()) -> tuple[Tensor, Tensor]:
    """A 3-D ultrasound volume of the anatomy of a CT-like volume, on the same grid.

    A probe at an apex outside the object sends beams into a cone around its direction. Along each beam: specular
    echoes where the acoustic impedance (monotonic in the CT value) changes, diffuse backscatter from tissue, loss of
    transmission behind every reflector (cumulative product: shadows behind bone and air), absorption rising with depth
    and strongly in bone; then multiplicative Rayleigh speckle of mean 1. Nothing outside the cone.

    Args:
        ct: ``(B, 1, N, N, N)`` intensities in ``[0, 1]``, bone brightest, 0 outside the object (a CT window, or a
            pseudo-CT on its solver grid).
        generator: source of randomness (any device; draws are moved to ``ct``'s).
        probe: ``(3,)`` or ``(B, 3)`` beam directions ``(x, y, z)`` (normalised here); uniform on the sphere if None.
        config: field of view and acoustics.

    Returns:
        ``(ultrasound, fov_mask)``, both ``(B, 1, N, N, N)`` with ``ct``'s device and dtype: echoes in ``[0, 1]``
        (brightest echo 1 before speckle, clipped after), and 1 inside the cone of view, 0 outside (where the
        ultrasound is 0).

    Raises:
        InputError: ``ct`` is not a finite cubic batch, a volume is empty, or ``probe`` is malformed or not finite.

    Convention:
        Voxel coordinates ``(x, y, z)`` from the grid centre, as in :mod:`dpcn_med.geometry`. The apex sits on the
        line along the probe direction through the object's centroid, ``config.standoff * N`` before its first voxel.
        The beams are sampled on a fan of ``N`` ranges times ``N x N`` directions (lateral resolution coarsens with
        depth, as with a real probe) and the echoes are resampled back onto the grid.
    """
    size = check_volumes("ct", ct, cubic=True)
    foreground = ct[:, 0] > 0
    if not bool(foreground.flatten(1).any(-1).all()):
        raise InputError("ct contains an empty volume (no voxel above 0); the probe needs an object to image")
    points = affine_points((size,) * 3, torch.eye(3, device=ct.device, dtype=ct.dtype)[None])  # (1, N, N, N, 3)
    fan = _placed_probe(ct, foreground, points, generator, probe, config)
    echoes = _fan_echoes(ct, fan, config)
    fan_index, inside = _fan_coordinates(points, fan, size)
    fov_mask = inside.to(ct.dtype)[:, None]
    rayleigh = math.sqrt(2.0 / math.pi) * torch.hypot(normal(generator, tuple(ct.shape), like=ct),
                                                      normal(generator, tuple(ct.shape), like=ct))
    return (sample(echoes, fan_index) * fov_mask * rayleigh).clamp(0.0, 1.0), fov_mask


B_MODE_FLOOR = 1 / 255
"""What the weakest echo inside the cone becomes in :func:`b_mode`, above the 0 outside it (an 8-bit scanner's first
grey), so that the cone stays the image's nonzero voxels."""


def b_mode(echoes: Tensor, cone: Tensor, dynamic_range_db: float) -> Tensor:
    """Echo intensities as a scanner displays them: log-compressed, the brightest ``0`` dB and
    ``-dynamic_range_db`` the floor, mapped to ``[B_MODE_FLOOR, 1]`` inside ``cone`` and 0 outside.

    Raw echo intensities span orders of magnitude (the brightest is about 40 times the mean inside the benchmark's
    cones), and every 3-D ultrasound a user exports is compressed so; a similarity on the raw intensities weighs a
    handful of bright voxels (docs/design_notes/registration.md).

    Args:
        echoes: intensities in ``[0, 1]``, any shape (:func:`simulated_ultrasound`'s, the brightest 1).
        cone: the same shape, nonzero inside the cone of view.
        dynamic_range_db: the range shown, dB (> 0; scanners show 40 to 80).

    Raises:
        InputError: a ``dynamic_range_db`` that is not positive, or shapes that differ.
    """
    dynamic_range_db = check_real("dynamic_range_db", dynamic_range_db, minimum=0.0, above=True)
    if echoes.shape != cone.shape:
        raise InputError(f"echoes have shape {tuple(echoes.shape)} and cone {tuple(cone.shape)}; expected one shape")
    decibels = 10 * torch.log10(echoes.clamp_min(torch.finfo(echoes.dtype).tiny))
    shown = (decibels / dynamic_range_db + 1).clamp(B_MODE_FLOOR, 1.0)
    return torch.where(cone > 0, shown, torch.zeros_like(shown))


class _Probe(NamedTuple):
    """A batch of probes in voxel coordinates ``(x, y, z)`` from the grid centre.

    Attributes:
        apex: ``(B, 3)`` where the beams start.
        direction: ``(B, 3)`` unit axis of the cone.
        across, up: ``(B, 3)`` unit lateral axes completing ``direction`` to a right-handed frame.
        tan_half: ``(B,)`` tangent of the cone's half-angle.
        reach: ``(B,)`` length of the beams, voxels.
    """

    apex: Tensor
    direction: Tensor
    across: Tensor
    up: Tensor
    tan_half: Tensor
    reach: Tensor


def _placed_probe(ct: Tensor, foreground: Tensor, points: Tensor, generator: torch.Generator, probe: Tensor | None,
                  config: UltrasoundConfig) -> _Probe:
    """The probes of :func:`simulated_ultrasound`: direction, half-angle and reach drawn (in that order), the apex on
    the line along the direction through the object's centroid, ``config.standoff * N`` before its first voxel.

    Args:
        ct: ``(B, 1, N, N, N)``.
        foreground: ``(B, N, N, N)`` bool, the object.
        points: ``(1, N, N, N, 3)`` voxel coordinates of the grid.
        generator, probe, config: as :func:`simulated_ultrasound` takes them.
    """
    batch, size = ct.shape[0], ct.shape[-1]
    direction = _probe_directions(probe, batch, generator, ct)
    across, up = _lateral_axes(direction)
    tan_half = torch.tan(torch.deg2rad(uniform(generator, (batch,), *config.half_angle_degrees, like=ct)))
    reach = (config.standoff + uniform(generator, (batch,), *config.depth_range, like=ct)) * size
    weights = foreground.to(ct.dtype)[..., None]
    centroid = (points * weights).sum((1, 2, 3)) / weights.sum((1, 2, 3))
    along = (points * direction[:, None, None, None]).sum(-1)
    entry = torch.where(foreground, along, math.inf).flatten(1).amin(-1)
    lateral = centroid - (centroid * direction).sum(-1, keepdim=True) * direction
    apex = lateral + (entry - config.standoff * size)[:, None] * direction
    return _Probe(apex, direction, across, up, tan_half, reach)


def _fan_echoes(ct: Tensor, fan: _Probe, config: UltrasoundConfig) -> Tensor:
    """``(B, 1, N, N, N)`` echoes on the fan of ``N`` ranges (torch axis D) times ``N x N`` beam tangents (H: up,
    W: across)."""
    size = ct.shape[-1]
    ticks = torch.linspace(0.0, 1.0, size, device=ct.device, dtype=ct.dtype)
    ranges = fan.reach[:, None] * ticks
    tangents = fan.tan_half[:, None] * (2.0 * ticks - 1.0)
    beams = (fan.direction[:, None, None] + tangents[:, None, :, None] * fan.across[:, None, None]
             + tangents[:, :, None, None] * fan.up[:, None, None])
    beams = beams / beams.norm(dim=-1, keepdim=True)
    fan_points = fan.apex[:, None, None, None] + ranges[:, :, None, None, None] * beams[:, None]
    return _echoes(sample(ct, fan_points), fan.reach / ((size - 1) * size), config)


def _fan_coordinates(points: Tensor, fan: _Probe, size: int) -> tuple[Tensor, Tensor]:
    """Each voxel's place in the fan of :func:`_fan_echoes`: ``(fan voxel coordinates (B, N, N, N, 3), inside the
    cone of view (B, N, N, N) bool)``."""
    offset = points - fan.apex[:, None, None, None]
    axial = (offset * fan.direction[:, None, None, None]).sum(-1)
    safe_axial = torch.where(axial > 0, axial, 1.0)
    tangent_across = (offset * fan.across[:, None, None, None]).sum(-1) / safe_axial
    tangent_up = (offset * fan.up[:, None, None, None]).sum(-1) / safe_axial
    distance = offset.norm(dim=-1)
    per_sample = (-1, 1, 1, 1)
    tan_half, reach = fan.tan_half.reshape(per_sample), fan.reach.reshape(per_sample)
    inside = (axial > 0) & (tangent_across ** 2 + tangent_up ** 2 <= tan_half ** 2) & (distance <= reach)
    centre = grid_centre(size)
    fan_index = torch.stack([(tangent_across / tan_half + 1.0) * (size - 1) / 2 - centre,
                             (tangent_up / tan_half + 1.0) * (size - 1) / 2 - centre,
                             distance / reach * (size - 1) - centre], -1)
    return fan_index, inside
