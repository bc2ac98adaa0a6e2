"""Reports of a registration: the report.json content, orthogonal planes through a point and the overview PNG."""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import SimpleITK as sitk

from dpcn_med import __version__
from dpcn_med.errors import InputError
from dpcn_med.geometry import grid_centre, slicer_to_parent_ras
from dpcn_med.preprocess import foreground_box, foreground_mask, histogram_values

if TYPE_CHECKING:
    from dpcn_med.outputs import RegistrationSettings
    from dpcn_med.registration import RegistrationResult

PLANE_AXES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "axial": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "coronal": ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0)),
    "sagittal": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
}
"""LPS unit vectors along which the columns and the rows of each plane run, in the order returned by
:func:`orthogonal_planes`. Radiological display: patient left on the image right, anterior (axial) or superior
(coronal, sagittal) at the top, anterior on the left of the sagittal plane as in 3D Slicer."""

PLANE_EDGE_LABELS: dict[str, tuple[str, str, str, str]] = {
    "axial": ("R", "L", "A", "P"),
    "coronal": ("R", "L", "S", "I"),
    "sagittal": ("A", "P", "S", "I"),
}
"""Patient direction at the (left, right, top, bottom) edge of each plane of :data:`PLANE_AXES`."""

OVERVIEW_ROWS = ("before (as stored)", "after registration", "after: checkerboard")
OVERVIEW_PIXELS = 256
OVERVIEW_WIDTH_PX = 1500
OVERVIEW_PNG_COMPRESSION = 3
"""zlib level of the overview PNG (Pillow's default 6 takes about twice as long for a file a few percent smaller)."""
CHECKER_SQUARES = 8
"""Squares along each side of the checkerboard panels."""
WINDOW_PERCENTILES = (1.0, 99.0)
CONTOUR_COLOURS = ("#ffe600", "#ff2bd6")
"""One bright colour per contour level, in increasing intensity, readable on greyscale."""
STATISTICS_SIDE = 128
"""Images are subsampled to at most this many voxels per side for percentiles, thresholds and the foreground
centre (why: docs/design_notes/report.md)."""


def registration_report(result: RegistrationResult, *, fixed: str | os.PathLike | sitk.Image,
                        moving: str | os.PathLike | sitk.Image, fixed_mask: str | os.PathLike | None = None,
                        moving_mask: str | os.PathLike | None = None, settings: RegistrationSettings,
                        outputs: Sequence[str] = ()) -> dict:
    """The content of ``report.json``: inputs and their geometry, both estimates, confidence and its verdict, metric
    values, timings, the Slicer to-parent RAS matrix, versions and conventions (JSON-ready)."""
    import torch

    def described(source, image: sitk.Image | None) -> dict:
        entry = {"path": None if isinstance(source, sitk.Image) else str(source)}
        if image is not None:
            entry.update(size=list(image.GetSize()), spacing_mm=list(image.GetSpacing()),
                         origin_lps=list(image.GetOrigin()),
                         direction=np.asarray(image.GetDirection()).reshape(3, 3).tolist(),
                         pixel_type=image.GetPixelIDTypeAsString())
        return entry

    verdict = {"confidence": result.confidence, "success_probability": result.success_probability}
    return {
        "status": "low confidence" if settings.flagged(verdict) else "ok",
        "min_confidence": settings.min_confidence,
        "min_success_probability": settings.probability_threshold,
        "inputs": {"fixed": described(fixed, result.fixed_image), "moving": described(moving, result.moving_image),
                   "fixed_mask": None if fixed_mask is None else str(fixed_mask),
                   "moving_mask": None if moving_mask is None else str(moving_mask)},
        **result.to_dict(),
        "slicer_to_parent_ras": slicer_to_parent_ras(result.fixed_to_moving).tolist(),
        "conventions": "LPS millimetres; the transforms map fixed points to moving points (ITK's resampling "
                       "direction): sitk.Resample(moving, fixed, transform) aligns them. Slicer's to-parent RAS "
                       "matrix is inv(F T F), F = diag(-1, -1, 1, 1). The similarity's values (Mattes mutual "
                       "information, or -LC2 where one image is ultrasound): lower is better.",
        "outputs": list(outputs),
        "version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "software": {"python": platform.python_version(), "torch": torch.__version__,
                     "SimpleITK": sitk.Version_VersionString()},
    }


