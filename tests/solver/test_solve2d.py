"""The public 2-D entry point: full-turn rotation, scale and translation of real slices."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import rotation_2d
from dpcn_med.solver import StageTemperatures, solve2d
from dpcn_med.synth import Pose, random_poses
from tests.conftest import axial_slice


class TestValidation:
    def test_volume_given_to_solve2d_points_at_solve(self):
        with pytest.raises(InputError, match=r"expected \(B, 1, N, N\) \(for the other dimension use solve\)"):
            solve2d(torch.zeros(1, 1, 8, 8, 8), torch.zeros(1, 1, 8, 8, 8))

    @pytest.mark.parametrize(("options", "message"), [
        ({"iterations": 0}, r"iterations is 0; expected an integer >= 1"),  # was run as 1 pass, silently
        ({"iterations": -3}, r"iterations is -3; expected an integer >= 1"),
        ({"upsample": 0}, r"upsample is 0; expected an integer >= 1"),  # was a NaN scale and translation
        ({"log_polar_angles": 1}, r"log_polar_angles is 1; expected an integer >= 12"),  # was a wrong pose
        ({"log_polar_angles": 8}, r"log_polar_angles is 8; expected an integer >= 12"),  # was up to 174 degrees off
        ({"log_polar_radii": 1}, r"log_polar_radii is 1; expected an integer >= 20"),  # was a ZeroDivisionError
        ({"log_polar_radii": 16}, r"log_polar_radii is 16; expected an integer >= 20"),  # was up to 59 degrees off
        ({"log_polar_band": (0.9, 0.03)}, r"log_polar_band is \(0\.9, 0\.03\); expected \(low, high\)"),
        ({"log_polar_band": (0.0, 0.9)}, r"log_polar_band is \(0\.0, 0\.9\); expected \(low, high\)"),
        ({"iteration": 2}, r"solver option 'iteration' is unknown \(did you mean 'iterations'\?\)"),  # a TypeError
    ], ids=["iterations 0", "iterations -3", "upsample 0", "angles 1", "angles 8", "radii 1", "radii 16",
            "band reversed", "band from 0", "unknown option"])
    def test_bad_settings_are_refused(self, options, message):
        image = torch.zeros(1, 1, 32, 32)
        with pytest.raises(InputError, match=message):
            solve2d(image, image, **options)

    def test_zero_temperature_is_refused(self):  # was a NaN confidence
        with pytest.raises(InputError, match=r"translation temperature is 0\.0; expected a finite number >= 1e-12"):
            solve2d(torch.zeros(1, 1, 16, 16), torch.zeros(1, 1, 16, 16),
                    temperatures=StageTemperatures(translation=0.0))

    def test_empty_batch(self):
        with pytest.raises(InputError, match=r"fixed holds no grids \(batch size 0"):
            solve2d(torch.zeros(0, 1, 16, 16), torch.zeros(0, 1, 16, 16))

    @pytest.mark.parametrize("size", [8, 16, 30])
    def test_small_images_are_refused(self, size):  # 8-24 passed and gave poses up to 180 degrees off
        image = torch.zeros(1, 1, size, size)
        with pytest.raises(InputError, match=rf"fixed grid size is {size}; expected an even N >= 32 \(smaller 2-D"):
            solve2d(image, image)

    def test_non_square(self):
        with pytest.raises(InputError, match="fixed grid is not cubic"):
            solve2d(torch.zeros(1, 1, 16, 32), torch.zeros(1, 1, 16, 32))


def _failures(name: str, count: int, seed: int, mode: str = "similarity") -> list[tuple[float, float, float]]:
    fixed = axial_slice(name, 256)
    failures = []
    for pose in random_poses(count, 256, seed, similarity=mode == "similarity", dim=2, max_shift=50.0):
        result = solve2d(fixed, pose.moving_from(fixed), mode)
        errors = pose.errors(result.rotation[0], result.scale[0], result.translation[0])
        if not (errors[0] < 1.0 and errors[1] < 1.0 and errors[2] < 0.01):
            failures.append(errors)
    return failures


class TestRecovery:
    """Rotation uniform in [0, 360) degrees, scale 0.8-1.2, translation up to 50 px on 256 x 256 slices."""

    @pytest.mark.parametrize("name", ["seg3d/MR.nii.gz", "stroke/T1.nii.gz"])
    def test_real_slices_within_1_degree_1_pixel_1_percent(self, name):
        assert _failures(name, 8, seed=21) == []

    def test_template_slice_rigid(self):
        assert _failures("mni", 4, seed=22, mode="rigid") == []

    @pytest.mark.parametrize("angle", [179.0, -91.0, 3.0])
    def test_half_turn_ambiguity_is_resolved(self, angle):
        fixed = axial_slice("mni", 256)
        pose = Pose(rotation_2d(torch.tensor(math.radians(angle), dtype=torch.float64)), 1.05,
                    torch.tensor([10.0, -20.0], dtype=torch.float64))
        result = solve2d(fixed, pose.moving_from(fixed))
        assert pose.errors(result.rotation[0], result.scale[0], result.translation[0])[0] < 1.0
        assert result.confidence.item() > 0.5


    def test_small_rotation_of_a_sparse_phantom_is_not_pinned_to_zero(self):
        # Whitened log-polar correlation once returned 0 degrees here: both resampled grids share a zero-shift pattern.
        fixed = axial_slice("mridir/mridir_t2_1p5mm.nii.gz", 256)
        pose = Pose(rotation_2d(torch.tensor(math.radians(1.66), dtype=torch.float64)), 0.98,
                    torch.tensor([-14.6, 0.9], dtype=torch.float64))
        result = solve2d(fixed, pose.moving_from(fixed))
        rotation_error, translation_error, scale_error = pose.errors(result.rotation[0], result.scale[0],
                                                                    result.translation[0])
        assert rotation_error < 0.2 and translation_error < 0.5 and scale_error < 0.002


class TestDegenerate:
    def test_empty_images_give_low_confidence_and_no_nan(self):
        result = solve2d(torch.zeros(1, 1, 64, 64), torch.zeros(1, 1, 64, 64))
        assert all(torch.isfinite(v).all() for v in (result.rotation, result.scale, result.translation))
        assert result.confidence.item() < 0.01


class TestGradients:
    def test_gradcheck_wrt_both_images_and_the_temperatures(self):
        generator = torch.Generator().manual_seed(23)
        fixed = torch.nn.functional.avg_pool2d(torch.randn(1, 1, 32, 32, generator=generator, dtype=torch.float64),
                                               3, 1, 1)
        moving = fixed.roll((2, -1), (-1, -2))
        rotation_t = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
        translation_t = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)

        def pose_of(f, m, t1, t2):
            result = solve2d(f, m, refine=False, iterations=1, temperatures=StageTemperatures(rotation=t1,
                                                                                               translation=t2))
            return result.angle, result.scale, result.translation, result.confidence

        assert torch.autograd.gradcheck(pose_of, (fixed.requires_grad_(), moving.requires_grad_(), rotation_t,
                                                  translation_t), fast_mode=True)
