"""Tests for dpcn_med.report: plane orientation on an oblique, anisotropic phantom, and the overview PNG."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.preprocess import foreground_mask
from dpcn_med.report import (
    OVERVIEW_PIXELS,
    _contour_levels,
    _window,
    orthogonal_planes,
    overview_figure,
    overview_planes,
)

CENTRE = np.array([10.0, -20.0, 30.0])
PIXELS = 64
EXTENT = 64.0  # 1 mm pixels
# One marker per plane, offset from CENTRE within that plane only (LPS mm), far (>= 10 mm) from the other planes,
# with the pixel where the documented orientation puts it: (row, column), centre pixel (32, 32).
MARKERS = {
    "axial": ((12.0, -16.0, 0.0), (16, 44)),  # patient left, anterior: right half, top half
    "coronal": ((-14.0, 0.0, 18.0), (14, 18)),  # patient right, superior: left half, top half
    "sagittal": ((0.0, -17.0, 12.0), (20, 15)),  # anterior, superior: left half, top half
}


def _rotation(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    return np.array(sitk.VersorTransform(axis, angle).GetMatrix()).reshape(3, 3)


def _phantom(points: list[np.ndarray], *, size: tuple[int, int, int], spacing: tuple[float, float, float],
             direction: np.ndarray, sigma: float = 3.0) -> sitk.Image:
    """Gaussian blobs at LPS ``points`` (mm) on a grid centred at CENTRE with the given geometry."""
    image = sitk.Image(size, sitk.sitkFloat32)
    image.SetSpacing(spacing)
    image.SetDirection(tuple(direction.ravel()))
    origin = CENTRE - direction @ (np.asarray(spacing) * (np.asarray(size) - 1) / 2)
    image.SetOrigin(tuple(origin))
    index = np.stack(np.meshgrid(*(np.arange(n) for n in size), indexing="ij"), axis=-1)  # [x, y, z, 3]
    physical = origin + (index * spacing) @ direction.T
    values = sum(np.exp(-np.sum((physical - p) ** 2, axis=-1) / (2 * sigma**2)) for p in points)
    array = sitk.GetImageFromArray(values.transpose(2, 1, 0).astype(np.float32))  # numpy is [z, y, x]
    array.CopyInformation(image)
    return array


def _oblique_phantom(shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> sitk.Image:
    """The three MARKERS moved by ``shift``, on an anisotropic grid with an oblique, axis-flipping direction."""
    direction = _rotation((0.3, 0.5, 0.2), 0.6) @ np.diag([-1.0, -1.0, 1.0])
    return _phantom([CENTRE + offset + np.asarray(shift) for offset, _ in MARKERS.values()], size=(40, 30, 24),
                    spacing=(1.5, 2.0, 2.5), direction=direction)


def _peak(plane: np.ndarray) -> np.ndarray:
    """(row, column) centroid of the plane's values above half its maximum."""
    weights = np.where(plane > plane.max() / 2, plane, 0.0)
    rows, columns = np.indices(plane.shape)
    return np.array([np.sum(rows * weights), np.sum(columns * weights)]) / weights.sum()


