"""Entropy images: near-invariance to a reordering of the intensities, range, smoothing, rotation candidates and
their ranking."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from dpcn_med.solver import SolverConfig, solve
from dpcn_med.solver.entropy import _smooth, entropy_image
from dpcn_med.solver.solve3d import candidate_scores
from dpcn_med.synth import random_poses
from tests.conftest import volume_grid

LEVELS = 8
REORDERED = torch.tensor([0.0, 5, 2, 7, 1, 6, 3, 4]) / (LEVELS - 1)
"""A one-to-one, non-monotonic map of eight tissue levels (two contrasts ordering the tissues differently); the
lowest and highest level keep their values, so each volume's intensity range, and so its bins, stay as they were."""

FLOOR = 0.3679
"""The entropy of a uniform region whose value lies on a bin centre: its soft bins' own spread (measured)."""


def quantised_head(size: int) -> torch.Tensor:
    """The MNI head on a ``size^3`` grid as ``LEVELS`` integer tissue labels, ``(1, 1, N, N, N)``."""
    head = volume_grid("mni", size)
    return (head * (LEVELS - 0.001) / head.max()).floor().clamp(0, LEVELS - 1)


class TestEntropyImage:
    def test_a_reordering_of_the_intensities_barely_changes_it(self):
        """Hard bins would give the same image; the soft bins spread each level to its neighbours, which a reordering
        changes, so the images agree closely rather than exactly. Inside the head the raw intensities do not."""
        labels = quantised_head(32)[:, 0]
        monotonic, reordered = labels / (LEVELS - 1), REORDERED[labels.long()]
        inside = labels > 0

        def correlation(first, second):
            return torch.corrcoef(torch.stack([first[inside], second[inside]]))[0, 1].item()

        assert correlation(monotonic, reordered) < 0.0  # measured -0.13
        first, second = entropy_image(monotonic, LEVELS, 1.0), entropy_image(reordered, LEVELS, 1.0)
        assert correlation(first, second) > 0.95  # measured 0.97
        assert (first - second).abs().amax() < 0.1 * first.amax()  # measured 0.15 of 2.0 nats
        # Boundaries are high; uniform tissue and the background are at the floor of one voxel's soft bins.
        assert first.amax() > 1.0 and first[:, 0, 0, 0].item() == pytest.approx(FLOOR, abs=1e-4)

    def test_its_range_and_a_constant_volume(self):
        torch.manual_seed(0)
        image = entropy_image(torch.rand(2, 16, 16, 16, dtype=torch.float64), 16, 2.0)
        assert image.shape == (2, 16, 16, 16) and image.dtype == torch.float64
        assert image.amin() >= 0 and image.amax() <= math.log(16) + 1e-9
        constant = entropy_image(torch.full((1, 16, 16, 16), 3.0), 8, 1.0)
        torch.testing.assert_close(constant, torch.full_like(constant, FLOOR), atol=1e-4, rtol=0)

    def test_gradients_reach_the_volume(self):
        volume = torch.rand(1, 16, 16, 16, dtype=torch.float64, requires_grad=True)
        entropy_image(volume, 8, 1.0).sum().backward()
        assert volume.grad is not None and volume.grad.isfinite().all() and volume.grad.abs().amax() > 0

    @pytest.mark.parametrize("sigma", [0.5, 1.0, 2.5])
    def test_the_smoothing_is_a_gaussian_with_replicated_edges(self, sigma):
        torch.manual_seed(1)
        volumes = torch.rand(3, 20, 20, 20, dtype=torch.float64)
        radius = max(1, math.ceil(3 * sigma))
        taps = torch.arange(-radius, radius + 1, dtype=torch.float64)
        kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
        kernel = kernel / kernel.sum()
        expected = volumes[:, None]
        for axis in range(3):
            shape, padding = [1, 1, 1, 1, 1], [0] * 6
            shape[2 + axis], padding[2 * (2 - axis):2 * (2 - axis) + 2] = kernel.numel(), [radius, radius]
            expected = F.conv3d(F.pad(expected, padding, mode="replicate"), kernel.view(shape))
        torch.testing.assert_close(_smooth(volumes, sigma), expected[:, 0])


