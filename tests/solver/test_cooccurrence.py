"""Co-occurrence spectra: near-invariance to a reordering of the intensities, their rotation candidates, and how
they join the solver's other sources."""

from __future__ import annotations

import pytest
import torch

from dpcn_med.solver import solve
from dpcn_med.solver.cooccurrence import cooccurrence_spectrum
from dpcn_med.solver.entropy import soft_bins
from dpcn_med.solver.spectrum import magnitude_spectrum
from dpcn_med.synth import random_poses
from tests.solver.test_entropy import LEVELS, REORDERED, quantised_head


def relative_difference(first: torch.Tensor, second: torch.Tensor) -> float:
    return ((first - second).norm() / first.norm()).item()


class TestCooccurrenceSpectrum:
    def test_a_reordering_of_the_intensities_barely_changes_it(self):
        """Hard bins would give the same spectrum (the bins are permuted, and the sum over them does not see the
        order); the soft bins spread each level to its neighbours, which a reordering changes, so the spectra agree
        closely rather than exactly. The raw volumes' magnitude spectra do not."""
        labels = quantised_head(32)[:, 0]
        monotonic, reordered = labels / (LEVELS - 1), REORDERED[labels.long()]
        raw = relative_difference(magnitude_spectrum(monotonic, 3, 0.25), magnitude_spectrum(reordered, 3, 0.25))
        cooccurring = relative_difference(cooccurrence_spectrum(monotonic, LEVELS, 0.25),
                                          cooccurrence_spectrum(reordered, LEVELS, 0.25))
        assert raw > 0.3  # measured 0.39
        assert cooccurring < 0.25 * raw  # measured 0.066

    def test_its_shape_sign_and_a_constant_volume(self):
        torch.manual_seed(0)
        spectrum = cooccurrence_spectrum(torch.rand(2, 16, 16, 16, dtype=torch.float64), 8, 0.25)
        assert spectrum.shape == (2, 16, 16, 16) and spectrum.dtype == torch.float64
        assert spectrum.amin() >= 0 and spectrum.isfinite().all()
        # Each bin of a constant volume is constant: nothing is left once the window-weighted mean is removed.
        assert cooccurrence_spectrum(torch.full((1, 16, 16, 16), 3.0), 8, 0.25).abs().amax() == 0

    def test_it_is_the_power_summed_over_the_bins(self):
        """Two bins that partition the voxels (memberships m and 1 - m): the apodised second is minus the first, so
        the spectrum is sqrt(2) times either bin's magnitude spectrum."""
        volume = (torch.rand(1, 16, 16, 16, generator=torch.Generator().manual_seed(2)) > 0.5).double()
        first = soft_bins(volume, 2)[0]
        torch.testing.assert_close(cooccurrence_spectrum(volume, 2, 0.25),
                                   2 ** 0.5 * magnitude_spectrum(first, 3, 0.25))


class TestCooccurrenceCandidates:
    @pytest.mark.parametrize("seed", [0, 3])
    def test_they_hold_the_truth_under_a_non_monotonic_map(self, seed):
        """The same head with its tissue levels reordered on the moving side: with the co-occurrence spectra's
        candidates beside the raw volumes' (no entropy images), the nearest is within 3 degrees and nearer than the
        volumes' alone (measured: 2.5 and 1.8 degrees against 3.7 and 5.8)."""
        labels = quantised_head(64)
        pose = random_poses(1, 64, seed=seed)[0]
        moving = pose.moving_from(REORDERED[labels.long()])
        nearest = {bins: solve(labels / (LEVELS - 1), moving, bandwidth=32, entropy_bins=0,
                               cooccurrence_bins=bins).ranking.errors(pose.rotation[None].to(torch.float32)).amin().item()
                   for bins in (0, 8)}
        assert nearest[8] < 3.0
        assert nearest[8] < 0.85 * nearest[0]

    def test_their_candidates_join_the_others(self):
        """A source of its own: near-duplicates are dropped within it, so the candidates kept with it are those kept
        without it and those it adds."""
        labels = quantised_head(32)
        pose = random_poses(1, 32, seed=4)[0]
        fixed, moving = labels / (LEVELS - 1), pose.moving_from(REORDERED[labels.long()])
        without = solve(fixed, moving, "rigid", entropy_bins=8)
        with_it = solve(fixed, moving, "rigid", entropy_bins=8, cooccurrence_bins=8)
        assert int(with_it.candidates[0]) > int(without.candidates[0])
        kept = with_it.ranking.rotation[0][with_it.ranking.score[0] > float("-inf")]
        before = without.ranking.rotation[0][without.ranking.score[0] > float("-inf")]
        assert all(bool(((kept - rotation).flatten(1).abs().amax(-1) < 1e-5).any()) for rotation in before)
