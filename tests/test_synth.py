"""Known poses for synthetic pairs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import grid_centre, rotation_angle, rotation_z, warp
from dpcn_med.synth import CTTissues, Pose, pseudo_ct, random_poses
from tests.conftest import shared_path


class TestPose:
    def test_moving_from_satisfies_the_solver_contract(self):
        # fixed(p) = moving(A p + t): warping the moving grid back by the pose reproduces the fixed one.
        fixed = torch.zeros(1, 1, 24, 24, 24, dtype=torch.float64)
        c = grid_centre(24)
        fixed[0, 0, c - 3:c + 1, c - 2:c + 5, c - 1:c + 3] = 1.0
        pose = Pose(rotation_z(torch.tensor(math.pi / 2, dtype=torch.float64)), 1.0,
                    torch.tensor([2.0, -1.0, 1.0], dtype=torch.float64))
        moving = pose.moving_from(fixed)
        back = warp(moving, pose.rotation[None], pose.translation[None])
        torch.testing.assert_close(back, fixed, atol=1e-9, rtol=0)

    def test_moving_from_follows_the_volume_dtype(self):
        pose = random_poses(1, 16, seed=1)[0]
        single = Pose(pose.rotation.float(), pose.scale, pose.translation.float())
        fixed = torch.rand(1, 1, 16, 16, 16, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        moving = single.moving_from(fixed)
        assert moving.dtype == torch.float64
        # The float32 pose, widened, is the pose used.
        widened = Pose(single.rotation.double(), single.scale, single.translation.double())
        torch.testing.assert_close(moving, widened.moving_from(fixed), rtol=0, atol=0)

    def test_moving_from_follows_the_volume_device(self):
        # Host poses with a volume elsewhere (CUDA in benchmarks/solver_speed.py; 'meta' here) failed in grid_sample.
        fixed = torch.zeros(2, 1, 16, 16, 16, dtype=torch.float64, device="meta")
        moving = random_poses(1, 16, seed=1)[0].moving_from(fixed)
        assert moving.device.type == "meta" and moving.dtype == torch.float64 and moving.shape == fixed.shape

    def test_errors_of_an_exact_and_of_a_wrong_estimate(self):
        pose = random_poses(1, 64, seed=0)[0]
        assert pose.errors(pose.rotation, pose.scale, pose.translation) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
        turned = pose.rotation @ rotation_z(torch.tensor(0.1, dtype=torch.float64))
        rotation_error, translation_error, scale_error = pose.errors(turned, pose.scale * 1.1,
                                                                     pose.translation + 3.0)
        assert rotation_error == pytest.approx(math.degrees(0.1))
        assert translation_error == pytest.approx(3.0 * math.sqrt(3))
        assert scale_error == pytest.approx(0.1)


class TestRandomPoses:
    def test_reproducible_and_within_range(self):
        first, second = random_poses(20, 64, seed=3), random_poses(20, 64, seed=3)
        for a, b in zip(first, second):
            torch.testing.assert_close(a.rotation, b.rotation)
        assert all(0.8 <= p.scale <= 1.2 for p in first)
        assert all(p.translation.norm() <= 0.2 * 64 for p in first)
        assert max(rotation_angle(p.rotation).item() for p in first) > math.radians(120)

    def test_two_dimensional_and_rigid(self):
        poses = random_poses(5, 256, seed=4, dim=2, similarity=False, max_shift=50.0)
        assert all(p.rotation.shape == (2, 2) and p.scale == 1.0 for p in poses)
        assert all(p.translation.norm() <= 50.0 for p in poses)

    @pytest.mark.parametrize("options,message", [
        ({"count": -3}, "^count is -3; expected an integer >= 0$"),
        ({"size": 0}, "^size is 0; expected an integer >= 1$"),
        ({"dim": 4}, "^dim is 4; expected an integer >= 2 and <= 3$"),
        ({"similarity": "yes"}, r"^similarity is 'yes' \(str\); expected True or False$"),
        ({"max_shift": math.nan}, "^max_shift is nan; expected a finite number >= 0$"),
        ({"max_shift": -1.0}, "^max_shift is -1.0; expected a finite number >= 0$"),
        ({"scale_range": (-1.0, -0.5)}, r"^scale_range is \(-1.0, -0.5\); expected \(low, high\) with 0 < low"),
        ({"scale_range": (1.2, 0.8)}, r"^scale_range is \(1.2, 0.8\); expected \(low, high\) with 0 < low <= high$"),
        ({"scale_range": (0.8, math.inf)}, r"^scale_range\[1\] is inf; expected a finite number$"),
        ({"seed": -1}, r"^seed is -1; expected an integer >= 0 and <= 9223372036854775807$"),
        ({"seed": 1.5}, r"^seed is 1.5 \(float\); expected an integer >= 0"),
    ])
    def test_invalid_arguments(self, options, message):
        arguments = {"count": 2, "size": 32, "seed": 0} | options
        with pytest.raises(InputError, match=message):
            random_poses(**arguments)


def _phantom() -> dict[str, sitk.Image]:
    """A T1-like head of nested spheres, 2 mm voxels: white matter inside grey, a CSF core, a dark skull, a scalp."""
    radius = np.linalg.norm(np.mgrid[:40, :40, :40] - 19.5, axis=0)
    shells = {"csf": radius < 3, "white": (radius >= 3) & (radius < 8), "grey": (radius >= 8) & (radius < 12),
              "bone": (radius >= 13) & (radius < 16), "scalp": (radius >= 16) & (radius < 18)}
    t1 = {"csf": 60.0, "white": 200.0, "grey": 150.0, "bone": 10.0, "scalp": 180.0}
    mr = np.zeros(radius.shape, np.float32)
    for name, inside in shells.items():
        mr[inside] = t1[name]
    images = {"mr": sitk.GetImageFromArray(mr), "bone": sitk.GetImageFromArray(shells["bone"].astype(np.uint8)),
              "brain": sitk.GetImageFromArray((radius < 12).astype(np.uint8)),
              **{name: sitk.GetImageFromArray(inside.astype(np.uint8)) for name, inside in shells.items()
                 if name != "bone"}}
    for image in images.values():
        image.SetSpacing((2.0, 2.0, 2.0))
        image.SetOrigin((-40.0, 10.0, 3.0))
    return images


def _median(ct: sitk.Image, mask: sitk.Image) -> float:
    return float(np.median(sitk.GetArrayViewFromImage(ct)[sitk.GetArrayViewFromImage(mask) > 0]))


@pytest.fixture(scope="module")
def seg3d() -> dict[str, sitk.Image]:
    """The shared T1 with its skull and brain masks, and its pseudo-CT."""
    images = {name: sitk.ReadImage(str(shared_path(f"seg3d/{name}.nii.gz")))
              for name in ("MR", "skull_mask", "brain_mask")}
    images["CT"] = pseudo_ct(images["MR"], bone=images["skull_mask"], brain=images["brain_mask"], seed=0)
    return images


class TestPseudoCT:
    def test_tissue_densities_on_a_phantom(self):
        images = _phantom()
        ct = pseudo_ct(images["mr"], bone=images["bone"], brain=images["brain"], seed=1)
        hu = {name: _median(ct, images[name]) for name in ("csf", "white", "grey", "bone", "scalp")}
        # Grey matter is denser than white matter although darker on T1: the map is not monotonic.
        assert hu["csf"] < hu["white"] < hu["grey"]
        assert 5 <= hu["csf"] <= 20 and 20 <= hu["white"] <= 30 and 35 <= hu["grey"] <= 45
        assert hu["bone"] > 700 and 15 <= hu["scalp"] <= 65
        assert sitk.GetArrayViewFromImage(ct)[0, 0, 0] < -900

    def test_bone_is_brightest_at_its_surface(self):
        images = _phantom()
        ct = sitk.GetArrayFromImage(pseudo_ct(images["mr"], bone=images["bone"], seed=0, head=images["brain"]))
        radius = np.linalg.norm(np.mgrid[:40, :40, :40] - 19.5, axis=0)
        # Voxels at the inner table, the middle of the shell and the outer table.
        inner, middle, outer = (np.median(ct[np.abs(radius - r) < 0.5]) for r in (13.3, 14.5, 15.6))
        assert middle < min(inner, outer) - 200

    def test_seeded_noise(self):
        images = _phantom()
        first, again, other = (sitk.GetArrayFromImage(pseudo_ct(images["mr"], bone=images["bone"], seed=seed))
                               for seed in (3, 3, 4))
        np.testing.assert_array_equal(first, again)
        assert 5 < np.std(first[:5, :5, :5].astype(float) - other[:5, :5, :5]) / math.sqrt(2) < 20

    def test_an_mr_without_signal_in_the_brain_mask_is_refused(self):
        """The white matter level was 0: values / 0 became 0 HU over the skull and half the air, silently."""
        images = _phantom()
        mr = images["mr"] * sitk.Cast(images["brain"] == 0, images["mr"].GetPixelID())
        with pytest.raises(InputError, match=r"^brain mask: the MR's white matter level inside it is 0; expected a "
                                             r"positive T1 magnitude"):
            pseudo_ct(mr, bone=images["bone"], brain=images["brain"])

    def test_negative_seed_is_refused(self):
        images = _phantom()
        with pytest.raises(InputError, match="^seed is -1; expected an integer >= 0$"):
            pseudo_ct(images["mr"], bone=images["bone"], seed=-1)

    @pytest.mark.parametrize("options,message", [
        ({"noise_hu": math.nan}, "^noise_hu is nan; expected a finite number >= 0$"),
        ({"noise_hu": -5.0}, "^noise_hu is -5.0; expected a finite number >= 0$"),
        ({"cortex_mm": math.nan}, "^cortex_mm is nan; expected a finite number > 0$"),
        ({"cortex_mm": 0.0}, "^cortex_mm is 0.0; expected a finite number > 0$"),
        ({"blur_mm": -1.0}, "^blur_mm is -1.0; expected a finite number >= 0$"),
        ({"air": -math.inf}, "^air is -inf; expected a finite number$"),
        ({"bone_core": math.nan}, "^bone_core is nan; expected a finite number$"),
        ({"soft_tissue": (60.0, math.nan)}, r"^soft_tissue\[1\] is nan; expected a finite number$"),
        ({"soft_tissue": 60.0}, r"^soft_tissue is 60.0 \(float\); expected a tuple of 2 values$"),
        ({"t1_ratios": (0.3, 1.0)}, r"^t1_ratios is \(0.3, 1.0\): 2 values; expected 3$"),
        ({"t1_ratios": (0.0, 0.75, 1.0)}, r"^t1_ratios\[0\] is 0.0; expected a finite number > 0$"),
        ({"t1_ratios": (0.75, 0.3, 1.0)}, r"^t1_ratios is \(0.75, 0.3, 1.0\); expected CSF < grey matter < white"),
    ])
    def test_invalid_tissues(self, options, message):
        with pytest.raises(InputError, match=message):
            CTTissues(**options)

    def test_mask_off_the_grid_is_refused(self):
        images = _phantom()
        shifted = sitk.Image(images["bone"])
        shifted.SetOrigin((0.0, 0.0, 0.0))
        with pytest.raises(InputError, match="bone mask .* is not on the MR's grid"):
            pseudo_ct(images["mr"], bone=shifted)

    @pytest.mark.shared_data
    def test_geometry_and_type_follow_the_mr(self, seg3d):
        ct, mr = seg3d["CT"], seg3d["MR"]
        assert ct.GetPixelID() == sitk.sitkInt16
        assert (ct.GetSize(), ct.GetOrigin(), ct.GetSpacing(), ct.GetDirection()) == \
            (mr.GetSize(), mr.GetOrigin(), mr.GetSpacing(), mr.GetDirection())

    @pytest.mark.shared_data
    def test_densities_of_a_real_head(self, seg3d):
        # Air: where the MR has no signal, mostly outside the head.
        background = sitk.GetArrayViewFromImage(seg3d["MR"]) == 0
        assert np.median(sitk.GetArrayViewFromImage(seg3d["CT"])[background]) < -900
        assert _median(seg3d["CT"], seg3d["skull_mask"]) > 600
        assert 15 <= _median(seg3d["CT"], seg3d["brain_mask"]) <= 60

    @pytest.mark.shared_data
    def test_bone_to_brain_contrast_is_reversed(self, seg3d):
        def contrast(image: sitk.Image) -> float:
            return _median(image, seg3d["skull_mask"]) - _median(image, seg3d["brain_mask"])

        assert contrast(seg3d["MR"]) < 0 < contrast(seg3d["CT"])
