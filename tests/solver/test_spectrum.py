"""Step 1: apodisation and the translation-invariant magnitude spectrum."""

from __future__ import annotations

import torch

from dpcn_med.solver.spectrum import apodize, magnitude_spectrum, spherical_window
from tests.conftest import volume_grid


class TestSphericalWindow:
    def test_one_inside_zero_outside_the_inscribed_ball(self):
        window = spherical_window((16, 16, 16), 0.25, dtype=torch.float64)
        assert window[8, 8, 8] == 1.0
        assert window[0, 0, 0] == 0.0 and window[8, 8, 0] == 0.0
        assert ((window >= 0) & (window <= 1)).all()


class TestApodize:
    def test_constant_volume_becomes_zero(self):
        assert apodize(torch.full((1, 12, 12, 12), 7.0, dtype=torch.float64), 3, 0.25).abs().max() < 1e-12


class TestMagnitudeSpectrum:
    def test_invariant_to_translation_of_the_content(self, dtype):
        volume = volume_grid("mni", 32, dtype)[:, 0]
        shifted = volume.roll((3, -2, 1), dims=(1, 2, 3))
        a, b = magnitude_spectrum(volume, 3, 0.25), magnitude_spectrum(shifted, 3, 0.25)
        # The window stays put while the content moves, so invariance is approximate; the head is well inside it.
        assert ((a - b).norm() / a.norm()).item() < 0.08
        assert ((volume - shifted).norm() / volume.norm()).item() > 0.5  # while the volumes themselves differ

    def test_zero_frequency_at_the_grid_centre_and_removed(self):
        volume = volume_grid("mni", 32, torch.float64)[:, 0]
        magnitude = magnitude_spectrum(volume, 3, 0.25)
        assert magnitude[0, 16, 16, 16] < 1e-9 * magnitude.max()