def orthogonal_planes(image: sitk.Image, centre: Sequence[float], *, extent: float, pixels: int = 256,
                      transform: sitk.Transform | None = None, default: float = 0.0) -> list[np.ndarray]:
    """The axial, coronal and sagittal planes of ``image`` through a physical point, for display.

    Each plane is a square of ``pixels x pixels`` samples, ``extent / pixels`` mm apart, aligned with the LPS axes,
    sampled by linear interpolation (SimpleITK resampling onto a one-voxel-thick reference image).

    Args:
        image: 3-D image, any spacing and direction.
        centre: ``(x, y, z)`` LPS point in mm the three planes pass through.
        extent: side of each plane in mm.
        pixels: samples along each side.
        transform: ``fixed_to_moving`` when ``image`` is the moving image: the plane point ``p`` shows
            ``image(transform(p))``, so moving planes through a registration result line up with the fixed planes
            through the same ``centre``. ``None`` samples the image as stored (identity).
        default: value where a plane leaves the image.

    Returns:
        ``[axial, coronal, sagittal]``, float32 arrays ``(pixels, pixels)`` indexed ``[row, column]``, pixel
        ``(pixels // 2, pixels // 2)`` at ``centre``, indices increasing towards:

        * axial (``z = centre z``): columns to patient left (+x), rows to posterior (+y); anterior at the top.
        * coronal (``y = centre y``): columns to patient left (+x), rows to inferior (-z); superior at the top.
        * sagittal (``x = centre x``): columns to posterior (+y), rows to inferior (-z); superior at the top,
          anterior on the left.

        Pixel ``(row, column)`` of a plane is the point ``centre + spacing * ((column - pixels // 2) * u +
        (row - pixels // 2) * v)`` with ``u, v`` its :data:`PLANE_AXES`, ``spacing = extent / pixels``; shown with
        ``imshow`` (row 0 at the top) it reads in the radiological convention.

    Raises:
        InputError: ``image`` is not 3-D, ``centre`` is not a 3-D point, or ``extent``/``pixels`` is not positive.
    """
    if image.GetDimension() != 3:
        raise InputError(f"image is {image.GetDimension()}-D (size {image.GetSize()}); orthogonal planes need a "
                         "3-D volume")
    if len(centre) != 3:
        raise InputError(f"centre {tuple(centre)} is not an (x, y, z) point in mm")
    if not extent > 0 or pixels < 1:
        raise InputError(f"extent {extent} mm and pixels {pixels} must both be positive")
    spacing = extent / pixels
    point = np.asarray(centre, dtype=float)
    planes = []
    for column_axis, row_axis in PLANE_AXES.values():
        u, v = np.asarray(column_axis), np.asarray(row_axis)
        reference = sitk.Image(pixels, pixels, 1, sitk.sitkFloat32)
        reference.SetSpacing((spacing, spacing, spacing))
        reference.SetDirection(tuple(np.column_stack([u, v, np.cross(u, v)]).ravel()))
        reference.SetOrigin(tuple(point - grid_centre(pixels) * spacing * (u + v)))
        plane = sitk.Resample(image, reference, transform if transform is not None else sitk.Transform(),
                              sitk.sitkLinear, default, sitk.sitkFloat32)
        planes.append(sitk.GetArrayFromImage(plane)[0])
    return planes


