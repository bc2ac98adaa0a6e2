"""LC2 in torch: the estimator's values, its windows, the ultrasound's levels and the refinement that scores it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.cli import _flag_message
from dpcn_med.errors import InputError
from dpcn_med.evaluation import moved_copy, target_registration_error
from dpcn_med.geometry import homogeneous_matrix, similarity_transform
from dpcn_med.lc2 import MIN_SCORED_WINDOWS, negative_lc2
from dpcn_med.local_search import correlation_level, fixed_samples, pyramid_level, sample, volume
from dpcn_med.outputs import RegistrationSettings
from dpcn_med.refine import Refinement, choose_and_refine, correlation_levels, metric_masks, ultrasound_side
from dpcn_med.registration import register

CPU = torch.device("cpu")


def _random(shape: tuple[int, ...], seed: int) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


class TestEstimator:
    def test_a_local_linear_combination_is_explained_whole(self):
        """Each window its own weights, as the ultrasound's gain changes with depth: LC2 is 1."""
        intensity, gradient = _random((1, 40, 343), 0), _random((1, 40, 343), 1)
        alpha, beta, gamma = _random((1, 40, 1), 2), _random((1, 40, 1), 3) - 0.5, _random((1, 40, 1), 4)
        ultrasound = alpha * intensity + beta * gradient + gamma
        valid = torch.ones_like(intensity, dtype=torch.bool)
        assert negative_lc2(ultrasound, intensity, gradient, valid).item() == pytest.approx(-1.0, abs=1e-3)

    def test_independent_images_explain_almost_nothing(self):
        intensity, gradient, ultrasound = (_random((1, 200, 343), seed) for seed in (0, 1, 2))
        valid = torch.ones_like(intensity, dtype=torch.bool)
        # a fit of two regressors to 343 independent values explains about 2 / 342 of their variance
        assert -0.02 < negative_lc2(ultrasound, intensity, gradient, valid).item() < 0

    def test_the_other_image_may_scale_and_shift_freely(self):
        intensity, gradient, noise = (_random((1, 60, 343), seed) for seed in (0, 1, 2))
        ultrasound = intensity - 2 * gradient + noise
        valid = torch.ones_like(intensity, dtype=torch.bool)
        value = negative_lc2(ultrasound, intensity, gradient, valid)
        # within [0, 1], as the levels scale them (the ridge is absolute)
        other = negative_lc2(3 * ultrasound + 1, 0.5 * intensity + 0.2, 0.8 * gradient, valid)
        assert -0.95 < value.item() < -0.5
        assert other.item() == pytest.approx(value.item(), abs=1e-3)

    def test_windows_mostly_invalid_do_not_count_and_too_few_do_not_overlap(self):
        intensity, gradient = _random((2, 30, 343), 0), _random((2, 30, 343), 1)
        ultrasound = intensity.clone()
        ultrasound[:, 10:] = _random((2, 20, 343), 2)  # windows 10 on explain nothing...
        valid = torch.ones_like(intensity, dtype=torch.bool)
        valid[0, 10:, :200] = False  # ...and in pose 0 they are mostly outside: only the explained ones count
        valid[1, MIN_SCORED_WINDOWS - 1:] = False  # pose 1 scores too few windows
        value = negative_lc2(ultrasound, intensity, gradient, valid)
        assert value[0].item() == pytest.approx(-1.0, abs=1e-3) and value[1].item() == math.inf

    def test_the_gradient_is_the_derivative(self):
        intensity, gradient, ultrasound = (_random((1, 20, 64), seed) for seed in (0, 1, 2))
        ultrasound = ultrasound + intensity
        valid = torch.ones_like(intensity, dtype=torch.bool)
        intensity.requires_grad_(True)
        value = negative_lc2(ultrasound, intensity, gradient, valid)
        derivative, = torch.autograd.grad(value.sum(), intensity)
        direction = _random(intensity.shape, 3) - 0.5
        step = 1e-6
        with torch.no_grad():
            moved = negative_lc2(ultrasound, intensity + step * direction, gradient, valid)
        assert (moved - value).item() / step == pytest.approx((derivative * direction).sum().item(), rel=1e-3)


def _phantom(size: int = 40, spacing: float = 2.0, seed: int = 0) -> sitk.Image:
    """A smooth random volume with structure at a few voxels, an oblique direction and an origin."""
    array = np.random.default_rng(seed).random((size,) * 3).astype(np.float32)
    image = sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(array), 1.5)
    image = sitk.RescaleIntensity(image, 0.0, 100.0)
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin((-30.0, 12.0, 40.0))
    image.SetDirection(sitk.VersorTransform((1, -2, 1), 0.3).GetMatrix())
    return image


def _ultrasound_of(image: sitk.Image, box: tuple[int, int]) -> sitk.Image:
    """An 'ultrasound' of ``image``: its gradient magnitude (boundaries echo) plus a little of its intensity, on the
    sub-box ``box`` (first voxel, voxels) of its grid, 0 outside a ball inside that box."""
    start, length = box
    region = sitk.RegionOfInterest(image, [length] * 3, [start] * 3)
    echoes = sitk.GradientMagnitude(region) + 0.1 * region
    array = sitk.GetArrayFromImage(echoes)
    centre = (np.asarray(array.shape) - 1) / 2
    ball = np.linalg.norm(np.indices(array.shape).T - centre, axis=-1).T <= length / 2
    result = sitk.GetImageFromArray(np.where(ball, array + 1e-3, 0).astype(np.float32))
    result.CopyInformation(echoes)
    return result


