"""Conventions of dpcn_med.geometry, pinned with known answers on asymmetric inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
import torch
import torch.nn.functional as F

from dpcn_med.errors import InputError
from dpcn_med.geometry import (
    LPS_TO_RAS,
    CanonicalGrid,
    affine_points,
    axis_angle_to_matrix,
    euler_zyz_to_matrix,
    geodesic_distance,
    grid_centre,
    half_turns,
    homogeneous_matrix,
    matrix_to_euler_zyz,
    physical_transform,
    project_to_rotation,
    random_rotation,
    rotation_angle,
    rotation_y,
    rotation_z,
    sample,
    sample_points,
    scale_and_rotation,
    similarity_transform,
    slicer_to_parent_ras,
    squared_distance_from_centre,
    warp,
)


class TestEulerZYZ:
    def test_matches_product_of_elementary_rotations(self):
        angles = torch.tensor([0.3, 1.1, -2.0], dtype=torch.float64)
        expected = rotation_z(angles[0]) @ rotation_y(angles[1]) @ rotation_z(angles[2])
        torch.testing.assert_close(euler_zyz_to_matrix(angles), expected)

    def test_active_rotation_about_z_turns_x_into_y(self):
        matrix = euler_zyz_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))
        torch.testing.assert_close(matrix @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))

    def test_round_trip_of_random_rotations(self):
        rotation = random_rotation(200, torch.Generator().manual_seed(0))
        angles = matrix_to_euler_zyz(rotation)
        assert (angles[:, 0] >= 0).all() and (angles[:, 0] < 2 * math.pi).all()
        assert (angles[:, 1] >= 0).all() and (angles[:, 1] <= math.pi).all()
        torch.testing.assert_close(euler_zyz_to_matrix(angles), rotation, atol=1e-9, rtol=0)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_rounded_rotations_near_the_poles(self, dtype):
        """alpha and gamma were each read from entries that are sin(beta) times rounding there: up to 180 degrees
        off (identity with r02 = 1e-8; products of float32 rotations)."""
        generator = torch.Generator().manual_seed(5)
        angles = torch.rand(500, 3, generator=generator, dtype=torch.float64) * 2 * math.pi
        near = torch.rand(500, generator=generator, dtype=torch.float64) * 1e-5
        angles[:, 1] = torch.where(torch.arange(500) % 2 == 0, near, math.pi - near)
        rotation = euler_zyz_to_matrix(angles).to(dtype)
        rebuilt = euler_zyz_to_matrix(matrix_to_euler_zyz(rotation))
        assert (rebuilt - rotation).abs().max() < 20 * torch.finfo(dtype).eps
        nudged = torch.eye(3, dtype=torch.float64)
        nudged[0, 2] = 1e-8
        assert matrix_to_euler_zyz(nudged)[[0, 2]].sum().remainder(2 * math.pi) < 1e-6 or \
            matrix_to_euler_zyz(nudged)[[0, 2]].sum().remainder(2 * math.pi) > 2 * math.pi - 1e-6

    @pytest.mark.parametrize("beta", [0.0, 5e-7, 2e-6, math.pi - 2e-6, math.pi])
    def test_round_trip_at_and_near_the_gimbal_poles(self, beta):
        rotation = euler_zyz_to_matrix(torch.tensor([0.7, beta, 0.4], dtype=torch.float64))
        torch.testing.assert_close(euler_zyz_to_matrix(matrix_to_euler_zyz(rotation)), rotation, atol=1e-9, rtol=0)


class TestRotationAngle:
    def test_known_angles_including_half_turn(self):
        axis = torch.tensor([0.2, -0.5, 0.8], dtype=torch.float64)
        axis = axis / axis.norm()
        for angle in (1e-7, 0.3, 2.0, math.pi - 1e-6):
            torch.testing.assert_close(rotation_angle(axis_angle_to_matrix(axis * angle)),
                                       torch.tensor(angle, dtype=torch.float64), atol=1e-9, rtol=0)

    def test_geodesic_distance_is_symmetric(self):
        a, b = random_rotation(2, torch.Generator().manual_seed(1))
        torch.testing.assert_close(geodesic_distance(a, b), geodesic_distance(b, a))


class TestRandomRotation:
    def test_orthonormal_and_proper(self):
        rotation = random_rotation(100, torch.Generator().manual_seed(2))
        torch.testing.assert_close(rotation @ rotation.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(
            100, 3, 3), atol=1e-12, rtol=0)
        torch.testing.assert_close(torch.linalg.det(rotation), torch.ones(100, dtype=torch.float64))

    def test_haar_uniform_mean_is_zero_and_angles_follow_the_haar_density(self):
        rotation = random_rotation(20000, torch.Generator().manual_seed(3))
        assert rotation.mean(0).abs().max() < 0.02
        # Haar measure: the rotation angle has density (1 - cos w) / pi, so P(w < pi/2) = (pi/2 - 1) / pi.
        fraction = (rotation_angle(rotation) < math.pi / 2).double().mean().item()
        assert abs(fraction - (math.pi / 2 - 1) / math.pi) < 0.01


class TestHalfTurns:
    def test_identity_then_half_turns_about_x_y_z(self):
        turns = half_turns(torch.device("cpu"), torch.float64)
        assert turns.shape == (4, 3, 3)
        torch.testing.assert_close(turns[0], torch.eye(3, dtype=torch.float64))
        for axis in range(3):
            turn = turns[axis + 1]
            torch.testing.assert_close(rotation_angle(turn), torch.tensor(math.pi, dtype=torch.float64))
            assert turn[axis, axis] == 1.0


class TestProjectToRotation:
    def test_returns_nearest_rotation_and_keeps_rotations(self):
        rotation = random_rotation(5, torch.Generator().manual_seed(4))
        torch.testing.assert_close(project_to_rotation(rotation), rotation)
        noisy = rotation + 0.05 * torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(5),
                                              dtype=torch.float64)
        u, _, vh = torch.linalg.svd(noisy)
        torch.testing.assert_close(project_to_rotation(noisy), u @ vh, atol=1e-10, rtol=0)


class TestAffinePoints:
    def test_centre_voxel_is_the_origin_and_x_runs_along_the_last_axis(self):
        points = affine_points((4, 6, 8), torch.eye(3, dtype=torch.float64)[None])[0]
        assert points.shape == (4, 6, 8, 3)
        torch.testing.assert_close(points[grid_centre(4), grid_centre(6), grid_centre(8)],
                                   torch.zeros(3, dtype=torch.float64))
        torch.testing.assert_close(points[2, 3, 5], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
        torch.testing.assert_close(points[2, 4, 4], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        torch.testing.assert_close(points[3, 3, 4], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


    def test_maps_every_voxel_by_matrix_and_translation(self):
        matrix = random_rotation(2, torch.Generator().manual_seed(6)) * 1.5
        translation = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]], dtype=torch.float64)
        identity = affine_points((5, 4, 6), torch.eye(3, dtype=torch.float64)[None])
        mapped = affine_points((5, 4, 6), matrix, translation)
        torch.testing.assert_close(mapped, torch.einsum("bij,...j->b...i", matrix, identity[0])
                                   + translation[:, None, None, None])


def _spot(size: int, where: tuple[int, int, int]) -> torch.Tensor:
    """A volume with one bright voxel at voxel coordinates ``where`` = (x, y, z) from the centre."""
    volume = torch.zeros(1, 1, size, size, size, dtype=torch.float64)
    c = grid_centre(size)
    volume[0, 0, c + where[2], c + where[1], c + where[0]] = 1.0
    return volume


def _argmax_xyz(volume: torch.Tensor) -> tuple[int, ...]:
    size = volume.shape[-1]
    z, y, x = torch.unravel_index(volume.flatten().argmax(), volume.shape[2:])
    return tuple(int(v) - grid_centre(size) for v in (x, y, z))


class TestWarp:
    def test_pulls_translation(self):
        # out(p) = volume(p + t): the spot at s appears at s - t.
        moved = warp(_spot(16, (3, -2, 1)), torch.eye(3, dtype=torch.float64)[None],
                     torch.tensor([[1.0, 2.0, -3.0]], dtype=torch.float64))
        assert _argmax_xyz(moved) == (2, -4, 4)

    def test_pulls_rotation_about_the_grid_centre(self):
        # out(p) = volume(R p): the spot at s appears at R^T s. R turns x into y (90 degrees about z).
        rotation = rotation_z(torch.tensor(math.pi / 2, dtype=torch.float64))
        moved = warp(_spot(16, (4, 1, -2)), rotation[None])
        assert _argmax_xyz(moved) == (1, -4, -2)

    def test_two_dimensional_warp(self):
        image = torch.zeros(1, 1, 12, 12, dtype=torch.float64)
        image[0, 0, 6 + 2, 6 + 3] = 1.0  # (x, y) = (3, 2)
        moved = warp(image, torch.eye(2, dtype=torch.float64)[None], torch.tensor([[1.0, -1.0]], dtype=torch.float64))
        y, x = torch.unravel_index(moved.flatten().argmax(), (12, 12))
        assert (int(x) - 6, int(y) - 6) == (2, 3)

    def test_follows_the_volume_device_and_dtype(self):
        # The grid is built on the volume's device: host matrices with a volume elsewhere (CUDA; 'meta' here, which
        # needs no accelerator) failed in grid_sample ("expected input and grid to be on same device").
        matrix = torch.eye(3, dtype=torch.float32)[None]
        translation = torch.tensor([[1.0, 0.0, 0.0]])
        moved = warp(torch.zeros(1, 1, 8, 8, 8, dtype=torch.float64, device="meta"), matrix, translation)
        assert moved.device.type == "meta" and moved.dtype == torch.float64 and moved.shape == (1, 1, 8, 8, 8)

    def test_threaded_chunks_give_the_same_samples(self):
        volume = torch.randn(1, 1, 16, 16, 16, generator=torch.Generator().manual_seed(7))
        matrix = random_rotation(1, torch.Generator().manual_seed(8)).float()
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            single = warp(volume, matrix)
            torch.set_num_threads(4)
            chunked = warp(volume, matrix)
        finally:
            torch.set_num_threads(threads)
        torch.testing.assert_close(chunked, single)

    @pytest.mark.parametrize("count", [1, 2, 3, 1001])
    @pytest.mark.parametrize(("mode", "padding"), [("bilinear", "zeros"), ("bilinear", "border"),
                                                   ("nearest", "border")])
    def test_sample_points_equal_one_grid_sample_over_threads(self, count, mode, padding):
        # Over three threads the points fall into three chunks, the last one padded, sampled from a channels-last
        # four-channel volume (the refinement's kind): the values and their gradient in the grid are one grid_sample's,
        # bit for bit.
        generator = torch.Generator().manual_seed(count)
        volume = torch.randn(1, 4, 9, 11, 7, generator=generator).contiguous(memory_format=torch.channels_last_3d)
        grid = (torch.rand(count, 3, generator=generator) * 2.4 - 1.2).requires_grad_()
        reference = F.grid_sample(volume, grid.view(1, 1, 1, count, 3), mode=mode, padding_mode=padding,
                                  align_corners=True)[0, :, 0, 0]
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(3)
            values = sample_points(volume, grid, mode=mode, padding_mode=padding)
        finally:
            torch.set_num_threads(threads)
        assert values.shape == (4, count) and torch.equal(values, reference)
        if mode == "bilinear":
            weights = torch.randn(4, count, generator=generator)
            expected, = torch.autograd.grad((reference * weights).sum(), grid)
            found, = torch.autograd.grad((values * weights).sum(), grid)
            assert torch.equal(found, expected)

    def test_sample_is_trilinear_and_zero_outside(self):
        volume = torch.arange(4 ** 3, dtype=torch.float64).reshape(1, 1, 4, 4, 4)
        points = torch.tensor([[[0.5, 0.0, 0.0], [0.0, 0.0, 10.0]]], dtype=torch.float64)
        values = sample(volume, points)[0, 0]
        centre = volume[0, 0, 2, 2, 2]
        torch.testing.assert_close(values, torch.stack([centre + 0.5, torch.tensor(0.0, dtype=torch.float64)]))
        single = sample(volume.float(), points)[0, 0]  # float64 points on a float32 volume raised, unlike warp
        assert single.dtype == torch.float32 and torch.allclose(single.double(), values)


class TestSquaredDistance:
    def test_matches_the_coordinates(self):
        points = affine_points((5, 4, 6), torch.eye(3, dtype=torch.float64)[None])[0]
        torch.testing.assert_close(squared_distance_from_centre((5, 4, 6), dtype=torch.float64),
                                   points.square().sum(-1))


class TestCanonicalGrid:
    def test_origin_puts_the_centre_voxel_at_the_centre(self):
        grid = CanonicalGrid(size=64, spacing=2.5, centre=(10.0, -20.0, 30.0))
        assert grid.origin == (10.0 - 80.0, -20.0 - 80.0, 30.0 - 80.0)

    def test_numbers_are_plain_floats(self):
        grid = CanonicalGrid(np.int64(8), np.float32(1.5), np.array([1, 2, 3]))
        assert (type(grid.size), type(grid.spacing), grid.centre) == (int, float, (1.0, 2.0, 3.0))

    @pytest.mark.parametrize(("arguments", "message"), [
        ((1, 1.0, (0, 0, 0)), r"^size is 1; expected an integer >= 2$"),
        ((8, -1.0, (0, 0, 0)), r"^spacing is -1\.0; expected a finite number > 0$"),
        ((8, 1.0, (0, 0)), r"^centre is \(0, 0\): 2 values; expected 3$"),
        ((8, 1.0, (0, float("inf"), 0)), r"^centre\[1\] is inf; expected a finite number$"),
    ])
    def test_bad_values_are_named(self, arguments, message):
        with pytest.raises(InputError, match=message):
            CanonicalGrid(*arguments)


def _similarity(seed: int = 3) -> sitk.Similarity3DTransform:
    rng = np.random.default_rng(seed)
    transform = sitk.Similarity3DTransform()
    transform.SetCenter(rng.normal(size=3).tolist())
    transform.SetRotation(rng.normal(size=3).tolist(), 2.5)  # near the versor's awkward half-turn region
    transform.SetScale(1.12)
    transform.SetTranslation((rng.normal(size=3) * 20).tolist())
    return transform


class TestHomogeneousMatrix:
    def test_matches_transform_point(self):
        transform = _similarity()
        matrix = homogeneous_matrix(transform)
        for point in np.random.default_rng(0).normal(size=(5, 3)) * 50:
            np.testing.assert_allclose(matrix[:3, :3] @ point + matrix[:3, 3], transform.TransformPoint(point.tolist()),
                                       atol=1e-9)

    def test_composite_applies_last_added_first(self):
        first, second = _similarity(1), _similarity(2)
        composite = sitk.CompositeTransform([first, second])
        point = [10.0, -20.0, 30.0]
        expected = composite.TransformPoint(point)
        matrix = homogeneous_matrix(composite)
        np.testing.assert_allclose(matrix[:3, :3] @ point + matrix[:3, 3], expected, atol=1e-9)

    @pytest.mark.parametrize("make", [
        lambda: sitk.TranslationTransform(3, (4.0, -5.0, 6.0)),  # was refused as not linear: a rigid ground truth
        lambda: sitk.Transform(),  # the identity, likewise
        lambda: sitk.VersorTransform((0.2, -0.4, 0.5), 2.0, (3.0, 1.0, -2.0)),  # AttributeError: no GetTranslation
        lambda: sitk.ScaleTransform(3, (1.1, 1.1, 1.1)),  # AttributeError too
        lambda: sitk.CompositeTransform([sitk.TranslationTransform(3, (1.0, 2.0, 3.0)), _similarity(4)]),
        lambda: sitk.AffineTransform(3),
    ], ids=["translation", "identity", "versor", "scale", "composite with a translation", "affine"])
    def test_every_linear_transform_type(self, make):
        transform = make()
        matrix = homogeneous_matrix(transform)
        for point in np.random.default_rng(1).normal(size=(5, 3)) * 50:
            np.testing.assert_allclose(matrix[:3, :3] @ point + matrix[:3, 3], transform.TransformPoint(point.tolist()),
                                       atol=1e-9)

    def test_rejects_nonlinear(self):
        with pytest.raises(ValueError, match="not a linear transform"):
            homogeneous_matrix(sitk.DisplacementFieldTransform(3))
        with pytest.raises(ValueError, match="not a linear transform"):
            homogeneous_matrix(sitk.CompositeTransform([_similarity(), sitk.DisplacementFieldTransform(3)]))

    def test_rejects_2d(self):
        with pytest.raises(ValueError, match=r"^Similarity2DTransform is 2-D; expected a 3-D transform$"):
            homogeneous_matrix(sitk.Similarity2DTransform())


class TestScaleAndRotation:
    def test_splits_mu_r(self):
        rotation = axis_angle_to_matrix(torch.tensor([0.3, 2.0, -1.1], dtype=torch.float64)).numpy()
        mu, found = scale_and_rotation(1.13 * rotation)
        assert mu == pytest.approx(1.13)
        np.testing.assert_allclose(found, rotation, atol=1e-12)

    def test_float32_rounding_is_tolerated(self):
        rotation = axis_angle_to_matrix(torch.tensor([0.3, 2.0, -1.1])).numpy()  # orthogonal to about 1e-7
        mu, found = scale_and_rotation(0.9 * rotation)
        assert mu == pytest.approx(0.9, rel=1e-6)
        np.testing.assert_allclose(found @ found.T, np.eye(3), atol=1e-12)

    # Before: a reflection came back as mu = -1 with a proper rotation, shear and anisotropic scale as a similarity
    # (mu = 1.26 for diag(1, 1, 2)), a singular or NaN matrix as numpy's "SVD did not converge".
    @pytest.mark.parametrize(("linear", "message"), [
        (np.diag([-1.0, 1.0, 1.0]), r"reflects \(determinant -1 < 0\)"),
        (np.diag([-2.0, -2.0, -2.0]), r"reflects \(determinant -8 < 0\)"),
        (np.array([[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), r"has shear or anisotropic scale \(singular "
                                                                       r"values 1\.10499, 1, 0\.904988\)"),
        (np.diag([1.0, 1.0, 2.0]), r"has shear or anisotropic scale \(singular values 2, 1, 1\)"),
        (np.diag([1.0, 1.0, 1.0 + 3e-4]), "has shear or anisotropic scale"),
        (np.diag([1.0, 1.0, 0.0]), r"is singular \(singular values 1, 1, 0\)"),
        (np.zeros((3, 3)), "is singular"),
        (np.full((3, 3), np.nan), r"rotation is \[\[nan, .*; expected a finite \(3, 3\) linear part"),
        (np.eye(4), r"rotation is .*; expected a finite \(3, 3\) linear part"),
    ], ids=["reflection", "negative scale", "shear", "anisotropic", "anisotropic 3e-4", "singular", "zero", "nan",
            "4x4"])
    def test_refuses_what_is_not_a_similarity(self, linear, message):
        with pytest.raises(InputError, match=message):
            scale_and_rotation(linear, "rotation")

    def test_names_the_matrix(self):
        with pytest.raises(InputError, match=r"^truth\.tfm is not a similarity: its linear part reflects"):
            scale_and_rotation(np.diag([1.0, -1.0, 1.0]), "truth.tfm")


class TestSimilarityTransform:
    @pytest.mark.parametrize("rigid", [True, False])
    def test_round_trip_keeps_matrix_and_centre(self, rigid):
        source = _similarity()
        if rigid:
            source.SetScale(1.0)
        centre = np.array([5.0, -7.0, 2.0])
        rebuilt = similarity_transform(homogeneous_matrix(source), centre, rigid=rigid)
        assert rebuilt.GetName() == ("VersorRigid3DTransform" if rigid else "Similarity3DTransform")
        np.testing.assert_allclose(rebuilt.GetFixedParameters(), centre)
        np.testing.assert_allclose(homogeneous_matrix(rebuilt), homogeneous_matrix(source), atol=1e-9)

    def test_rigid_refuses_a_scale(self):  # before: a VersorRigid3DTransform that dropped the 1.2 silently
        matrix = np.eye(4)
        matrix[:3, :3] *= 1.2
        with pytest.raises(InputError, match=r"start scales by 1\.2; a rigid transform has scale 1"):
            similarity_transform(matrix, np.zeros(3), rigid=True, name="start")
        assert similarity_transform(matrix, np.zeros(3), rigid=False).TransformPoint((10.0, 0.0, 0.0)) == \
            pytest.approx((12.0, 0.0, 0.0))

    def test_refuses_a_reflection(self):
        with pytest.raises(InputError, match="matrix is not a similarity: its linear part reflects"):
            similarity_transform(np.diag([1.0, 1.0, -1.0, 1.0]), np.zeros(3), rigid=False)


class TestPhysicalTransform:
    def test_maps_grid_voxels_as_the_solver_says(self):
        """Fixed voxel u (from the grid centre) lands on moving voxel v = mu R u + tau, in physical space."""
        fixed_grid = CanonicalGrid(64, 2.5, (10.0, -20.0, 5.0))
        moving_grid = CanonicalGrid(64, 2.5, (-30.0, 4.0, 60.0))
        rotation = axis_angle_to_matrix(torch.tensor([0.4, -1.2, 2.0], dtype=torch.float64))
        tau = torch.tensor([3.0, -1.5, 7.25], dtype=torch.float64)
        transform = physical_transform(rotation, 0.9, tau, fixed_grid, moving_grid)
        u = np.array([5.0, -3.0, 11.0])
        v = 0.9 * rotation.double().numpy() @ u + tau.double().numpy()
        fixed_point = np.asarray(fixed_grid.centre) + fixed_grid.spacing * u
        np.testing.assert_allclose(transform.TransformPoint(fixed_point.tolist()),
                                   np.asarray(moving_grid.centre) + moving_grid.spacing * v, atol=1e-9)
        np.testing.assert_allclose(transform.GetFixedParameters(), fixed_grid.centre)

    def test_the_grid_centre_lands_exactly_where_the_solver_says(self):
        """A rotation off orthogonal by 1e-5 (within what ITK is given after projection), far from the origin: the
        fixed centre still maps to c_m + h tau."""
        fixed_grid = CanonicalGrid(64, 2.0, (3000.0, -2500.0, 4000.0))
        moving_grid = CanonicalGrid(64, 2.0, (-10.0, 20.0, 30.0))
        rotation = axis_angle_to_matrix(torch.tensor([0.3, 0.2, -0.9], dtype=torch.float64))
        rotation = rotation + 1e-5 * torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
                                                  dtype=torch.float64)
        tau = torch.tensor([1.0, 2.0, -3.0], dtype=torch.float64)
        transform = physical_transform(rotation, None, tau, fixed_grid, moving_grid)
        np.testing.assert_allclose(transform.TransformPoint(fixed_grid.centre),
                                   np.asarray(moving_grid.centre) + 2.0 * tau.numpy(), atol=1e-9)

    def test_rigid_gives_a_versor_transform(self):
        grid = CanonicalGrid(32, 1.0, (0.0, 0.0, 0.0))
        transform = physical_transform(torch.eye(3), None, torch.zeros(3), grid, grid)
        assert transform.GetName() == "VersorRigid3DTransform"

    def test_rejects_grids_with_different_spacing(self):
        with pytest.raises(ValueError, match="share one spacing"):
            physical_transform(torch.eye(3), None, torch.zeros(3), CanonicalGrid(32, 1.0, (0, 0, 0)),
                               CanonicalGrid(32, 2.0, (0, 0, 0)))


class TestSlicerToParentRas:
    def test_is_the_inverse_motion_in_ras(self):
        transform = _similarity()
        to_parent = slicer_to_parent_ras(transform)
        # A moving point p (LPS) that the fixed point x maps onto is carried back onto x by the node's motion.
        x = np.array([12.0, -4.0, 33.0])
        p = np.asarray(transform.TransformPoint(x.tolist()))
        p_ras = LPS_TO_RAS[:3, :3] @ p
        np.testing.assert_allclose(to_parent[:3, :3] @ p_ras + to_parent[:3, 3], LPS_TO_RAS[:3, :3] @ x, atol=1e-9)

    @pytest.mark.parametrize("suffix", [".tfm", ".h5"])
    def test_equals_what_slicer_reads_from_the_file(self, tmp_path, suffix):
        slicer = pytest.importorskip("slicer", reason="slicer-core (the test extra) is not installed")
        vtk = pytest.importorskip("vtk")
        transform = _similarity()
        path = tmp_path / f"transform{suffix}"
        sitk.WriteTransform(transform, str(path))
        scene = slicer.vtkMRMLScene()
        storage = slicer.vtkMRMLTransformStorageNode()
        node = slicer.vtkMRMLLinearTransformNode()
        scene.AddNode(storage)
        scene.AddNode(node)
        storage.SetFileName(str(path))
        assert storage.ReadData(node) == 1
        matrix = vtk.vtkMatrix4x4()
        node.GetMatrixTransformToParent(matrix)
        read = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
        np.testing.assert_allclose(read, slicer_to_parent_ras(transform), atol=1e-6)
