"""3-D renders of a registration, before and after: both heads as surfaces in the fixed image's physical space.

pyvista is the optional ``mesh`` extra (it brings PyPI's VTK); without it :func:`before_after` raises
:class:`~dpcn_med.errors.InputError` saying how to install it. Renders off screen: no display is needed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError
from dpcn_med.geometry import homogeneous_matrix
from dpcn_med.preprocess import foreground_mask, histogram_values

if TYPE_CHECKING:
    import pyvista

FIXED_COLOUR, MOVING_COLOUR = "#d9d9d9", "#e6862e"


def _pyvista():
    try:
        import pyvista as pv  # imported here: VTK takes about a second to load and most runs render nothing
    except ImportError as error:
        raise InputError("3-D renders need pyvista, an optional dependency (it brings its own VTK): "
                         "pip install 'dpcn_med[mesh]'") from error
    return pv


def surface(image: sitk.Image, level: float | None = None, *, target_cells: int = 100_000) -> pyvista.PolyData:
    """An isosurface of the image in LPS mm: the outline of its foreground (``level=None``,
    :func:`dpcn_med.preprocess.foreground_mask`) or where its intensity crosses ``level``.

    Args:
        image: a 3-D scalar volume.
        level: intensity of the isosurface, or ``None`` for the foreground's outline.
        target_cells: the surface is decimated to about this many triangles (a render, not a measurement).
    """
    pv = _pyvista()
    # Smoothing by about a voxel gives a surface without voxel steps; on the mask, the 0.5 level is its old edge.
    volume = sitk.Cast(foreground_mask(image) if level is None else image, sitk.sitkFloat32)
    volume = sitk.SmoothingRecursiveGaussian(volume, float(max(image.GetSpacing())))
    grid = pv.ImageData(dimensions=volume.GetSize(), spacing=volume.GetSpacing())
    grid.point_data["values"] = sitk.GetArrayFromImage(volume).ravel()  # (z, y, x) in C order: x fastest, as VTK
    mesh = grid.contour([0.5 if level is None else level], scalars="values").triangulate()
    if mesh.n_cells > target_cells:
        mesh = mesh.decimate_pro(1.0 - target_cells / mesh.n_cells, preserve_topology=True)
    direction = np.reshape(image.GetDirection(), (3, 3))
    mesh.points = mesh.points @ direction.T + np.asarray(image.GetOrigin())  # index * spacing -> LPS
    return mesh


def brightest_tissue_level(image: sitk.Image) -> float:
    """The highest of three multi-level Otsu thresholds (of :func:`~dpcn_med.preprocess.histogram_values`): bone on
    a CT, the brightest tissue class on an MR."""
    otsu = sitk.OtsuMultipleThresholdsImageFilter()
    otsu.SetNumberOfThresholds(3)
    otsu.Execute(histogram_values(image))
    return float(max(otsu.GetThresholds()))


def before_after_surfaces(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform
                          ) -> tuple[pyvista.PolyData, pyvista.PolyData, pyvista.PolyData]:
    """The surfaces :func:`before_after` draws, in LPS mm: ``(fixed, before, after)``.

    Args:
        fixed, moving: the registered volumes.
        fixed_to_moving: the registration, fixed to moving (LPS mm).

    Returns:
        The fixed foreground's outline (:func:`surface`); the moving image's brightest tissue
        (:func:`brightest_tissue_level`) as stored; and that surface with its points moved through the inverse of
        ``fixed_to_moving``, onto the fixed image where the registration is right.
    """
    fixed_surface, moving_surface = surface(fixed), surface(moving, brightest_tissue_level(moving))
    after = moving_surface.copy()
    inverse = np.linalg.inv(homogeneous_matrix(fixed_to_moving))
    after.points = after.points @ inverse[:3, :3].T + inverse[:3, 3]
    return fixed_surface, moving_surface, after


def before_after(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform, path: str | os.PathLike,
                 *, title: str = "", window_size: tuple[int, int] = (1400, 700)) -> None:
    """Write a PNG of the two volumes, before (the moving image as stored) and after (through ``fixed_to_moving``):
    the fixed foreground's outline in grey and the moving image's brightest tissue (bone on a CT,
    :func:`brightest_tissue_level`) in translucent orange over it.

    Args:
        fixed, moving: the registered volumes.
        fixed_to_moving: the registration, fixed to moving (LPS mm); moving points go through its inverse.
        path: the PNG (``.png``), written atomically.
        title: shown above the two panels.

    Raises:
        InputError: ``path`` does not end in ``.png`` (docs/design_notes/report.md), or pyvista is not installed.
    """
    if Path(path).suffix.lower() != ".png":
        raise InputError(f"render path {path} must end in .png")
    pv = _pyvista()
    fixed_surface, moving_surface, after = before_after_surfaces(fixed, moving, fixed_to_moving)
    plotter = pv.Plotter(shape=(1, 2), off_screen=True, window_size=list(window_size), border=False)
    for column, (moved, label) in enumerate(((moving_surface, "before: moving as stored"),
                                             (after, "after: moving through the registration"))):
        plotter.subplot(0, column)
        plotter.add_mesh(fixed_surface, color=FIXED_COLOUR, smooth_shading=True)
        plotter.add_mesh(moved, color=MOVING_COLOUR, opacity=0.4, smooth_shading=True)
        plotter.add_text(label, position="upper_left", font_size=11)
        plotter.view_isometric()
        plotter.camera.up = (0.0, 0.0, 1.0)  # LPS: superior up
        plotter.reset_camera()
    if title:
        plotter.subplot(0, 0)
        plotter.add_text(title, position="lower_left", font_size=9)
    plotter.link_views()
    try:
        with io.atomic_output(path) as temporary:
            plotter.screenshot(str(temporary))
    finally:
        plotter.close()  # a failed screenshot keeps no render window open
