"""Step 5 of DPC: translation by phase correlation of the rotation- and scale-compensated volumes."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from dpcn_med.solver.phase_correlation import SoftPeak, phase_correlation, refine_peak, soft_argmax
from dpcn_med.solver.spectrum import apodize


@dataclass
class TranslationEstimate:
    """Result of :func:`phase_translation`.

    Attributes:
        shift: ``(batch, d)`` voxels ``(x, y[, z])`` with ``fixed(p) ~ moving(p + shift)``.
        peak: the soft arg-max; ``peak.mass`` is the solver's confidence.
        height: ``(batch,)`` phase-correlation value at the shift, about 1 for a perfect match and near 0 for none.
    """

    shift: Tensor
    peak: SoftPeak
    height: Tensor


def phase_translation(fixed: Tensor, moving: Tensor, temperature: Tensor | float, *, dim: int, taper: float,
                      refine: bool, upsample: int) -> TranslationEstimate:
    """Shift between two volumes (or images) by phase correlation.

    Args:
        fixed: ``(batch, *S)`` real, ``S`` the last ``dim`` axes.
        moving: ``(batch, *S)`` real; already compensated for rotation and scale.
        temperature: softmax temperature over shifts.
        dim: 2 or 3.
        taper: apodisation of :func:`dpcn_med.solver.spectrum.apodize`.
        refine: arg-max plus an upsampled-DFT refinement (True) or the differentiable soft arg-max (False).
        upsample: refinement factor.

    Returns:
        A :class:`TranslationEstimate`. Shifts are unambiguous up to half the grid per axis (they wrap beyond).
    """
    surface, spectrum = phase_correlation(apodize(fixed, dim, taper), apodize(moving, dim, taper), dim)
    peak = soft_argmax(surface, temperature, dim)
    if refine:
        shift, height = refine_peak(spectrum, peak.index, tuple(fixed.shape[-dim:]), upsample=upsample)
    else:
        shift, height = peak.shift, surface.flatten(1).max(-1).values
    return TranslationEstimate(shift=shift, peak=peak, height=height)