def overview_planes(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform, centre: Sequence[float],
                    extent: float) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The planes :func:`overview_figure` shows, :data:`OVERVIEW_PIXELS` a side (see :func:`orthogonal_planes`).

    Returns:
        ``(fixed, before, after)``, each ``[axial, coronal, sagittal]`` through ``centre``: the fixed image, the moving
        image as stored, and the moving image through ``fixed_to_moving`` (which lines up with the fixed planes where
        the registration is right). NaN outside each image's field of view: no contour runs along its edge, and it
        shows black in every panel.
    """
    fixed_planes = orthogonal_planes(fixed, centre, extent=extent, pixels=OVERVIEW_PIXELS, default=math.nan)
    before = orthogonal_planes(moving, centre, extent=extent, pixels=OVERVIEW_PIXELS, default=math.nan)
    after = orthogonal_planes(moving, centre, extent=extent, pixels=OVERVIEW_PIXELS, transform=fixed_to_moving,
                              default=math.nan)
    return fixed_planes, before, after


def overview_figure(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform,
                    path: str | os.PathLike[str], *, title: str = "", centre: Sequence[float] | None = None,
                    extent: float | None = None,
                    foregrounds: tuple[sitk.Image | None, sitk.Image | None] | None = None) -> None:
    """Write a PNG that shows at a glance whether a registration worked.

    Three rows by three columns (axial, coronal, sagittal, see :func:`orthogonal_planes`): the fixed image in
    greyscale with the moving image's contours, before registration (moving as stored) and after (moving through
    ``fixed_to_moving``), then a checkerboard of the fixed and the registered moving image.

    Args:
        fixed: 3-D fixed image.
        moving: 3-D moving image.
        fixed_to_moving: the registration result, mapping fixed LPS points to moving ones.
        path: ``.png`` file, written atomically.
        title: figure title; the centre and field of view are appended on a second line.
        centre: LPS point in mm the planes pass through; default the centre of the fixed image's foreground
            bounding box.
        extent: field of view in mm; default the fixed image's largest physical side.
        foregrounds: ``(fixed, moving)`` binary masks of each image's foreground, in its physical space on any grid
            (a registration's, :attr:`~dpcn_med.result.RegistrationResult.fixed_foreground`); default (or ``None`` for
            one) :func:`~dpcn_med.preprocess.foreground_mask` of the image, found again.

    Raises:
        InputError: ``path`` does not end in ``.png``, or an image is not 3-D.

    Notes:
        Greyscale windows are the 1st..99th percentiles of each image's foreground. Contours are drawn at the moving
        image's two multi-level Otsu thresholds (typically the outline of the object and a boundary inside it), a
        CT's padding and far outliers left out.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"overview path {path} must end in .png")
    for name, image in (("fixed", fixed), ("moving", moving)):
        if image.GetDimension() != 3:
            raise InputError(f"{name} image is {image.GetDimension()}-D (size {image.GetSize()}); the overview "
                             "needs 3-D volumes")
    from dpcn_med.io import atomic_output

    fixed_small, moving_small = _subsampled(fixed), _subsampled(moving)
    fixed_foreground, moving_foreground = (
        foreground_mask(small) if mask is None else _on_grid(mask, small)
        for small, mask in zip((fixed_small, moving_small), foregrounds or (None, None), strict=True))
    if centre is None:
        centre = foreground_box(fixed_small, fixed_foreground)[0]
    if extent is None:
        extent = max(size * spacing for size, spacing in zip(fixed.GetSize(), fixed.GetSpacing()))
    fixed_window = _window(fixed_small, fixed_foreground)
    moving_window = _window(moving_small, moving_foreground)
    levels = _contour_levels(moving_small)

    planes = overview_planes(fixed, moving, fixed_to_moving, centre, extent)
    centre_text = ", ".join(f"{c:.1f}" for c in centre)
    subtitle = f"planes through ({centre_text}) mm LPS, field of view {extent:.0f} mm"
    figure = _overview_canvas(planes, (fixed_window, moving_window), levels,
                              f"{title}\n{subtitle}" if title else subtitle)
    with atomic_output(path) as temporary:
        figure.save(temporary, format="PNG", compress_level=OVERVIEW_PNG_COMPRESSION)