class TestOrthogonalPlanes:
    def test_markers_at_documented_pixels(self):
        planes = orthogonal_planes(_oblique_phantom(), CENTRE, extent=EXTENT, pixels=PIXELS)
        assert [plane.shape for plane in planes] == [(PIXELS, PIXELS)] * 3
        assert all(plane.dtype == np.float32 for plane in planes)
        for plane, (_, expected) in zip(planes, MARKERS.values()):
            np.testing.assert_allclose(_peak(plane), expected, atol=0.25)

    def test_radiological_orientation(self):
        axial, coronal, sagittal = (_peak(plane) for plane in
                                    orthogonal_planes(_oblique_phantom(), CENTRE, extent=EXTENT, pixels=PIXELS))
        half = PIXELS / 2
        assert axial[1] > half and axial[0] < half  # patient left on the image right, anterior at the top
        assert coronal[1] < half and coronal[0] < half  # patient right on the image left, superior at the top
        assert sagittal[1] < half and sagittal[0] < half  # anterior on the left, superior at the top

    def test_translation_lines_moving_up_with_fixed(self):
        shift = np.array([6.0, -4.0, 8.0])
        moving = _phantom([CENTRE + offset + shift for offset, _ in MARKERS.values()], size=(36, 36, 36),
                          spacing=(1.8, 1.8, 1.8), direction=_rotation((1.0, 0.0, 1.0), -0.4))
        fixed_to_moving = sitk.TranslationTransform(3, tuple(shift))
        planes = orthogonal_planes(moving, CENTRE, extent=EXTENT, pixels=PIXELS, transform=fixed_to_moving)
        for plane, (_, expected) in zip(planes, MARKERS.values()):
            np.testing.assert_allclose(_peak(plane), expected, atol=0.25)
        as_stored = orthogonal_planes(moving, CENTRE + shift, extent=EXTENT, pixels=PIXELS)
        for through_transform, shifted in zip(planes, as_stored):
            np.testing.assert_allclose(through_transform, shifted, atol=1e-5)

    def test_default_outside_the_image(self):
        planes = orthogonal_planes(_oblique_phantom(), CENTRE, extent=400.0, pixels=16, default=math.nan)
        assert all(np.isnan(plane[0, 0]) and np.isfinite(plane[8, 8]) for plane in planes)

    def test_rejects_2d_image(self):
        with pytest.raises(InputError, match="image is 2-D"):
            orthogonal_planes(sitk.Image(8, 8, sitk.sitkFloat32), (0.0, 0.0), extent=10.0)


class TestOverviewPlanes:
    def test_after_lines_up_with_fixed_and_before_does_not(self):
        shift = (5.0, 3.0, -4.0)
        fixed_planes, before, after = overview_planes(_oblique_phantom(), _oblique_phantom(shift),
                                                      sitk.TranslationTransform(3, shift), CENTRE, EXTENT)
        for fixed_plane, before_plane, after_plane in zip(fixed_planes, before, after):
            assert fixed_plane.shape == after_plane.shape == (OVERVIEW_PIXELS, OVERVIEW_PIXELS)
            both = np.isfinite(fixed_plane) & np.isfinite(after_plane)
            assert both.mean() > 0.7 and fixed_plane[both].max() > 0.8  # the plane's marker, mostly in both views
            # Linear interpolation of 3 mm blobs on 1.5..2.5 mm voxels, sampled at other points of the two grids.
            np.testing.assert_allclose(after_plane[both], fixed_plane[both], atol=0.15)
            stored = np.isfinite(fixed_plane) & np.isfinite(before_plane)
            assert np.abs(before_plane - fixed_plane)[stored].max() > 0.6  # 7 mm apart as stored


