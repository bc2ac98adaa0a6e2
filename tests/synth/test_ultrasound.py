"""Simulated 3-D ultrasound: cone of view, echoes at boundaries, shadows behind bone, speckle."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from dpcn_med.errors import InputError
from dpcn_med.geometry import affine_points
from dpcn_med.synth import UltrasoundConfig, simulated_ultrasound
from dpcn_med.synth.ultrasound import B_MODE_FLOOR, b_mode

SIZE = 32
ALONG_Z = torch.tensor([0.0, 0.0, 1.0])
# Fixed field of view, so that the tests know the cone.
FIXED_CONE = UltrasoundConfig(half_angle_degrees=(35.0, 35.0), depth_range=(0.8, 0.8))


def _seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _phantom(bone: bool = True) -> torch.Tensor:
    """A cube of soft tissue (0.5) with a bone plate (1.0) across z at z = 14..16: ``(1, 1, 32, 32, 32)``."""
    ct = torch.zeros(1, 1, SIZE, SIZE, SIZE, dtype=torch.float64)
    ct[..., 6:26, 6:26, 6:26] = 0.5
    if bone:
        ct[..., 14:17, 8:24, 8:24] = 1.0
    return ct


def _eroded(mask: torch.Tensor, voxels: int) -> torch.Tensor:
    return -F.max_pool3d(-mask, 2 * voxels + 1, stride=1, padding=voxels)


class TestSimulatedUltrasound:
    def test_zero_outside_a_cone_from_an_apex_before_the_object(self):
        ultrasound, fov = simulated_ultrasound(_phantom(), _seeded(0), probe=ALONG_Z, config=FIXED_CONE)
        assert (ultrasound[fov == 0] == 0).all() and (ultrasound[fov == 1] > 0).float().mean() > 0.5
        # The phantom's centroid is at x = y = -0.5 and its first voxel at z = -10: the apex is 0.05 N before it.
        apex = torch.tensor([-0.5, -0.5, -10.0 - 0.05 * SIZE], dtype=torch.float64)
        offset = affine_points((SIZE,) * 3, torch.eye(3, dtype=torch.float64)[None])[0] - apex
        tangent = offset[..., :2].norm(dim=-1) / offset[..., 2].clamp_min(1e-9)
        reach = 0.8 * SIZE + 0.05 * SIZE
        cone = (offset[..., 2] > 0) & (tangent <= math.tan(math.radians(35.0))) & (offset.norm(dim=-1) <= reach)
        assert torch.equal(fov[0, 0].bool(), cone)

    def test_boundaries_echo_brighter_than_homogeneous_tissue_and_bone_casts_a_shadow(self):
        ultrasound, _ = simulated_ultrasound(_phantom(), _seeded(1), probe=ALONG_Z, config=FIXED_CONE)
        core = ultrasound[0, 0, :, 13:19, 13:19].mean((1, 2))  # along z, near the beam axis
        in_front, bone_surface, behind = core[9:13].mean(), core[13:15].max(), core[18:25].mean()
        assert bone_surface > 2 * in_front
        assert behind < 0.2 * in_front

    def test_without_bone_there_is_no_shadow(self):
        ultrasound, _ = simulated_ultrasound(_phantom(bone=False), _seeded(1), probe=ALONG_Z, config=FIXED_CONE)
        core = ultrasound[0, 0, :, 13:19, 13:19].mean((1, 2))
        assert core[18:25].mean() > 0.5 * core[9:13].mean()

    def test_speckle_is_rayleigh(self):
        # No absorption: the diffuse echo of homogeneous tissue is constant, the speckle alone varies.
        flat = UltrasoundConfig(half_angle_degrees=(45.0, 45.0), depth_range=(0.9, 0.9), attenuation=0.0)
        tissue = _phantom(bone=False)
        ultrasound, fov = simulated_ultrasound(tissue, _seeded(2), probe=ALONG_Z, config=flat)
        homogeneous = (_eroded(fov, 2) * _eroded((tissue > 0).double(), 2)).bool()
        homogeneous[..., :10, :, :] = False  # away from the entry echo
        values = ultrasound[homogeneous]
        assert values.numel() > 1000
        # Rayleigh: mean / std = sqrt(pi / (4 - pi)); its median is sqrt(log 4 / (pi / 2)) ~ 0.94 of its mean.
        assert (values.mean() / values.std()).item() == pytest.approx(math.sqrt(math.pi / (4 - math.pi)), rel=0.08)
        assert (values.median() / values.mean()).item() == pytest.approx(math.sqrt(2 * math.log(4) / math.pi),
                                                                          rel=0.05)

    def test_random_probes_are_reproducible_and_differ_between_seeds(self):
        ct = _phantom().expand(3, -1, -1, -1, -1)
        (first, first_fov), (again, _), (_, other_fov) = (simulated_ultrasound(ct, _seeded(s)) for s in (4, 4, 5))
        torch.testing.assert_close(first, again, rtol=0, atol=0)
        assert not torch.equal(first_fov, other_fov)
        # Different probes for the volumes of one batch.
        assert not torch.equal(first_fov[0], first_fov[1])
        assert first.min() >= 0 and first.max() <= 1

    def test_device_and_dtype_follow_the_input(self, device, dtype):
        ct = _phantom().to(device, dtype)
        ultrasound, fov = simulated_ultrasound(ct, _seeded(0))
        for out in (ultrasound, fov):
            assert out.shape == ct.shape and out.device == ct.device and out.dtype == dtype

    @pytest.mark.parametrize("options", [
        {"impedance_gain": 30.0},  # exp(impedance_gain * ct) overflowed float32 from a gain of 89: inf / inf, NaN
        {"attenuation": 100.0, "bone_attenuation": 1000.0},  # strongest absorption: cumsum - itself was inf - inf
        {"reflection_gain": 1e300, "scatter_gain": 1e-300},  # 1e300 is inf in float32, inf * 0 NaN
    ])
    def test_extreme_settings_stay_finite_and_echo(self, options):
        extreme = UltrasoundConfig(half_angle_degrees=(35.0, 35.0), depth_range=(0.8, 0.8), **options)
        ultrasound, fov = simulated_ultrasound(_phantom().float(), _seeded(1), probe=ALONG_Z, config=extreme)
        assert torch.isfinite(ultrasound).all() and (ultrasound[fov == 1] > 0).any()

    @pytest.mark.parametrize("probe,message", [
        (torch.ones(2, 3), r"probe has shape \(2, 3\); expected \(3,\) or \(1, 3\) directions"),
        (torch.zeros(3), "probe contains a zero vector"),
        (torch.tensor([0.0, math.nan, 1.0]), "^probe contains a NaN or infinite value; a beam direction must be"),
        (torch.tensor([math.inf, 0.0, 1.0]), "^probe contains a NaN or infinite value"),
    ])
    def test_malformed_probe(self, probe, message):
        with pytest.raises(InputError, match=message):
            simulated_ultrasound(_phantom(), _seeded(0), probe=probe)

    def test_non_finite_volumes_are_refused(self):
        ct = _phantom()
        ct[0, 0, 10, 10, 10] = math.nan
        with pytest.raises(InputError, match="^ct contains NaN or infinite values"):
            simulated_ultrasound(ct, _seeded(0))

    def test_empty_or_non_cubic_volumes_are_refused(self):
        with pytest.raises(InputError, match="ct contains an empty volume"):
            simulated_ultrasound(torch.zeros(1, 1, 8, 8, 8), _seeded(0))
        with pytest.raises(InputError, match=r"spatial shape \(8, 8, 6\), not cubic"):
            simulated_ultrasound(torch.ones(1, 1, 8, 8, 6), _seeded(0))


class TestUltrasoundConfig:
    @pytest.mark.parametrize("options,message", [
        ({"half_angle_degrees": (0.0, 0.0)}, r"^half_angle_degrees is \(0.0, 0.0\); expected \(low, high\) with 5 <="),
        ({"half_angle_degrees": (1.0, 30.0)}, r"^half_angle_degrees is \(1.0, 30.0\); expected \(low, high\) "
                                              r"with 5 <= low <= high <= 89$"),
        ({"depth_range": (0.05, 0.05)}, r"^depth_range is \(0.05, 0.05\); expected \(low, high\) with 0.1 <= low <= "
                                        r"high <= 2 \(fractions of the grid side N\)$"),
        ({"depth_range": (100.0, 100.0)}, r"^depth_range is \(100.0, 100.0\); expected \(low, high\) with 0.1 <= low"),
        ({"depth_range": (0.8, 0.4)}, r"^depth_range is \(0.8, 0.4\); expected \(low, high\) with 0.1 <= low"),
        ({"depth_range": (0.4, math.inf)}, r"^depth_range\[1\] is inf; expected a finite number$"),
        ({"standoff": 10.0}, r"^standoff is 10.0; expected a finite number >= 0 and <= 1$"),
        ({"impedance_gain": math.nan}, "^impedance_gain is nan; expected a finite number >= 0"),
        ({"impedance_gain": 200.0}, r"^impedance_gain is 200.0; expected a finite number >= 0 and <= 30$"),
        ({"attenuation": 1e300}, r"^attenuation is 1e\+300; expected a finite number >= 0 and <= 100$"),
        ({"bone_attenuation": 3e38}, r"^bone_attenuation is 3e\+38; expected a finite number >= 0 and <= 1000$"),
        ({"reflection_gain": 0.0, "scatter_gain": 0.0}, "^reflection_gain and scatter_gain are both 0"),
    ])
    def test_settings_that_give_nan_or_blank_volumes_are_refused(self, options, message):
        with pytest.raises(InputError, match=message):
            UltrasoundConfig(**options)

    def test_either_gain_alone_is_enough(self):
        UltrasoundConfig(reflection_gain=0.0)
        UltrasoundConfig(scatter_gain=0.0)


class TestBMode:
    def test_echoes_are_compressed_over_the_range_with_nothing_outside_the_cone(self):
        echoes = torch.tensor([1.0, 0.1, 0.01, 1e-5, 0.0, 0.5])
        cone = torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
        shown = b_mode(echoes, cone, 40.0)
        # 0, -10 and -20 dB of a 40 dB range; the floor below -40 dB; 0 outside the cone whatever the echo
        torch.testing.assert_close(shown, torch.tensor([1.0, 0.75, 0.5, B_MODE_FLOOR, B_MODE_FLOOR, 0.0]))

    def test_a_simulated_cone_stays_its_nonzero_voxels(self):
        ct = _phantom()
        echoes, cone = simulated_ultrasound(ct, _seeded(0), probe=ALONG_Z, config=FIXED_CONE)
        shown = b_mode(echoes, cone, 50.0)
        assert torch.equal(shown > 0, cone > 0)
        # monotonic: the order of the echoes inside the cone is kept
        inside = cone > 0
        order = torch.argsort(echoes[inside])
        assert (torch.diff(shown[inside][order]) >= 0).all()

    @pytest.mark.parametrize(("range_db", "shape", "message"), [
        (0.0, (3,), "dynamic_range_db"), (-10.0, (3,), "dynamic_range_db"), (40.0, (2,), "shapes? that differ|shape"),
    ])
    def test_bad_arguments_are_refused(self, range_db, shape, message):
        with pytest.raises(InputError, match=message):
            b_mode(torch.ones(3), torch.ones(shape), range_db)
