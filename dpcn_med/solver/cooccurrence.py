"""Co-occurrence spectra: a magnitude spectrum that a one-to-one intensity map between two volumes barely changes.

The magnitude spectrum of a volume is the Fourier transform of its autocorrelation, ``sum_x v(x) v(x + d)``: it
depends on which tissue is bright. Split the intensities into soft bins instead (memberships ``m_i``, as the entropy
images' histograms, :func:`dpcn_med.solver.entropy.soft_bins`), and sum the bins' power spectra:
``sum_i |FFT(m_i)|^2`` is the Fourier transform of ``sum_i sum_x m_i(x) m_i(x + d)``, how often two voxels ``d``
apart fall in the same bin. Relabelling the intensities, even in a non-monotonic order (two MR contrasts that order the
tissues differently, CT and MR), permutes the bins, and the sum over them does not see the order (nearly: each soft
bin spreads a level over its neighbours, which a reordering changes). Like the magnitude spectrum it is invariant to
translation and turns with the volume, so it goes through the same spheres and SO(3) correlation, one more source of
rotation candidates (:attr:`dpcn_med.solver.SolverConfig.cooccurrence_bins`; why: docs/design_notes/solver.md).
"""

from __future__ import annotations

from torch import Tensor

from dpcn_med.solver.entropy import soft_bins
from dpcn_med.solver.spectrum import magnitude_spectrum


def cooccurrence_spectrum(volume: Tensor, bins: int, taper: float) -> Tensor:
    """``sqrt(sum_i |FFT(m_i)|^2)`` over the apodised soft-bin memberships ``m_i`` of each volume.

    Args:
        volume: ``(batch, N, N, N)`` real grids.
        bins: soft histogram bins over each volume's own intensity range, at least 2.
        taper: the apodisation window's taper (:func:`dpcn_med.solver.spectrum.spherical_window`).

    Returns:
        ``(batch, N, N, N)`` non-negative, ``fftshift``-ed as :func:`dpcn_med.solver.spectrum.magnitude_spectrum`;
        zero for a constant volume.
    """
    power = None
    for membership in soft_bins(volume, bins):  # one bin at a time: all at once would hold `bins` spectra
        part = magnitude_spectrum(membership, 3, taper).square()
        power = part if power is None else power + part
    return power.sqrt()
