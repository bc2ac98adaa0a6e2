"""Random anatomy: the deformation's coordinate convention, its ranges, its reproducibility, and exact pair poses."""

from __future__ import annotations

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import affine_points, warp
from dpcn_med.synth import AnatomyConfig, PairConfig, deformed_anatomy, synthetic_pairs
from dpcn_med.synth.contrast import _gaussian_blur
from tests.conftest import volume_grid

ALWAYS = AnatomyConfig(probability=1.0)


def _seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _box(sizes: tuple[int, int, int], half: tuple[float, float, float]) -> torch.Tensor:
    """1 inside a centred box of half-widths ``half`` (x, y, z voxels), 0 outside: ``(1, 1, D, H, W)`` float64."""
    points = affine_points(sizes, torch.eye(3, dtype=torch.float64)[None])
    inside = (points.abs() <= torch.tensor(half, dtype=torch.float64)).all(-1)
    return inside.to(torch.float64)[:, None]


def _extent(volume: torch.Tensor) -> torch.Tensor:
    """Foreground half-widths (x, y, z voxels from the grid centre) of a ``(1, 1, D, H, W)`` volume."""
    points = affine_points(tuple(volume.shape[2:]), torch.eye(3, dtype=volume.dtype)[None])[0]
    return points[volume[0, 0] > 0.5].abs().amax(0)


class TestConvention:
    @pytest.mark.parametrize("sizes", [(24, 24, 24), (16, 24, 32)])
    def test_no_stretch_shear_or_displacement_is_the_identity(self, sizes):
        volume = torch.rand(2, 1, *sizes, generator=_seeded(0), dtype=torch.float64)
        still = AnatomyConfig(probability=1.0, stretch=0.0, shear=0.0, displacement=0.0)
        torch.testing.assert_close(deformed_anatomy(volume, _seeded(1), still), volume)

    @pytest.mark.parametrize("sizes", [(32, 32, 32), (24, 32, 40)])
    def test_a_stretch_scales_each_axis_about_the_centre_within_its_range(self, sizes):
        # out(p) = volume(M p): a box of half-width h comes out with half-width h / m per axis, still centred.
        box = _box(sizes, (6.0, 5.0, 4.0)).expand(8, -1, -1, -1, -1)
        stretched = deformed_anatomy(box, _seeded(2), AnatomyConfig(probability=1.0, stretch=0.25, shear=0.0,
                                                                     displacement=0.0))
        ratios = torch.stack([_extent(one[None]) for one in stretched]) / torch.tensor([6.0, 5.0, 4.0],
                                                                                       dtype=torch.float64)
        assert (ratios > 1 / 1.25 - 0.15).all() and (ratios < 1 / 0.75 + 0.15).all()
        assert ratios.std() > 0.05  # a stretch per axis and per volume, not one for all
        points = affine_points(sizes, torch.eye(3, dtype=torch.float64)[None])[0]
        for one in stretched:
            centroid = (points * one[0, ..., None]).sum((0, 1, 2)) / one.sum()
            assert centroid.abs().max() < 0.3

    def test_matches_the_project_warp_for_a_pure_linear_map(self):
        # With no displacement the map is out(p) = volume(M p), geometry.warp's convention: recover M from the draws.
        head = volume_grid("mni", 24, torch.float64)
        config = AnatomyConfig(probability=1.0, stretch=0.2, shear=0.1, displacement=0.0)
        deformed = deformed_anatomy(head, _seeded(3), config)
        generator = _seeded(3)
        torch.rand((1,), generator=generator, dtype=torch.float64)  # the probability draw
        diagonal = 0.8 + 0.4 * torch.rand((1, 3, 1), generator=generator, dtype=torch.float64)
        off = -0.1 + 0.2 * torch.rand((1, 3, 3), generator=generator, dtype=torch.float64)
        matrix = torch.eye(3, dtype=torch.float64) * diagonal + (1 - torch.eye(3, dtype=torch.float64)) * off
        torch.testing.assert_close(deformed, warp(head, matrix), atol=1e-6, rtol=0)


class TestDraws:
    def test_off_by_default_and_then_draws_nothing(self):
        volume = torch.rand(3, 1, 16, 16, 16, generator=_seeded(0))
        generator = _seeded(5)
        assert deformed_anatomy(volume, generator) is volume
        assert torch.equal(torch.rand(4, generator=generator), torch.rand(4, generator=_seeded(5)))

    def test_reproducible_different_per_volume_and_in_range(self):
        head = volume_grid("mni", 32).expand(3, -1, -1, -1, -1)
        first = deformed_anatomy(head, _seeded(7), ALWAYS)
        torch.testing.assert_close(first, deformed_anatomy(head, _seeded(7), ALWAYS))
        assert not torch.allclose(first, deformed_anatomy(head, _seeded(8), ALWAYS))
        support = head[0] > 0
        assert (first[0] - first[1])[support].abs().mean() > 0.02  # each volume its own head
        assert first.min() >= head.min() - 1e-6 and first.max() <= head.max() + 1e-6
        for one, base in zip(first, head):  # a new head, still mostly the old one
            assert 0.4 < torch.corrcoef(torch.stack([one.flatten(), base.flatten()]))[0, 1] < 0.999

    def test_probability_chooses_which_volumes_change(self):
        volume = torch.rand(64, 1, 8, 8, 8, generator=_seeded(0), dtype=torch.float64)
        deformed = deformed_anatomy(volume, _seeded(1), AnatomyConfig(probability=0.5))
        unchanged = (deformed == volume).flatten(1).all(1)
        assert 16 < int(unchanged.sum()) < 48

    @pytest.mark.parametrize("options, message", [
        ({"probability": 1.5}, "probability"), ({"stretch": -0.1}, "stretch"), ({"shear": 0.6}, "shear"),
        ({"displacement": -1.0}, "displacement"), ({"control_points": 1}, "control_points"),
    ])
    def test_bad_settings_are_refused(self, options, message):
        with pytest.raises(InputError, match=message):
            AnatomyConfig(**options)

    def test_malformed_volumes_are_refused(self):
        with pytest.raises(InputError, match="volumes"):
            deformed_anatomy(torch.zeros(8, 8, 8), _seeded(0), ALWAYS)


class TestPairs:
    def test_both_sides_share_the_new_anatomy_and_the_pose_stays_exact(self):
        head = _gaussian_blur(volume_grid("mni", 32, torch.float64), torch.tensor([0.7], dtype=torch.float64))
        config = PairConfig(crop_probability=0.0, anatomy=ALWAYS)
        fixed, moving, target = synthetic_pairs(head.expand(4, -1, -1, -1, -1), _seeded(1), config,
                                                fixed_modality="identity", moving_modality="identity")
        back = warp(moving, target.scale[:, None, None] * target.rotation, target.translation)
        for one, returned in zip(fixed, back):
            assert torch.corrcoef(torch.stack([one.flatten(), head[0].flatten()]))[0, 1] < 0.99  # deformed
            support = (one > 0) | (returned > 0)
            assert torch.corrcoef(torch.stack([one[support], returned[support]]))[0, 1] > 0.97
