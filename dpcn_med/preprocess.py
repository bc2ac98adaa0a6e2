"""From a physical image to a solver grid: foreground, intensity normalisation, resampling onto the canonical cube;
surface meshes and point clouds voxelised into images."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import SimpleITK as sitk
import torch
from torch import Tensor

from dpcn_med import io
from dpcn_med.arguments import check_integer, check_pair, check_real
from dpcn_med.errors import InputError
from dpcn_med.geometry import CanonicalGrid
from dpcn_med.modalities import MODALITIES

if TYPE_CHECKING:
    import pyvista

LOWEST_HU = -1024.0
"""No Hounsfield value lies below air's -1024 HU: a CT's voxels below it are the scanner's padding."""
OUTLIER_PERCENTILES = (0.1, 99.9)
OUTLIER_SPREADS = 10.0
"""Values more than this many ``OUTLIER_PERCENTILES`` ranges beyond them are outliers for Otsu's histogram."""
UNIFORM_SPREAD = 1e-6
"""Foreground percentiles closer than this fraction of the image's range are one intensity."""
MIN_SHRUNK_VOXELS = 4
"""``shrink_factors`` leaves at least this many voxels along each axis (or the axis as it is, if shorter)."""
SHRINK_SLACK = 1.3
"""An axis up to this many times finer than its share of ``max_voxels`` is left as it is (why this value:
docs/design_notes/preprocess.md)."""


@dataclass(frozen=True)
class Preprocessing:
    """How a volume becomes a solver grid; the defaults are the product's.

    Attributes:
        fill: fraction of the cube's side that the larger foreground diagonal of the pair spans, 0.1 to 1 (the rest
            is padding against wrap-around and room for any rotation).
        percentiles: foreground percentiles mapped to 0 and 1 for MR and ultrasound, ``0 <= low < high <= 100``.
        ct_window: Hounsfield units mapped to 0 and 1 for CT, ``low < high`` (air to 0, soft tissue near the middle,
            bone saturating).
        outline_weight: the solver sees this much (0 to 1) of the binary foreground blended with the normalised
            intensities (why: docs/design_notes/preprocess.md).
        max_voxels: larger images are first averaged down (``BinShrink``) to about this many voxels (at least 1000);
            the canonical grid is far coarser.
        ct_detection_hu: an image whose 1st percentile lies below this is taken for a CT when the modality is "auto"
            (air, and the scanner's padding, sit near -1000 HU or below; no MR or ultrasound goes there).

    Raises:
        InputError: a value of the wrong type or out of range, named with its value.
    """

    fill: float = 0.5
    outline_weight: float = 0.5
    max_voxels: int = 2_000_000
    percentiles: tuple[float, float] = (1.0, 99.0)
    ct_window: tuple[float, float] = (-1000.0, 1000.0)
    ct_detection_hu: float = -500.0

    def __post_init__(self) -> None:
        checked = {
            "fill": check_real("fill", self.fill, minimum=0.1, maximum=1.0),
            "outline_weight": check_real("outline_weight", self.outline_weight, minimum=0.0, maximum=1.0),
            "max_voxels": check_integer("max_voxels", self.max_voxels, minimum=1000),
            "percentiles": check_pair("percentiles", self.percentiles, minimum=0.0, maximum=100.0),
            "ct_window": check_pair("ct_window", self.ct_window),
            "ct_detection_hu": check_real("ct_detection_hu", self.ct_detection_hu),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)


