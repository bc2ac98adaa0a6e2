"""From a physical image to a solver grid: foreground, intensity normalisation, resampling onto the canonical cube."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import torch
from torch import Tensor

from dpcn_med.errors import InputError
from dpcn_med.geometry import CanonicalGrid


def foreground_mask(image: sitk.Image) -> sitk.Image:
    """Voxels brighter than Otsu's threshold, the largest connected component, holes filled: a binary image."""
    mask = sitk.OtsuThreshold(sitk.Cast(image, sitk.sitkFloat32), 0, 1)
    components = sitk.RelabelComponent(sitk.ConnectedComponent(mask), sortByObjectSize=True)
    largest = components == 1
    return sitk.BinaryFillhole(largest)


def foreground_box(image: sitk.Image, mask: sitk.Image | None = None) -> tuple[np.ndarray, float]:
    """Physical (LPS, mm) centre and corner-to-corner diagonal length of the foreground's bounding box.

    Args:
        image: any 3-D image.
        mask: its :func:`foreground_mask`, if already computed.

    Raises:
        InputError: the image has no foreground (empty or constant).
    """
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(foreground_mask(image) if mask is None else mask)
    if not stats.HasLabel(1):
        raise InputError("image has no foreground (empty or constant intensity)")
    start_x, start_y, start_z, size_x, size_y, size_z = stats.GetBoundingBox(1)
    first = np.array(image.TransformContinuousIndexToPhysicalPoint((start_x - 0.5, start_y - 0.5, start_z - 0.5)))
    last = np.array(image.TransformContinuousIndexToPhysicalPoint(
        (start_x + size_x - 0.5, start_y + size_y - 0.5, start_z + size_z - 0.5)))
    return (first + last) / 2, float(np.linalg.norm(last - first))


def normalize_intensity(image: sitk.Image, percentiles: tuple[float, float] = (1.0, 99.0),
                        mask: sitk.Image | None = None) -> sitk.Image:
    """Map the ``percentiles`` of the foreground to 0 and 1 and clip to ``[0, 1]``: float32 image, same geometry.

    Robust to a few extreme voxels (markers, metal) and to the amount of background. ``mask``: the image's
    :func:`foreground_mask`, if already computed.
    """
    array = sitk.GetArrayViewFromImage(image).astype(np.float32)
    inside = sitk.GetArrayFromImage(foreground_mask(image) if mask is None else mask).astype(bool)
    low, high = np.percentile(array[inside] if inside.any() else array, percentiles)
    scaled = np.clip((array - low) / max(high - low, 1e-12), 0.0, 1.0)
    out = sitk.GetImageFromArray(scaled)
    out.CopyInformation(image)
    return out


def canonical_grid(image: sitk.Image, size: int, *, fill: float = 0.5, spacing: float | None = None,
                   mask: sitk.Image | None = None) -> CanonicalGrid:
    """The canonical cube for one image: centred on its foreground, the foreground diagonal covering ``fill``.

    Args:
        image: any 3-D SimpleITK image.
        size: ``N`` voxels per side.
        fill: fraction of the cube's side the foreground's bounding-box diagonal spans (the rest is padding against
            wrap-around and room for rotation).
        spacing: isotropic spacing in mm, overriding ``fill``: the two volumes of a pair must share one, so that
            the solver's scale is physical.
        mask: the image's :func:`foreground_mask`, if already computed.
    """
    centre, diagonal = foreground_box(image, mask)
    return CanonicalGrid(size=size, spacing=spacing or diagonal / (fill * size), centre=tuple(float(c) for c in centre))


def resample_to_grid(image: sitk.Image, grid: CanonicalGrid, *, default: float = 0.0, slice_only: bool = False
                     ) -> sitk.Image:
    """Linear resampling of ``image`` onto ``grid`` (identity direction, isotropic spacing), float32.

    ``slice_only`` keeps only the grid's central z-plane: a ``size x size x 1`` image.
    """
    reference = sitk.Image([grid.size, grid.size, 1 if slice_only else grid.size], sitk.sitkFloat32)
    reference.SetSpacing([grid.spacing] * 3)
    reference.SetOrigin((*grid.origin[:2], grid.centre[2]) if slice_only else grid.origin)
    return sitk.Resample(sitk.Cast(image, sitk.sitkFloat32), reference, sitk.Transform(), sitk.sitkLinear, default,
                         sitk.sitkFloat32)


def to_tensor(image: sitk.Image, *, dtype: torch.dtype = torch.float32) -> Tensor:
    """A 3-D SimpleITK image as a ``(1, 1, D, H, W)`` tensor (array order ``[z, y, x]``)."""
    if image.GetDimension() != 3:
        raise InputError(f"image is {image.GetDimension()}-D (size {image.GetSize()}); expected a 3-D volume")
    return torch.from_numpy(sitk.GetArrayFromImage(image).astype(np.float64)).to(dtype)[None, None]


def _normalised_on_grid(image: sitk.Image, size: int, fill: float, spacing: float | None, slice_only: bool
                        ) -> tuple[Tensor, CanonicalGrid]:
    mask = foreground_mask(image)  # once: Otsu and connected components are the slow part
    grid = canonical_grid(image, size, fill=fill, spacing=spacing, mask=mask)
    resampled = resample_to_grid(normalize_intensity(image, mask=mask), grid, slice_only=slice_only)
    return to_tensor(resampled, dtype=torch.float64), grid


def solver_grid(image: sitk.Image, size: int, *, fill: float = 0.5, spacing: float | None = None,
                dtype: torch.dtype = torch.float32) -> tuple[Tensor, CanonicalGrid]:
    """Normalise and resample an image onto its canonical cube: ``((1, 1, N, N, N) tensor, grid)``.

    Pass the fixed volume's ``grid.spacing`` as ``spacing`` for the moving one, so that both share it.
    """
    tensor, grid = _normalised_on_grid(image, size, fill, spacing, slice_only=False)
    return tensor.to(dtype), grid


def solver_slice(image: sitk.Image, size: int, *, fill: float = 0.55, spacing: float | None = None,
                 dtype: torch.dtype = torch.float32) -> Tensor:
    """The axial slice through the foreground centre, normalised like :func:`solver_grid`: ``(1, 1, N, N)`` (y, x).

    It is the central z-plane of the canonical cube, so the foreground spans about ``fill`` of the side.
    """
    tensor, _ = _normalised_on_grid(image, size, fill, spacing, slice_only=True)
    return tensor[:, :, 0].to(dtype)