class TestOverviewFigure:
    def test_writes_readable_png_and_no_temporary_files(self, tmp_path):
        from matplotlib.image import imread

        shift = (5.0, 3.0, -4.0)
        path = tmp_path / "overview.png"
        overview_figure(_oblique_phantom(), _oblique_phantom(shift), sitk.TranslationTransform(3, shift),
                        path, title="phantom")
        pixels = imread(path)
        assert pixels.ndim == 3 and 1400 <= pixels.shape[1] <= 1600 and pixels.shape[0] > 1000
        assert pixels[..., :3].std() > 0.02
        assert list(tmp_path.iterdir()) == [path]

    def test_drawn_without_importing_matplotlib(self, tmp_path):
        """matplotlib's import was a third of the second the overview cost a command-line registration."""
        script = ("import sys, SimpleITK as sitk\n"
                  "from dpcn_med.report import overview_figure\n"
                  "image = sitk.GaussianSource(sitk.sitkFloat32, [24, 24, 24], [5, 5, 5], [12, 12, 12], 100)\n"
                  f"overview_figure(image, image, sitk.Transform(), {str(tmp_path / 'o.png')!r}, title='t')\n"
                  "print(sorted(name for name in sys.modules if name.split('.')[0] == 'matplotlib'))\n")
        run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
        assert run.stdout.strip() == "[]"
        assert (tmp_path / "o.png").read_bytes()[:4] == b"\x89PNG"

    def test_given_foregrounds_are_used_on_any_grid_in_place_of_finding_them(self, tmp_path, monkeypatch):
        """A registration's foregrounds (on a coarser grid) draw the same figure as those found again, without the
        second search for them (a third of the overview's time on a 1 mm head)."""
        from matplotlib.image import imread

        import dpcn_med.report

        shift = (5.0, 3.0, -4.0)
        fixed, moving = _oblique_phantom(), _oblique_phantom(shift)
        arguments = (fixed, moving, sitk.TranslationTransform(3, shift))
        overview_figure(*arguments, tmp_path / "found.png", title="phantom")
        coarse = [sitk.Shrink(foreground_mask(image), [2, 2, 2]) for image in (fixed, moving)]
        monkeypatch.setattr(dpcn_med.report, "foreground_mask", lambda *args, **kwargs: 1 / 0)
        overview_figure(*arguments, tmp_path / "given.png", title="phantom", foregrounds=tuple(coarse))
        found, given = imread(tmp_path / "found.png"), imread(tmp_path / "given.png")
        assert found.shape == given.shape and np.abs(found - given).mean() < 0.02
        empty = sitk.Image(coarse[1].GetSize(), sitk.sitkUInt8)
        empty.CopyInformation(coarse[1])
        overview_figure(*arguments, tmp_path / "empty.png", title="phantom", foregrounds=(coarse[0], empty))
        assert np.abs(imread(tmp_path / "empty.png") - given).mean() > 0.0  # the moving window is another one

    def test_rejects_other_suffix(self, tmp_path):
        image = _oblique_phantom()
        with pytest.raises(InputError, match=r"must end in \.png"):
            overview_figure(image, image, sitk.Transform(), tmp_path / "overview.jpg")

    def test_a_title_with_dollar_signs_is_plain_text(self, tmp_path):
        """matplotlib read 'a$_$b' as TeX and raised: a file name lost the whole registration."""
        image = _oblique_phantom()
        overview_figure(image, image, sitk.Transform(), tmp_path / "o.png", title="moving_$_$.nii.gz onto x$\\q$")
        assert (tmp_path / "o.png").read_bytes()[:4] == b"\x89PNG"


def _shell_and_core(size: int = 128) -> sitk.Image:
    """A ball of 100 (radius 12 voxels) around a core of 300 (radius 6): 0.34% of the volume."""
    z, y, x = np.mgrid[:size, :size, :size] - size / 2
    radius = np.sqrt(x ** 2 + y ** 2 + z ** 2)
    return sitk.GetImageFromArray((100.0 * (radius < 12) + 200.0 * (radius < 6)).astype(np.float32))


class TestDisplayStatistics:
    def test_the_window_spans_a_small_object(self):
        """Over the whole image the window was (0, 1e-6): shell and core both white."""
        image = _shell_and_core()
        low, high = _window(image, foreground_mask(image))
        assert low <= 100.0 < high and high >= 250.0

    def test_contour_levels_leave_out_padding_and_hot_voxels(self):
        array = sitk.GetArrayFromImage(_shell_and_core(64)) - 1000.0  # air -1000, shell -900, core -700
        array[:, :, :6] = -2048.0  # a CT's padding beside its field of view
        array[32, 32, 50:58] = 3.0e5  # 8 hot voxels
        levels = _contour_levels(sitk.GetImageFromArray(array))
        assert len(levels) == 2 and -1000.0 < levels[0] < -900.0 < levels[1] < -700.0