class TestEntropyCandidates:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_they_hold_the_truth_under_a_non_monotonic_map(self, seed):
        """The same head with its tissue levels reordered on the moving side: the entropy images' candidates hold the
        truth within 3 degrees, and at most 0.6 times as far as the raw volumes' nearest (measured: 1.4-2.0 degrees
        against 4.8-7.6 on one machine, 1.4-2.0 against 3.2-4.8 on an AVX-512 one; ratios 0.35-0.44)."""
        labels = quantised_head(64)
        pose = random_poses(1, 64, seed=seed)[0]
        moving = pose.moving_from(REORDERED[labels.long()])
        nearest = {bins: solve(labels / (LEVELS - 1), moving, bandwidth=32, entropy_bins=bins).ranking.errors(
            pose.rotation[None].to(torch.float32)).amin().item() for bins in (0, 8)}
        assert nearest[8] < 3.0
        assert nearest[8] < 0.6 * nearest[0]


class TestExtraEntropySources:
    def test_each_source_adds_its_own_candidates(self):
        """A second entropy source's candidates join the others', near-duplicates dropped within each source: the
        candidates kept with 8 bins and an extra 16-bin source are those kept with either alone (each beside the
        volumes'), and the volumes' once."""
        labels = quantised_head(32)
        pose = random_poses(1, 32, seed=4)[0]
        fixed, moving = labels / (LEVELS - 1), pose.moving_from(REORDERED[labels.long()])

        counts = []

        def kept(**options):
            """The plausible candidates (ranked), after counting every one left by the near-duplicate drop."""
            result = solve(fixed, moving, "rigid", **options)
            counts.append(int(result.candidates[0]))
            return result.ranking.rotation[0][result.ranking.score[0] > float("-inf")]

        volumes, eight, sixteen = kept(entropy_bins=0), kept(entropy_bins=8), kept(entropy_bins=16)
        both = kept(entropy_bins=8, extra_entropy_bins=(16,))
        assert counts[0] < counts[1] and counts[0] < counts[2]
        assert counts[3] == counts[1] + counts[2] - counts[0]
        assert volumes.shape[0] < eight.shape[0] and volumes.shape[0] < sixteen.shape[0]
        assert both.shape[0] == eight.shape[0] + sixteen.shape[0] - volumes.shape[0]

        def found(rotation, among):
            return bool(((among - rotation).flatten(1).abs().amax(-1) < 1e-5).any())

        assert all(found(rotation, both) for rotation in torch.cat([eight, sixteen]))
        # The extra source alone, without the ranking's entropy images: the volumes' and the 16-bin images'.
        alone = kept(entropy_bins=0, extra_entropy_bins=(16,))
        assert counts[4] == counts[2]
        assert alone.shape[0] == sixteen.shape[0] and all(found(rotation, alone) for rotation in sixteen)


class TestEntropyRanking:
    @pytest.mark.parametrize(("weight", "extra"), [(0.0, ()), (1.0, ()), (2.5, ()), (1.0, (16,))])
    def test_the_finalists_rank_by_both_relative_peaks(self, weight, extra):
        """The finalists' scores are their translation peaks on the volumes and on the entropy images of
        ``entropy_bins`` (not of ``extra_entropy_bins``, which only propose), each divided by its best among them,
        summed with the weight: recomputed here from :func:`candidate_scores`."""
        labels = quantised_head(32)
        pose = random_poses(1, 32, seed=3)[0]
        fixed, moving = labels / (LEVELS - 1), pose.moving_from(REORDERED[labels.long()])
        config = SolverConfig(entropy_ranking_weight=weight, extra_entropy_bins=extra)
        ranking = solve(fixed, moving, "rigid", config=config).ranking
        count = min(config.finalists, int((ranking.score[0] > float("-inf")).sum()))
        assert count >= 2
        linear = ranking.rotation[:, :count]
        peaks = candidate_scores(fixed[:, 0], moving[:, 0], linear, config.finalist_size, config.taper)
        images = [entropy_image(volume[:, 0], config.entropy_bins, config.entropy_sigma) for volume in (fixed, moving)]
        image_peaks = candidate_scores(*images, linear, config.finalist_size, config.taper)
        # Weight 0: the volumes' peaks as they are, as before the entropy ranking.
        expected = peaks / peaks.amax() + weight * image_peaks / image_peaks.amax() if weight else peaks
        torch.testing.assert_close(ranking.score[:, :count], expected, rtol=1e-4, atol=1e-5)
        assert (ranking.score[0, :count].diff() <= 0).all()
