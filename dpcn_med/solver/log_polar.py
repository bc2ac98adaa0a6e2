"""2-D DPC, step 2-4 in one: rotation and scale as one shift of the log-polar magnitude spectrum."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.geometry import sample
from dpcn_med.solver.phase_correlation import SoftPeak, phase_correlation, refine_peak, soft_argmax
from dpcn_med.solver.scale import detrend
from dpcn_med.solver.sphere import floored_log, log_radii, log_radius_step


@dataclass
class LogPolarEstimate:
    """Result of :func:`log_polar_rotation_scale`.

    Attributes:
        angle: ``(batch,)`` radians in ``[-pi/2, pi/2)``, counter-clockwise; ``angle + pi`` is equally likely (``|FFT|``
            is point-symmetric).
        scale: ``(batch,)``.
        peak: soft arg-max over ``(angle, log-radius)`` cells: ``peak.shift`` is ``(log-radius, angle)`` in cells.
        angle_bin: radians per angular cell.
        radius_bin: ``log r`` per radial cell.
    """

    angle: Tensor
    scale: Tensor
    peak: SoftPeak
    angle_bin: float
    radius_bin: float


def log_polar(magnitude: Tensor, angles: int, radii: Tensor) -> Tensor:
    """Log-magnitude spectrum on a log-polar grid over half a turn.

    Args:
        magnitude: ``(batch, N, N)`` ``fftshift``-ed magnitude spectrum.
        angles: number of angles ``theta_i = pi i / angles`` (half a turn suffices: ``|FFT|`` is point-symmetric).
        radii: ``(R,)`` log-spaced radii in frequency cells.

    Returns:
        ``(batch, angles, R)`` ``log |G|(r (cos theta, sin theta))``.
    """
    theta = torch.arange(angles, device=magnitude.device, dtype=magnitude.dtype) * (math.pi / angles)
    directions = torch.stack([theta.cos(), theta.sin()], -1)
    points = directions[:, None, :] * radii[:, None]  # (A, R, 2)
    values = sample(magnitude[:, None], points.expand(magnitude.shape[0], *points.shape))[:, 0]
    return floored_log(values, magnitude)


def log_polar_rotation_scale(fixed_magnitude: Tensor, moving_magnitude: Tensor, band: tuple[float, float],
                             samples: int, angles: int, temperature: Tensor | float, *, refine: bool,
                             upsample: int) -> LogPolarEstimate:
    """Rotation (modulo half a turn) and scale between two 2-D magnitude spectra.

    Args:
        fixed_magnitude: ``(batch, N, N)`` ``fftshift``-ed magnitude spectrum of the fixed image.
        moving_magnitude: ``(batch, N, N)`` same for the moving image.
        band: radii, fractions of the Nyquist radius.
        samples: log-spaced radial samples.
        angles: angular samples over half a turn.
        temperature: softmax temperature.
        refine: arg-max plus an upsampled-DFT refinement (True) or the soft arg-max (False).
        upsample: refinement factor.

    Returns:
        A :class:`LogPolarEstimate`.

    Notes:
        ``|G_fixed|(r, theta) = mu^-2 |G_moving|(r / mu, theta + angle)``: in ``(theta, log r)`` the fixed log-polar
        image is the moving one shifted by ``(-angle, log mu)``; the log-radius axis is detrended, tapered and
        zero-padded (it does not wrap), the angle axis wraps.

    References:
        Reddy and Chatterji, "An FFT-based technique for translation, rotation, and scale-invariant image
        registration", IEEE TIP 1996.
    """
    radii = log_radii(fixed_magnitude.shape[-1], band, samples, device=fixed_magnitude.device,
                      dtype=fixed_magnitude.dtype)
    taper = torch.hann_window(samples, periodic=False, device=radii.device, dtype=radii.dtype)
    pad = (0, samples)
    fixed = torch.nn.functional.pad(detrend(log_polar(fixed_magnitude, angles, radii)) * taper, pad)
    moving = torch.nn.functional.pad(detrend(log_polar(moving_magnitude, angles, radii)) * taper, pad)
    # Normalised cross-correlation, not whitened: whitening amplifies the structure both images share at zero shift
    # (the taper over log r, the interpolation of the resampled grids) into a spike that pins small rotations to zero
    # (measured on the MRI-DIR T2: a 1.7-degree rotation found as 0).
    surface, spectrum = phase_correlation(fixed, moving, 2, whiten=False)
    energy = (torch.linalg.vector_norm(fixed, dim=(-2, -1)) * torch.linalg.vector_norm(moving, dim=(-2, -1))
              + torch.finfo(fixed.dtype).eps)  # vector_norm: its gradient at zero is 0, sqrt's is NaN
    surface, spectrum = surface / energy[:, None, None], spectrum / energy[:, None, None]
    peak = soft_argmax(surface, temperature, 2)
    shift = refine_peak(spectrum, peak.index, tuple(fixed.shape[-2:]), upsample=upsample)[0] if refine else peak.shift
    angle_bin = math.pi / angles
    radius_bin = log_radius_step(band, samples)
    angle = torch.remainder(shift[:, 1] * angle_bin + math.pi / 2, math.pi) - math.pi / 2
    return LogPolarEstimate(angle=angle, scale=torch.exp(-shift[:, 0] * radius_bin), peak=peak,
                            angle_bin=angle_bin, radius_bin=radius_bin)