def _font(size: int):
    """Pillow's built-in scalable font at ``size`` pixels (its bitmap font where Pillow has no FreeType)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError):  # Pillow < 10.1, or built without FreeType
        return ImageFont.load_default()


def _overview_canvas(planes: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]],
                     windows: tuple[tuple[float, float], tuple[float, float]], levels: Sequence[float], title: str):
    """The overview as a Pillow RGB image :data:`OVERVIEW_WIDTH_PX` wide: the title, then :data:`OVERVIEW_ROWS` by
    :data:`PLANE_AXES` panels, drawn with Pillow (why not matplotlib: docs/design_notes/report.md).

    Args:
        planes: ``(fixed, before, after)`` of :func:`overview_planes`.
        windows: the display windows of the fixed and the moving image (:func:`_window`).
        levels: the moving image's contour levels (:func:`_contour_levels`).
        title: one or two lines above the panels.
    """
    from PIL import Image, ImageDraw

    fixed_planes, before, after = planes
    fixed_window, moving_window = windows
    columns, rows = len(PLANE_AXES), len(OVERVIEW_ROWS)
    margin, gap, heading = 44, 6, 30
    panel = (OVERVIEW_WIDTH_PX - margin - gap * columns) // columns
    title_height = 30 + 26 * title.count("\n")
    top = title_height + heading
    canvas = Image.new("RGB", (OVERVIEW_WIDTH_PX, top + rows * (panel + gap)), "black")
    draw = ImageDraw.Draw(canvas)
    draw.multiline_text((OVERVIEW_WIDTH_PX // 2, 8), title, fill="white", font=_font(22), anchor="ma",
                        align="center")
    labels, headings = _font(17), _font(20)
    for column, plane_name in enumerate(PLANE_AXES):
        left = margin + column * (panel + gap)
        draw.text((left + panel // 2, top - 6), plane_name, fill="white", font=headings, anchor="mb")
        fixed_grey = _normalised(fixed_planes[column], fixed_window)
        shown = [(fixed_grey, before[column]), (fixed_grey, after[column]),
                 (_checkerboard(fixed_grey, _normalised(after[column], moving_window)), None)]
        for row, (grey, contoured) in enumerate(shown):
            corner = (left, top + row * (panel + gap))
            image = Image.fromarray(np.round(255 * grey).astype(np.uint8)).resize((panel, panel), Image.NEAREST)
            canvas.paste(image.convert("RGB"), corner)
            if contoured is not None:
                _draw_contours(draw, contoured, levels, corner, panel / contoured.shape[1])
            _label_edges(draw, corner, panel, PLANE_EDGE_LABELS[plane_name], labels)
            draw.rectangle((corner[0] - 1, corner[1] - 1, corner[0] + panel, corner[1] + panel), outline="#555555")
    for row, label in enumerate(OVERVIEW_ROWS):
        text = Image.new("RGB", (panel, margin - 8), "black")
        ImageDraw.Draw(text).text((panel // 2, (margin - 8) // 2), label, fill="white", font=headings, anchor="mm")
        canvas.paste(text.rotate(90, expand=True), (2, top + row * (panel + gap)))
    return canvas


def _subsampled(image: sitk.Image) -> sitk.Image:
    """``image`` keeping every n-th voxel so that no side exceeds :data:`STATISTICS_SIDE` voxels."""
    factors = [max(1, math.ceil(size / STATISTICS_SIDE)) for size in image.GetSize()]
    return sitk.Shrink(image, factors) if max(factors) > 1 else image


def _on_grid(mask: sitk.Image, reference: sitk.Image) -> sitk.Image:
    """``mask`` on ``reference``'s grid, by nearest neighbour (0 outside it)."""
    return sitk.Resample(mask, reference, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)


