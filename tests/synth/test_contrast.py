"""Simulated modalities: random intensity maps, bias field, blur, thick slices, noise and their chain."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.synth import (
    ContrastConfig,
    bias_field,
    blur,
    noise,
    random_intensity_map,
    random_modality,
    resolution_loss,
)


def _seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _ramp(batch: int, size: int = 16, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Intensities rising along x from 0 (background) to 1, the same in every volume: ``(batch, 1, N, N, N)``."""
    ramp = torch.linspace(0.0, 1.0, size, dtype=dtype)
    return ramp.expand(batch, 1, size, size, size).contiguous()


def _tissues(size: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Four tissue classes in nested boxes around an off-centre core, background 0: (volume, labels)."""
    labels = torch.zeros(size, size, size, dtype=torch.long)
    for label, (low, high) in enumerate([(2, 14), (4, 12), (6, 9)], start=1):
        labels[low:high, low:high + 1, low - 1:high] = label
    return torch.tensor([0.0, 0.3, 0.9, 0.6])[labels][None, None].double(), labels


FUNCTIONS = [random_intensity_map, bias_field, blur, resolution_loss, noise, random_modality]


@pytest.mark.parametrize("function", FUNCTIONS, ids=lambda f: f.__name__)
class TestCommon:
    def test_reproducible_from_a_seed_and_different_with_another(self, function):
        volume, _ = _tissues()
        volume = volume.expand(3, -1, -1, -1, -1)
        first, again, other = (function(volume, _seeded(seed)) for seed in (5, 5, 6))
        torch.testing.assert_close(first, again, rtol=0, atol=0)
        assert (first - other).abs().amax() > 1e-3

    def test_shape_device_and_dtype_follow_the_input(self, function, device, dtype):
        volume, _ = _tissues()
        volume = volume.expand(2, -1, -1, -1, -1).to(device, dtype)
        out = function(volume, _seeded(0))
        assert out.shape == volume.shape and out.device == volume.device and out.dtype == dtype
        assert torch.isfinite(out).all()

    @pytest.mark.parametrize("shape,message", [
        ((16, 16, 16), r"shape \(16, 16, 16\); expected a batch of volumes \(B, 1, D, H, W\)"),
        ((1, 2, 8, 8, 8), r"shape \(1, 2, 8, 8, 8\)"),
        # one voxel along an axis divided by zero in the grid's coordinates
        ((1, 1, 8, 3, 8), r"^volume has spatial shape \(8, 3, 8\); expected at least 4 voxels along each axis$"),
    ])
    def test_malformed_volumes_are_refused(self, function, shape, message):
        with pytest.raises(InputError, match=message):
            function(torch.zeros(shape), _seeded(0))

    @pytest.mark.parametrize("other", [torch.long, torch.float16, torch.bfloat16], ids=str)
    def test_other_dtypes_are_refused(self, function, other):
        with pytest.raises(InputError, match=rf"volume has dtype {other}; expected float32 or float64"):
            function(torch.zeros(1, 1, 8, 8, 8, dtype=other), _seeded(0))

    @pytest.mark.parametrize("value", [math.nan, math.inf])
    def test_non_finite_volumes_are_refused(self, function, value):
        volume = _ramp(1)
        volume[0, 0, 3, 4, 5] = value
        with pytest.raises(InputError, match="^volume contains NaN or infinite values; expected finite intensities"):
            function(volume, _seeded(0))


class TestRandomIntensityMap:
    def test_background_stays_zero_and_values_stay_in_the_unit_interval(self):
        volume, labels = _tissues()
        mapped = random_intensity_map(volume.expand(8, -1, -1, -1, -1), _seeded(1))
        assert (mapped[:, 0][:, labels == 0] == 0).all()
        assert (mapped[:, 0][:, labels > 0] > 0).all()
        assert mapped.min() >= 0 and mapped.max() <= 1

    def test_each_tissue_keeps_one_value(self):
        # A map of intensities moves nothing: equal inputs give equal outputs.
        volume, labels = _tissues()
        mapped = random_intensity_map(volume, _seeded(2))[0, 0]
        for label in range(4):
            assert mapped[labels == label].unique().numel() == 1

    def test_non_monotonic_by_default_and_monotonic_on_request(self):
        ramp = _ramp(16)
        steps = random_intensity_map(ramp, _seeded(3), knots=6)[:, 0, 0, 0, 1:].diff(dim=-1)
        reordered = ((steps > 1e-9).any(-1) & (steps < -1e-9).any(-1)).sum().item()
        assert reordered >= 12  # a random 6-knot map is monotonic with probability 2 / 6!
        steps = random_intensity_map(ramp, _seeded(3), knots=6, monotonic=True)[:, 0, 0, 0, 1:].diff(dim=-1)
        assert (steps >= -1e-12).all()

    def test_piecewise_linear_through_its_knots(self):
        mapped = random_intensity_map(_ramp(2, size=21), _seeded(4), knots=5)[:, 0, 0, 0]
        # Knots at inputs 0, 0.25, ..., 1 (every 5th sample of the ramp): the map is linear between them.
        for start in range(0, 20, 5):
            segment = mapped[:, start:start + 6] if start else mapped[:, 1:6]
            torch.testing.assert_close(segment.diff(n=2, dim=-1), torch.zeros_like(segment[:, 2:]), atol=1e-12,
                                       rtol=0)

    @pytest.mark.parametrize("options,message", [
        ({"knots": 1}, "^knots is 1; expected an integer >= 2 and <= 64$"),
        ({"knots": 2.5}, r"^knots is 2.5 \(float\); expected an integer >= 2 and <= 64$"),
        ({"monotonic": "false"}, r"^monotonic is 'false' \(str\); expected True or False$"),
    ])
    def test_bad_arguments(self, options, message):
        with pytest.raises(InputError, match=message):
            random_intensity_map(_ramp(1), _seeded(0), **options)


class TestBiasField:
    def test_smooth_positive_and_bounded(self):
        field = bias_field(torch.ones(8, 1, 16, 16, 16, dtype=torch.float64), _seeded(0), strength=0.3, order=3)
        assert field.min() >= math.exp(-0.3) - 1e-12 and field.max() <= math.exp(0.3) + 1e-12
        assert (field.flatten(1).std(-1) > 1e-3).all()
        # Its log is a polynomial of degree <= 3 along each axis: fourth differences vanish.
        for axis in (2, 3, 4):
            assert field.log().diff(n=4, dim=axis).abs().max() < 1e-10

    def test_multiplicative_so_the_background_stays_zero(self):
        volume, labels = _tissues()
        biased = bias_field(volume.expand(4, -1, -1, -1, -1), _seeded(1))
        assert (biased[:, 0][:, labels == 0] == 0).all()
        assert (biased[:, 0][:, labels > 0] > 0).all()

    def test_zero_strength_is_the_identity(self):
        volume, _ = _tissues()
        torch.testing.assert_close(bias_field(volume, _seeded(2), strength=0.0), volume, rtol=0, atol=0)

    @pytest.mark.parametrize("options,message", [
        ({"order": 0}, "^order is 0; expected an integer >= 1 and <= 10$"),
        ({"strength": math.nan}, "^strength is nan; expected a finite number >= 0 and <= 80$"),
        ({"strength": math.inf}, "^strength is inf; expected a finite number >= 0 and <= 80$"),
        ({"strength": -0.1}, "^strength is -0.1; expected a finite number >= 0 and <= 80$"),
        # exp(100) overflows float32: the background's 0 * inf was NaN.
        ({"strength": 100.0}, "^strength is 100.0; expected a finite number >= 0 and <= 80$"),
    ])
    def test_bad_arguments(self, options, message):
        with pytest.raises(InputError, match=message):
            bias_field(_ramp(1), _seeded(0), **options)

    def test_the_strongest_field_stays_finite_in_float32(self):
        volume, _ = _tissues()
        biased = bias_field(volume.float().expand(8, -1, -1, -1, -1), _seeded(0), strength=80.0)
        assert torch.isfinite(biased).all()


class TestBlur:
    def test_impulse_response_is_a_gaussian_of_the_drawn_sigma(self):
        impulse = torch.zeros(2, 1, 17, 17, 17, dtype=torch.float64)
        impulse[:, 0, 8, 8, 8] = 1.0
        response = blur(impulse, _seeded(0), sigma_range=(1.2, 1.2))
        assert response.sum().item() == pytest.approx(2.0, abs=1e-10)
        ticks = torch.arange(17, dtype=torch.float64) - 8
        for axis in (2, 3, 4):
            marginal = response.sum([a for a in (2, 3, 4) if a != axis])[:, 0]
            assert (marginal * ticks ** 2).sum(-1).tolist() == pytest.approx([1.44, 1.44], rel=0.01)  # 3-sigma kernel

    def test_sigma_is_drawn_per_volume(self):
        impulse = torch.zeros(6, 1, 17, 17, 17, dtype=torch.float64)
        impulse[:, 0, 8, 8, 8] = 1.0
        peaks = blur(impulse, _seeded(1), sigma_range=(0.5, 2.0))[:, 0, 8, 8, 8]
        assert peaks.unique().numel() == 6

    def test_zero_sigma_is_the_identity(self):
        volume, _ = _tissues()
        torch.testing.assert_close(blur(volume, _seeded(0), sigma_range=(0.0, 0.0)), volume, atol=1e-12, rtol=0)

    def test_negative_sigma(self):
        with pytest.raises(InputError, match=r"sigma_range is \(-1.0, 1.0\); expected \(low, high\) with 0 <= low"):
            blur(_ramp(1), _seeded(0), sigma_range=(-1.0, 1.0))

    def test_unbounded_sigma(self):  # a range to draw from must be finite
        with pytest.raises(InputError, match=r"^sigma_range\[1\] is inf; expected a finite number$"):
            blur(_ramp(1), _seeded(0), sigma_range=(0.0, math.inf))


def _high_frequency_share(volume: torch.Tensor, axis: int) -> torch.Tensor:
    """Share of the power above half the Nyquist frequency along ``axis``, per volume (mean removed)."""
    centred = volume - volume.mean(dim=(2, 3, 4), keepdim=True)
    power = torch.fft.rfft(centred, dim=axis).abs() ** 2
    power = power.movedim(axis, -1).flatten(1, -2).sum(1)
    cut = power.shape[-1] // 2
    return power[:, cut:].sum(-1) / power.sum(-1)


class TestResolutionLoss:
    def test_thick_slices_remove_high_frequencies_along_one_axis_only(self):
        white = torch.rand(6, 1, 32, 32, 32, generator=_seeded(7), dtype=torch.float64)
        thick = resolution_loss(white, _seeded(8), factor_range=(3.0, 3.0))
        ratios = torch.stack([_high_frequency_share(thick, a) / _high_frequency_share(white, a) for a in (2, 3, 4)], 1)
        for per_axis in ratios:
            assert (per_axis < 0.3).sum() == 1
            assert ((per_axis - 1).abs() < 0.1).sum() == 2

    def test_axes_differ_between_volumes(self):
        white = torch.rand(8, 1, 16, 16, 16, generator=_seeded(0), dtype=torch.float64)
        thick = resolution_loss(white, _seeded(1), factor_range=(4.0, 4.0))
        smoothed = torch.stack([_high_frequency_share(thick, a) for a in (2, 3, 4)], 1).argmin(1)
        assert smoothed.unique().numel() >= 2

    def test_unit_factor_is_the_identity(self):
        volume, _ = _tissues()
        out = resolution_loss(volume.expand(3, -1, -1, -1, -1), _seeded(0), factor_range=(1.0, 1.0))
        torch.testing.assert_close(out, volume.expand(3, -1, -1, -1, -1), atol=1e-12, rtol=0)

    def test_factor_below_one(self):
        with pytest.raises(InputError, match=r"factor_range is \(0.5, 2.0\); expected \(low, high\) with 1 <= low"):
            resolution_loss(_ramp(1), _seeded(0), factor_range=(0.5, 2.0))


class TestNoise:
    def test_gaussian_noise_has_the_drawn_deviation(self):
        volume = torch.full((2, 1, 32, 32, 32), 0.5, dtype=torch.float64)
        residual = noise(volume, _seeded(0), std_range=(0.05, 0.05), rician=False) - volume
        assert residual.mean().abs() < 2e-3
        assert residual.std().item() == pytest.approx(0.05, rel=0.03)

    def test_rician_noise_makes_the_background_rayleigh(self):
        volume = torch.zeros(2, 1, 32, 32, 32, dtype=torch.float64)
        volume[:, :, 16:] = 1.0
        noisy = noise(volume, _seeded(1), std_range=(0.05, 0.05), rician=True)
        background, signal = noisy[:, :, :16], noisy[:, :, 16:]
        assert background.min() >= 0
        assert background.mean().item() == pytest.approx(0.05 * math.sqrt(math.pi / 2), rel=0.03)
        assert signal.mean().item() == pytest.approx(1.0, abs=3e-3)
        assert signal.std().item() == pytest.approx(0.05, rel=0.05)

    def test_negative_deviation(self):
        with pytest.raises(InputError, match="std_range"):
            noise(_ramp(1), _seeded(0), std_range=(-0.1, 0.1))

    def test_rician_must_be_a_flag(self):
        with pytest.raises(InputError, match=r"^rician is 'no' \(str\); expected True or False$"):
            noise(_ramp(1), _seeded(0), rician="no")


class TestRandomModality:
    def test_in_the_unit_interval_and_tissue_order_varies(self):
        volume, labels = _tissues()
        out = random_modality(volume.expand(12, -1, -1, -1, -1), _seeded(0))
        assert out.min() >= 0 and out.max() <= 1
        # Median of the brightest input tissue minus that of the middle one: both signs occur across draws.
        bright = out[:, 0][:, labels == 2].median(-1).values
        middle = out[:, 0][:, labels == 3].median(-1).values
        assert ((bright > middle).any() and (bright < middle).any()).item()

    @pytest.mark.parametrize("options,message", [
        ({"bias_strength": 100.0}, r"^bias_strength is 100.0; expected a finite number >= 0 and <= 80$"),
        ({"knots": 10 ** 8}, r"^knots is 100000000; expected an integer >= 2 and <= 64$"),
        ({"bias_order": 40}, r"^bias_order is 40; expected an integer >= 1 and <= 10$"),
        # sigma 1e4 took 33 s and left a blank volume; std 1e30 a constant one
        ({"sigma_range": (0.0, 1e4)}, r"^sigma_range is \(0.0, 10000.0\); expected \(low, high\) with 0 <= low <= "
                                      r"high <= 8$"),
        ({"noise_std_range": (0.0, 1e30)}, r"^noise_std_range is \(0.0, 1e\+30\); expected \(low, high\) with 0 <= "
                                           r"low <= high <= 1$"),
    ])
    def test_settings_that_give_blank_volumes_or_take_too_long_are_refused(self, options, message):
        with pytest.raises(InputError, match=message):
            ContrastConfig(**options)

    def test_without_acquisition_effects_it_is_an_intensity_map(self):
        quiet = ContrastConfig(bias_strength=0.0, sigma_range=(0.0, 0.0), factor_range=(1.0, 1.0),
                               noise_std_range=(0.0, 0.0))
        volume, labels = _tissues()
        out = random_modality(volume, _seeded(3), quiet)[0, 0]
        assert (out[labels == 0] == 0).all()
        for label in range(1, 4):
            assert out[labels == label].unique().numel() == 1
