"""3-D renders: isosurfaces in LPS millimetres, and the before/after picture."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.evaluation import moved_copy, random_similarity
from tests.conftest import shared_path

pytest.importorskip("pyvista", reason="pyvista (the mesh extra) is not installed")
from dpcn_med import render  # noqa: E402  (needs pyvista, checked above)

CENTRE, RADIUS = np.array([12.0, -30.0, 45.0]), 20.0


def oblique_ball() -> sitk.Image:
    """A bright ball of radius 20 mm at CENTRE (LPS) on an oblique grid with anisotropic voxels."""
    image = sitk.Image([48, 40, 36], sitk.sitkFloat32)
    image.SetSpacing((1.1, 1.3, 1.6))
    angle = np.radians(30)
    direction = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    image.SetDirection(direction.ravel().tolist())
    image.SetOrigin((CENTRE - direction @ (np.array(image.GetSize()) / 2 * image.GetSpacing())).tolist())
    index = np.stack(np.meshgrid(*[np.arange(n) for n in image.GetSize()], indexing="ij"), -1).reshape(-1, 3)
    points = (index * image.GetSpacing()) @ direction.T + image.GetOrigin()
    inside = np.linalg.norm(points - CENTRE, axis=1) < RADIUS
    values = np.where(inside, 100.0, 5.0).reshape(image.GetSize()).transpose(2, 1, 0)  # (x, y, z) -> (z, y, x)
    ball = sitk.GetImageFromArray(values.astype(np.float32))
    ball.CopyInformation(image)
    return ball


@pytest.mark.parametrize("level", [50.0, None])
def test_surface_lies_on_the_ball_in_physical_space(level):
    mesh = render.surface(oblique_ball(), level)
    distance = np.linalg.norm(mesh.points - CENTRE, axis=1)
    assert mesh.n_cells > 100
    assert abs(np.median(distance) - RADIUS) < 1.0 and np.abs(distance - RADIUS).max() < 2.5


def test_before_and_after_panels(tmp_path):
    fixed = oblique_ball()
    truth = random_similarity(np.random.default_rng(0), CENTRE, max_shift_mm=30.0)
    path = tmp_path / "render.png"
    render.before_after(fixed, moved_copy(fixed, truth), truth, path, title="ball", window_size=(400, 200))
    picture = matplotlib.image.imread(path)
    assert picture.shape[:2] == (200, 400)
    left, right = picture[:, :200, :3], picture[:, 200:, :3]
    assert left.std() > 0.01 and right.std() > 0.01 and not np.allclose(left, right)
    assert [p.name for p in tmp_path.iterdir()] == ["render.png"]  # written atomically, nothing left over


def test_the_after_surface_lies_on_the_fixed_ball():
    fixed = oblique_ball()
    truth = random_similarity(np.random.default_rng(0), CENTRE, max_shift_mm=30.0)
    fixed_surface, before, after = render.before_after_surfaces(fixed, moved_copy(fixed, truth), truth)
    assert abs(np.median(np.linalg.norm(fixed_surface.points - CENTRE, axis=1)) - RADIUS) < 1.0
    moving_to_fixed = truth.GetInverse()
    expected = [moving_to_fixed.TransformPoint(point) for point in before.points.astype(float)]
    np.testing.assert_allclose(after.points, expected, atol=1e-6)
    # The brightest level of a two-valued ball lies just above its background: the blurred surface is a shell a few
    # mm outside the edge, centred on the ball.
    assert np.linalg.norm(after.points.mean(axis=0) - CENTRE) < 0.5
    assert np.abs(np.linalg.norm(after.points - CENTRE, axis=1) - RADIUS).max() < 4.0
    assert np.linalg.norm(before.points.mean(axis=0) - CENTRE) > 10.0
    assert np.median(np.abs(np.linalg.norm(before.points - CENTRE, axis=1) - RADIUS)) > 10.0


def test_the_brightest_level_finds_bone_beside_padding():
    """The MRI-DIR CT's -2048 HU padding outside its field of view had pulled the 'bone' level to -236 HU."""
    image = sitk.ReadImage(str(shared_path("mridir/mridir_ct_3p0mm.nii.gz")))
    assert 200.0 < render.brightest_tissue_level(image) < 500.0


@pytest.mark.parametrize("name", ["render.jpg", "render", "render.PNG.txt"])
def test_a_path_not_ending_in_png_is_refused(name, tmp_path):
    ball = oblique_ball()
    with pytest.raises(InputError, match=r"must end in \.png$"):
        render.before_after(ball, ball, sitk.Euler3DTransform(), tmp_path / name)
    assert not list(tmp_path.iterdir())