class TestLevel:
    def test_the_windows_hold_the_ultrasound_at_their_points(self):
        ultrasound = _ultrasound_of(_phantom(), (6, 26))
        us_volume = volume(ultrasound, CPU)
        inside = us_volume.values > 0
        other = pyramid_level(volume(_phantom(), CPU), [1, 1, 1], 0.0)
        samples = fixed_samples(us_volume, None, 1000, 32, np.zeros(3), torch.Generator().manual_seed(0))
        level = correlation_level(us_volume, inside, other, None, samples, ultrasound_fixed=True, window=5)
        windows, voxels = level.ultrasound.shape[1:]
        assert voxels == 125 and level.points.shape == (windows * voxels, 3)
        # every window at least half inside, and together they hold every voxel of the ball but the sparse edges
        assert (level.inside.sum(-1) >= 0.5 * voxels).all()
        assert 0.8 * inside.sum() < level.inside.sum() <= inside.sum()
        values, within = sample(us_volume, level.points.unsqueeze(0))
        raw = values.reshape(level.ultrasound.shape)[level.inside]
        low, high = raw.min(), raw.max()
        torch.testing.assert_close(level.ultrasound[level.inside], (raw - low) / (high - low), atol=1e-5, rtol=0)
        assert within.all()

    def test_the_true_pose_scores_best_from_either_side(self):
        whole = _phantom()
        ultrasound = _ultrasound_of(whole, (6, 26))
        centre = np.asarray(ultrasound.TransformContinuousIndexToPhysicalPoint([12.5] * 3))
        settings = Refinement(shrink_factors=(1,), smoothing_mm=(0.0,))
        for side, (fixed, moving) in (("fixed", (ultrasound, whole)), ("moving", (whole, ultrasound))):
            level = correlation_levels(fixed, moving, (None, None), centre, side, settings)[0]
            shifts = torch.zeros(7, 6, dtype=torch.float64)
            shifts[1:, 3:] = 4.0 * torch.cat([torch.eye(3), -torch.eye(3)]).double()
            values = level.metric(torch.eye(4, dtype=torch.float64).expand(7, 4, 4), shifts, centre)
            assert int(values.argmin()) == 0 and values[0] < -0.5, side


class TestRefinement:
    @pytest.mark.parametrize("side", ["fixed", "moving"])
    def test_lc2_refines_an_ultrasound_a_few_millimetres_off(self, side):
        whole = _phantom()
        ultrasound = _ultrasound_of(whole, (6, 26))
        centre = np.asarray(ultrasound.TransformContinuousIndexToPhysicalPoint([12.5] * 3))
        truth = sitk.Euler3DTransform(centre.tolist(), 0.05, -0.03, 0.1, (3.0, -2.0, 4.0))
        fixed, moving = (ultrasound, moved_copy(whole, truth)) if side == "fixed" else (whole, moved_copy(
            ultrasound, truth))
        offset = sitk.Euler3DTransform(centre.tolist(), 0.02, 0.0, -0.02, (1.5, 1.0, -1.0))
        start = similarity_transform(homogeneous_matrix(truth) @ homogeneous_matrix(offset), centre, rigid=True)
        corners = np.array([ultrasound.TransformIndexToPhysicalPoint([int(c) for c in corner * 25])
                            for corner in np.array(list(np.ndindex(2, 2, 2)))])
        masks = metric_masks(None, sitk.Cast(fixed > 0, sitk.sitkUInt8), None, Refinement(), ultrasound=side)
        choice = choose_and_refine(fixed, moving, [start], masks, ultrasound=side)
        assert choice.similarity == "lc2" and choice.refined and choice.fixed_entropy is None
        assert target_registration_error(start, truth, corners) > 2.0
        assert target_registration_error(choice.fixed_to_moving, truth, corners) < 0.5

    def test_the_ultrasound_side_follows_the_modalities(self):
        assert ultrasound_side("us", "mr") == "fixed" and ultrasound_side("ct", "us") == "moving"
        assert ultrasound_side("us", "us") is None and ultrasound_side("ct", "mr") is None

    def test_a_fixed_ultrasound_is_sampled_whole_without_a_mask_of_its_brightest_echoes(self):
        foreground = sitk.Cast(_phantom() > 50, sitk.sitkUInt8)
        assert metric_masks(None, foreground, None, Refinement(), ultrasound="fixed") == (None, None)
        assert metric_masks(None, foreground, None, Refinement(), ultrasound="moving")[0] is not None

    def test_an_unknown_side_is_refused(self):
        whole = _phantom()
        start = similarity_transform(np.eye(4), np.zeros(3), rigid=True)
        with pytest.raises(InputError, match="ultrasound is 'left'"):
            choose_and_refine(whole, whole, [start], (None, None), ultrasound="left")

    def test_a_registration_with_an_ultrasound_refines_and_reports_by_lc2(self):
        whole = _phantom()
        ultrasound = _ultrasound_of(whole, (6, 26))
        result = register(ultrasound, whole, fixed_modality="us", moving_modality="mr")
        summary = result.to_dict()
        assert result.similarity == "lc2" and summary["similarity"].startswith("LC2")
        assert summary["negative_lc2"] == result.metric and "mattes_mutual_information" not in summary
        assert len(summary["candidate_negative_lc2"]) == len(result.candidate_metrics) > 1
        mattes = register(whole, whole, fixed_modality="mr", moving_modality="mr").to_dict()
        assert mattes["similarity"] == "Mattes mutual information" and "mattes_mutual_information" in mattes
        # nothing verifies an ultrasound result yet: it is flagged whatever its confidence, and says why
        settings = RegistrationSettings()
        assert result.success_probability is None and settings.flagged({**summary, "confidence": 1.0})
        assert not settings.flagged({**mattes, "success_probability": 0.99})
        assert "not verified" in _flag_message(summary, settings, "look at it")