def _window(image: sitk.Image, foreground: sitk.Image) -> tuple[float, float]:
    """Display window: the :data:`WINDOW_PERCENTILES` of the intensities on the image's ``foreground`` (of all, when
    it is empty), never empty (why the foreground: docs/design_notes/report.md)."""
    values = sitk.GetArrayViewFromImage(image)
    inside = sitk.GetArrayViewFromImage(foreground).astype(bool)
    low, high = np.percentile(values[inside] if inside.any() else values, WINDOW_PERCENTILES)
    return float(low), float(max(high, low + 1e-6))


def _normalised(plane: np.ndarray, window: tuple[float, float]) -> np.ndarray:
    """``plane`` mapped from ``window`` to ``[0, 1]``, clipped, NaN (outside the image) to 0."""
    low, high = window
    return np.nan_to_num(np.clip((plane - low) / (high - low), 0.0, 1.0), nan=0.0)


def _contour_levels(image: sitk.Image) -> list[float]:
    """The multi-level Otsu thresholds of ``image``'s :func:`~dpcn_med.preprocess.histogram_values` (one per contour
    colour), strictly increasing."""
    otsu = sitk.OtsuMultipleThresholdsImageFilter()
    otsu.SetNumberOfThresholds(len(CONTOUR_COLOURS))
    otsu.Execute(histogram_values(image))
    return sorted(set(otsu.GetThresholds()))  # a two-valued image gives repeated thresholds


def _draw_contours(draw, plane: np.ndarray, levels: Sequence[float], corner: tuple[int, int], zoom: float
                   ) -> None:
    """Contours of ``plane`` at ``levels`` in :data:`CONTOUR_COLOURS` onto a Pillow ``draw``, the plane shown from
    ``corner`` (pixels) at ``zoom`` pixels per plane pixel; levels the plane never crosses, and NaN (outside the image),
    draw nothing."""
    import contourpy  # matplotlib's own contouring, without matplotlib

    finite = np.isfinite(plane)
    if not finite.any():
        return
    generator = contourpy.contour_generator(z=np.ma.masked_array(np.nan_to_num(plane), mask=~finite),
                                            line_type=contourpy.LineType.Separate)
    low, high = float(plane[finite].min()), float(plane[finite].max())
    for level, colour in zip(levels, CONTOUR_COLOURS):
        if not low < level < high:
            continue
        for line in generator.lines(level):
            # Pixel (row, column) of the plane covers [column, column + 1) x [row, row + 1) of the panel, in plane
            # pixels: its centre is at + 0.5.
            points = ((line + 0.5) * zoom + np.asarray(corner)).ravel().tolist()
            draw.line(points, fill=colour, width=2)


def _checkerboard(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``first`` and ``second`` (same shape) alternating in :data:`CHECKER_SQUARES` squares per side."""
    rows, columns = first.shape
    square = max(1, max(rows, columns) // CHECKER_SQUARES)
    parity = (np.arange(rows)[:, None] // square + np.arange(columns)[None, :] // square) % 2
    return np.where(parity == 0, first, second)


def _label_edges(draw, corner: tuple[int, int], panel: int, labels: tuple[str, str, str, str], font) -> None:
    """Patient directions at the (left, right, top, bottom) edges of the panel of side ``panel`` at ``corner``; a dark
    outline keeps the letters readable on white checkerboard squares."""
    x, y = corner
    left, right, top, bottom = labels
    style = {"fill": "#9fd0ff", "font": font, "stroke_width": 2, "stroke_fill": "black"}
    draw.text((x + 4, y + panel // 2), left, anchor="lm", **style)
    draw.text((x + panel - 4, y + panel // 2), right, anchor="rm", **style)
    draw.text((x + panel // 2, y + 3), top, anchor="mt", **style)
    draw.text((x + panel // 2, y + panel - 3), bottom, anchor="mb", **style)