def _strided_sample(values: np.ndarray) -> np.ndarray:
    """About a million of ``values``, evenly strided: plenty for a percentile."""
    flat = values.ravel()
    return flat[::max(1, flat.size // 1_000_000)]


def _binary_like(image: sitk.Image, array: np.ndarray) -> sitk.Image:
    """A boolean ``[z, y, x]`` array as a uint8 image on ``image``'s grid."""
    binary = sitk.GetImageFromArray(array.astype(np.uint8))
    binary.CopyInformation(image)
    return binary


def _outlier_bounds(values: np.ndarray) -> tuple[float, float] | None:
    """The bulk's ``OUTLIER_PERCENTILES`` when some of ``values`` lie more than ``OUTLIER_SPREADS`` times their
    distance beyond them, else ``None``."""
    low, high = np.percentile(_strided_sample(values), OUTLIER_PERCENTILES)
    margin = OUTLIER_SPREADS * (high - low)
    if margin > 0 and (values.min() < low - margin or values.max() > high + margin):
        return float(low), float(high)
    return None


def clip_outliers(image: sitk.Image) -> sitk.Image:
    """``image`` with values far outside its bulk (see :func:`foreground_mask`) clipped to the bulk's
    ``OUTLIER_PERCENTILES``, float32; ``image`` itself when there are none."""
    bounds = _outlier_bounds(sitk.GetArrayViewFromImage(image))
    return image if bounds is None else sitk.Clamp(image, sitk.sitkFloat32, *bounds)


def histogram_values(image: sitk.Image) -> sitk.Image:
    """``image`` as a histogram of its intensities should see it (display windows, contour levels), float32: a CT's
    padding below ``LOWEST_HU`` raised to air, then far outliers clipped (:func:`clip_outliers`) (why:
    docs/design_notes/preprocess.md)."""
    values = sitk.Cast(image, sitk.sitkFloat32)
    if sitk.GetArrayViewFromImage(values).min() < LOWEST_HU:
        values = sitk.Clamp(values, sitk.sitkFloat32, LOWEST_HU)
    return clip_outliers(values)


def _otsu(image: sitk.Image, counted: np.ndarray | None) -> tuple[sitk.Image, float]:
    """Otsu's threshold over the ``counted`` voxels (all when ``None``), far outliers clipped: the counted voxels
    above it (uint8, 1) and the threshold."""
    array = sitk.GetArrayViewFromImage(image)
    values = sitk.Cast(image, sitk.sitkFloat32)
    bounds = _outlier_bounds(array if counted is None else array[counted])
    if bounds is not None:
        values = sitk.Clamp(values, sitk.sitkFloat32, *bounds)
    otsu = sitk.OtsuThresholdImageFilter()
    otsu.SetInsideValue(0)
    otsu.SetOutsideValue(1)
    if counted is None:
        bright = otsu.Execute(values)
    else:
        otsu.SetMaskValue(1)
        bright = otsu.Execute(values, _binary_like(image, counted))
    return bright, otsu.GetThreshold()


def _drawn_along_an_edge(image: sitk.Image, inside: np.ndarray, counted: np.ndarray | None) -> bool:
    """Whether a mask is a segmentation: the median of its inner border and that of the voxels just outside it lie
    on opposite sides of the image's Otsu threshold (a box or a cut through the anatomy has the same on both)."""
    array = sitk.GetArrayViewFromImage(image)
    region = _binary_like(image, inside)
    inner = inside & ~sitk.GetArrayFromImage(sitk.BinaryErode(region, [1, 1, 1])).astype(bool)
    outer = sitk.GetArrayFromImage(sitk.BinaryDilate(region, [1, 1, 1])).astype(bool) & ~inside
    if counted is not None:
        outer &= counted
    if not inner.any() or not outer.any():
        return False
    threshold = _otsu(image, counted)[1]
    return bool((np.median(array[inner]) > threshold) != (np.median(array[outer]) > threshold))


def foreground_mask(image: sitk.Image, mask: sitk.Image | None = None) -> sitk.Image:
    """Voxels brighter than Otsu's threshold, the largest connected component, holes filled: a binary image.

    Otsu's threshold counts only the voxels that matter (why each: docs/design_notes/preprocess.md):

    - no CT padding: when the image goes below ``LOWEST_HU``, the voxels below it (the scanner's fill outside its
      circular field of view and its resampled edge) neither count nor are foreground.
    - no far outliers: values more than ``OUTLIER_SPREADS`` 0.1-99.9 percentile ranges beyond them are clipped to
      them.
    - only inside ``mask``, when given; the foreground lies within it. A mask drawn along an edge, a segmentation
      (the medians just inside and just outside its border on either side of the image's threshold), is itself the
      foreground.

    Args:
        image: any 3-D image.
        mask: where to look, binary, on ``image``'s grid.

    Returns:
        uint8 image on ``image``'s grid, 1 on the foreground; empty when no voxel counts.
    """
    array = sitk.GetArrayViewFromImage(image)
    counted = array >= LOWEST_HU if array.min() < LOWEST_HU else None
    if mask is not None:
        inside = sitk.GetArrayViewFromImage(mask) > 0
        within = inside if counted is None else inside & counted
        if _drawn_along_an_edge(image, inside, counted):
            return _binary_like(image, within)
        counted = within
    if counted is not None and not counted.any():
        return _binary_like(image, counted)
    components = sitk.RelabelComponent(sitk.ConnectedComponent(_otsu(image, counted)[0]), sortByObjectSize=True)
    filled = _fill_holes(components == 1)
    return filled if mask is None else sitk.And(filled, mask > 0)


def _fill_holes(mask: sitk.Image) -> sitk.Image:
    """``mask`` (uint8, 0 or 1) with every background region that no path through faces connects to the image's
    border filled: uint8, the voxels of ``sitk.BinaryFillhole(mask)``.

    Our own: labelling the background once is several times faster than either BinaryFillhole or scipy's
    ``binary_fill_holes`` on a head mask (docs/design_notes/preprocess.md).
    """
    background = sitk.ConnectedComponent(mask == 0)  # face connectivity: fullyConnected is off
    labels = sitk.GetArrayViewFromImage(background)
    outside = np.unique(np.concatenate([labels.take(end, axis).ravel() for axis in range(3) for end in (0, -1)]))
    kept = np.ones(int(labels.max()) + 1, dtype=bool)
    kept[outside] = False
    kept[0] = True  # the mask itself
    return _binary_like(mask, kept[labels])


def dilate(mask: sitk.Image, radius: int) -> sitk.Image:
    """``mask`` (binary, 0 outside) dilated by a ball of ``radius`` voxels: uint8, 1 on every voxel whose centre lies
    within ``radius + 1/2`` voxels (counted in voxels along each axis, whatever the spacing) of a voxel of ``mask``.

    The same voxels as ``sitk.BinaryDilate(mask, [radius] * 3)``, whose ball holds the offsets of squared length up
    to ``radius * (radius + 1)``, from a squared distance map (ITK's Maurer) in half its time
    (docs/design_notes/preprocess.md).
    """
    radius = check_integer("radius", radius, minimum=0)
    distance = sitk.SignedMaurerDistanceMap(mask, insideIsPositive=False, squaredDistance=True,
                                            useImageSpacing=False)
    return distance <= radius * (radius + 1)


def foreground_box(image: sitk.Image, mask: sitk.Image | None = None) -> tuple[np.ndarray, float]:
    """Physical (LPS, mm) centre and corner-to-corner diagonal length of the foreground's bounding box.

    Args:
        image: any 3-D image.
        mask: its :func:`foreground_mask`, if already computed.

    Raises:
        InputError: the image has no foreground (empty or constant).
    """
    box = bounding_box(foreground_mask(image) if mask is None else mask)
    if box is None:
        raise InputError("image has no foreground (empty or constant intensity)")
    start, size = box
    first = np.array(image.TransformContinuousIndexToPhysicalPoint((start - 0.5).tolist()))
    last = np.array(image.TransformContinuousIndexToPhysicalPoint((start + size - 0.5).tolist()))
    return (first + last) / 2, float(np.linalg.norm(last - first))


def bounding_box(mask: sitk.Image) -> tuple[np.ndarray, np.ndarray] | None:
    """``(start, size)``: the first voxel index ``(x, y, z)`` and the voxel counts of the box that holds every voxel
    of ``mask`` above 0 (int64 arrays), or ``None`` where there is none."""
    statistics = sitk.LabelShapeStatisticsImageFilter()
    statistics.ComputePerimeterOff()  # on by default, and most of the filter's time on a head mask
    statistics.Execute(sitk.Cast(mask > 0, sitk.sitkUInt8))
    if not statistics.HasLabel(1):
        return None
    start, size = np.split(np.asarray(statistics.GetBoundingBox(1), dtype=np.int64), 2)
    return start, size


def normalize_intensity(image: sitk.Image, percentiles: tuple[float, float] = (1.0, 99.0),
                        mask: sitk.Image | None = None) -> sitk.Image:
    """Map the ``percentiles`` of the foreground to 0 and 1 and clip to ``[0, 1]``: float32 image, same geometry.

    Robust to a few extreme voxels (markers, metal) and to the amount of background. ``mask``: the image's
    :func:`foreground_mask`, if already computed. A uniform foreground (a binary phantom, a voxelised mesh), whose
    percentiles coincide, maps to 1 and the image's minimum to 0.
    """
    percentiles = check_pair("percentiles", percentiles, minimum=0.0, maximum=100.0)
    array = sitk.GetArrayViewFromImage(image).astype(np.float32)
    inside = sitk.GetArrayFromImage(foreground_mask(image) if mask is None else mask).astype(bool)
    low, high = np.percentile(array[inside] if inside.any() else array, percentiles)
    if high - low <= UNIFORM_SPREAD * (array.max() - array.min()):
        low = array.min()
    scaled = np.clip((array - low) / max(high - low, 1e-12), 0.0, 1.0)
    out = sitk.GetImageFromArray(scaled)
    out.CopyInformation(image)
    return out


def detect_modality(image: sitk.Image, config: Preprocessing = Preprocessing()) -> str:
    """``"ct"`` when the image holds Hounsfield units (its 1st percentile is air), ``"mr"`` otherwise.

    Ultrasound cannot be told from MR by its intensities; both use the same robust percentiles.
    """
    sample = _strided_sample(sitk.GetArrayViewFromImage(image))
    return "ct" if np.percentile(sample, 1.0) < config.ct_detection_hu else "mr"


def normalize_modality(image: sitk.Image, modality: str, mask: sitk.Image, config: Preprocessing = Preprocessing()
                       ) -> sitk.Image:
    """Intensities in ``[0, 1]`` by modality: a fixed Hounsfield window for CT, foreground percentiles otherwise.

    Args:
        image: 3-D image.
        modality: one of :data:`MODALITIES`; ``"auto"`` uses :func:`detect_modality`.
        mask: the foreground (or user) mask of ``image``.
        config: windows and percentiles.
    """
    if modality not in MODALITIES:
        raise InputError(f"modality {modality!r} is not supported; use one of {', '.join(MODALITIES)}")
    if (detect_modality(image, config) if modality == "auto" else modality) != "ct":
        return normalize_intensity(image, config.percentiles, mask)
    # SimpleITK's window, not MONAI's ScaleIntensityRange (the same values): importing MONAI takes seconds, which a
    # command-line registration of a CT paid for one linear map.
    low, high = config.ct_window
    return sitk.IntensityWindowing(sitk.Cast(image, sitk.sitkFloat32), windowMinimum=low, windowMaximum=high,
                                   outputMinimum=0.0, outputMaximum=1.0)


def masked(image: sitk.Image, mask: sitk.Image) -> sitk.Image:
    """``image`` with every voxel outside ``mask`` (same grid) set to 0, float32."""
    return sitk.Mask(sitk.Cast(image, sitk.sitkFloat32), sitk.Cast(mask > 0, sitk.sitkUInt8))


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
    if spacing is None:
        fill = check_real("fill", fill, minimum=0.1, maximum=1.0)
        size = check_integer("size", size, minimum=2)
    centre, diagonal = foreground_box(image, mask)
    return CanonicalGrid(size, diagonal / (fill * size) if spacing is None else spacing, tuple(map(float, centre)))


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


@dataclass
class PreparedImage:
    """A volume ready for the canonical grid: normalised intensities blended with the foreground (zero outside a user
    mask), and the foreground itself.

    Attributes:
        image: float32 in ``[0, 1]`` on the input's grid (or a coarser one over the same space): what the solver
            sees.
        foreground: binary mask on the same grid (within the user's mask when given).
        modality: ``"ct"``, ``"mr"`` or ``"us"`` as used.
        centre: ``(3,)`` LPS centre of the foreground's bounding box, mm.
        diagonal: its corner-to-corner length, mm.
    """

    image: sitk.Image
    foreground: sitk.Image
    modality: str
    centre: np.ndarray
    diagonal: float


def shrink_factors(image: sitk.Image, max_voxels: int) -> list[int]:
    """Per-axis ``BinShrink`` factors bringing ``image`` near ``max_voxels``, shrinking fine axes more than coarse
    ones (a 4 mm slice axis stays as it is next to 1 mm in-plane pixels), and no axis below
    :data:`MIN_SHRUNK_VOXELS` voxels (a slab's few slices stay)."""
    size, spacing = np.asarray(image.GetSize()), np.asarray(image.GetSpacing(), dtype=float)
    largest = np.maximum(1, size // MIN_SHRUNK_VOXELS)
    overall = (np.prod(size, dtype=float) / max_voxels) ** (1 / 3)
    wanted = np.ceil(overall * spacing.min() / spacing - (SHRINK_SLACK - 1))
    factors = np.clip(wanted, 1, largest).astype(int)
    # Where an axis is too short or too coarse to take its share, the others shrink further, finest binned voxels
    # first, until no more than the slack above lets through on a cube.
    while np.prod(size // factors, dtype=float) > SHRINK_SLACK ** 3 * max_voxels and (factors < largest).any():
        binned = np.where(factors < largest, spacing * factors, np.inf)
        factors[np.argmin(binned)] += 1
    return factors.tolist()


def prepare(image: sitk.Image, *, modality: str = "auto", mask: sitk.Image | None = None,
            config: Preprocessing = Preprocessing(), mask_name: str = "mask") -> PreparedImage:
    """Normalise an image by modality, find its foreground (within the user's ``mask``, same grid, called
    ``mask_name`` in messages) and blend the two (``config.outline_weight``) into the image the solver sees.

    The result may be on a coarser grid than ``image`` (see ``Preprocessing.max_voxels``); it covers the same space.
    """
    factors = shrink_factors(image, config.max_voxels)
    if max(factors) > 1:
        image = sitk.BinShrink(image, factors)
        mask = None if mask is None else sitk.BinShrink(sitk.Cast(mask > 0, sitk.sitkFloat32), factors) >= 0.5
    foreground = foreground_mask(image, mask)
    if mask is not None and not sitk.GetArrayViewFromImage(foreground).any():
        raise InputError(f"{mask_name}: holds no foreground of its image (only background inside it); give a "
                         "mask that covers the anatomy, or leave it out")
    used = detect_modality(image, config) if modality == "auto" else modality
    normalised = normalize_modality(image, used, foreground, config)
    if mask is not None:
        normalised = masked(normalised, mask)
    weight = config.outline_weight
    blended = (weight * sitk.Cast(foreground, sitk.sitkFloat32)
               + (1.0 - weight) * sitk.Cast(normalised, sitk.sitkFloat32))
    centre, diagonal = foreground_box(image, foreground)
    return PreparedImage(blended, foreground, used, centre, diagonal)


def pair_grids(fixed: PreparedImage, moving: PreparedImage, size: int, config: Preprocessing = Preprocessing()
               ) -> tuple[CanonicalGrid, CanonicalGrid]:
    """The two canonical cubes of a pair: one shared spacing, chosen so the larger foreground diagonal spans
    ``config.fill`` of the side, each centred on its own foreground (DESIGN section 4)."""
    spacing = max(fixed.diagonal, moving.diagonal) / (config.fill * size)
    return (CanonicalGrid(size, spacing, tuple(float(c) for c in fixed.centre)),
            CanonicalGrid(size, spacing, tuple(float(c) for c in moving.centre)))


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


def voxelize(mesh: pyvista.DataSet, *, spacing: float = 1.0, margin: float = 10.0, name: str = "mesh") -> sitk.Image:
    """A surface mesh or point cloud (LPS, mm) as a binary float32 volume, so it registers like any image.

    A closed surface becomes its filled interior (pyvista's ``voxelize_binary_mask``); an open surface or a point
    cloud becomes the voxels its points fall in, dilated by one voxel so neighbouring points join up.

    Args:
        mesh: pyvista data set with at least one point, coordinates in LPS millimetres (as
            :func:`dpcn_med.io.read_mesh` returns them, converting a file marked ``SPACE=RAS``).
        spacing: isotropic voxel size, mm.
        margin: empty border around the mesh's bounding box, mm.
        name: what to call the mesh in messages (its file).

    Returns:
        Image with identity direction covering the mesh's bounds plus ``margin``; 1 inside, 0 outside.

    Raises:
        InputError: the volume would not fit in memory (a stray point far away, or coordinates not in mm).
    """
    bounds = np.asarray(mesh.bounds, dtype=np.float64).reshape(3, 2)
    origin = bounds[:, 0] - margin
    size = np.ceil((bounds[:, 1] + margin - origin) / spacing).astype(int) + 1
    extent = " x ".join(f"{length:.4g}" for length in bounds[:, 1] - bounds[:, 0])
    io.check_memory(f"{name} voxelised at {spacing:g} mm (its points span {extent} mm: a stray point, or not in mm?)",
                    tuple(int(length) for length in size))
    surface = mesh.extract_surface(algorithm="dataset_surface") if mesh.n_cells else None
    closed = surface is not None and surface.n_faces > 0 and surface.is_manifold
    if closed:
        import pyvista as pv  # imported here: pyvista pulls in VTK, which takes a second

        reference = pv.ImageData(dimensions=size.tolist(), spacing=(spacing,) * 3, origin=origin.tolist())
        filled = surface.voxelize_binary_mask(reference_volume=reference)
        # VTK point data runs x fastest, the same memory order as a SimpleITK [z, y, x] array.
        array = np.asarray(filled.point_data["mask"], dtype=np.float32).reshape(size[::-1])
    else:
        array = np.zeros(size[::-1], dtype=np.float32)
        index = np.rint((np.asarray(mesh.points, dtype=np.float64) - origin) / spacing).astype(int)
        array[index[:, 2], index[:, 1], index[:, 0]] = 1.0
    image = sitk.GetImageFromArray(array)
    image.SetOrigin(origin.tolist())
    image.SetSpacing((spacing,) * 3)
    if not closed:
        dilated = sitk.BinaryDilate(sitk.Cast(image, sitk.sitkUInt8), (1, 1, 1), sitk.sitkBox)
        image = sitk.Cast(dilated, sitk.sitkFloat32)
    return image
