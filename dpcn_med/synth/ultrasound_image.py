"""An ultrasound image simulated from a CT image, in the CT's physical space: a probe through a craniotomy.

:func:`dpcn_med.synth.simulated_ultrasound` works on a cubic tensor grid; this module puts it in physical space, as a
user's intra-operative 3-D ultrasound is: the CT resampled onto an isotropic cube over its foreground, the bone cut
away where the probe goes in (a craniotomy: an intact skull reflects and absorbs nearly all the sound), the cone
simulated, and the result cropped to the cone's bounding box, a SimpleITK image whose voxels lie where the CT's
anatomy is (the exact ground truth of a CT-ultrasound or, through an aligned MR, an MR-ultrasound pair).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med.arguments import check_integer, check_pair, check_real, check_sequence
from dpcn_med.errors import InputError
from dpcn_med.geometry import CanonicalGrid, affine_points
from dpcn_med.preprocess import foreground_box, resample_to_grid, to_tensor
from dpcn_med.synth.ultrasound import UltrasoundConfig, b_mode, simulated_ultrasound

DYNAMIC_RANGE_DB = 50.0
""":func:`ultrasound_image`'s default display range: a B-mode image's usual 40 to 60 dB."""


@dataclass(frozen=True)
class Craniotomy:
    """The opening in the skull that the probe looks through, and how the CT becomes the simulator's input.

    Attributes:
        radius_mm: bone within this distance of the probe's axis, on the probe's side of the head's centroid, is
            replaced by ``fill_hu`` (0: no opening, the skull intact).
        bone_hu: what counts as bone (HU, above soft tissue).
        fill_hu: HU of what replaces the cut bone (the dura and the fluid under it).
        window: Hounsfield units mapped to 0 and 1 for the simulator (its acoustic impedance is monotonic in the
            value, its diffuse backscatter proportional to it): air and fat below the low end are 0, bone above the
            high end 1. A narrow window keeps the brain's few tens of HU between CSF, grey and white matter as
            echoes; the CT's own window (-1000 to 1000 HU) would leave the brain one flat grey.
    """

    radius_mm: float = 25.0
    bone_hu: float = 300.0
    fill_hu: float = 10.0
    window: tuple[float, float] = (-50.0, 100.0)

    def __post_init__(self) -> None:
        """Raises: InputError: a value out of range, named with its value."""
        check_real("radius_mm", self.radius_mm, minimum=0.0)
        check_real("bone_hu", self.bone_hu)
        check_real("fill_hu", self.fill_hu, maximum=self.bone_hu, below=True)
        object.__setattr__(self, "window", check_pair("window", self.window))


def _unit_probe(probe: Sequence[float]) -> torch.Tensor:
    values = check_sequence("probe", probe, length=3)
    direction = torch.tensor([check_real(f"probe[{axis}]", float(v)) for axis, v in enumerate(values)],
                             dtype=torch.float64)
    if float(direction.norm()) == 0:
        raise InputError("probe is (0, 0, 0); give the beam direction (x, y, z) in LPS, pointing into the body")
    return direction / direction.norm()


def ultrasound_image(ct: sitk.Image, probe: Sequence[float], *, seed: int = 0, spacing: float = 1.5,
                     config: UltrasoundConfig | None = None, craniotomy: Craniotomy | None = None,
                     dynamic_range_db: float | None = DYNAMIC_RANGE_DB) -> tuple[sitk.Image, sitk.Image]:
    """A 3-D ultrasound cone of ``ct``'s anatomy, in ``ct``'s physical space.

    Args:
        ct: 3-D CT (or pseudo-CT) in Hounsfield units, any grid and direction.
        probe: beam direction ``(x, y, z)`` in LPS (any length but 0), pointing into the body: the probe sits on
            the side of the head this points away from, aimed at the foreground's centroid (as
            :func:`dpcn_med.synth.simulated_ultrasound` places it).
        seed: the simulator's draws (half-angle, depth, speckle), at least 0.
        spacing: isotropic voxel size of the ultrasound image, mm (> 0).
        config: the probe's field of view and the tissue acoustics (default :class:`UltrasoundConfig`);
            ``depth_range`` and ``standoff`` are fractions of the side of the cube that holds ``ct``'s foreground (its
            bounding-box diagonal).
        craniotomy: the opening in the skull and the simulator's CT window (default :class:`Craniotomy`).
        dynamic_range_db: the echoes log-compressed over this range (:func:`dpcn_med.synth.ultrasound.b_mode`), as
            a scanner exports them; ``None``: the raw echo intensities.

    Returns:
        ``(ultrasound, cone)``: float32 echoes in ``[0, 1]`` (0 outside the cone, above 0 inside it when
        compressed) and the uint8 cone of view, both on one grid: identity direction, ``spacing`` mm, cropped to the
        cone's bounding box.

    Raises:
        InputError: ``ct`` not a 3-D scalar image or without foreground, a malformed ``probe``, ``seed`` or
            ``spacing``, or a cone that misses the grid.
    """
    if ct.GetDimension() != 3 or ct.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"ct is a {ct.GetDimension()}-D image with {ct.GetNumberOfComponentsPerPixel()} components "
                         "per voxel; expected a 3-D scalar CT in Hounsfield units")
    direction = _unit_probe(probe)
    seed = check_integer("seed", seed, minimum=0)
    spacing = check_real("spacing", spacing, minimum=0.0, above=True)
    if dynamic_range_db is not None:
        dynamic_range_db = check_real("dynamic_range_db", dynamic_range_db, minimum=0.0, above=True)
    config, craniotomy = config or UltrasoundConfig(), craniotomy or Craniotomy()
    centre, diagonal = foreground_box(ct)
    size = 2 * math.ceil(diagonal / spacing / 2)  # even: the simulator's grid centre is voxel size // 2
    grid = CanonicalGrid(size, spacing, tuple(map(float, centre)))
    low, high = craniotomy.window
    hu = to_tensor(resample_to_grid(ct, grid, default=low), dtype=torch.float64)[0, 0]
    window = ((hu - low) / (high - low)).clamp(0.0, 1.0)
    if craniotomy.radius_mm > 0:
        window = _opened(window, hu, direction, spacing, craniotomy)
    generator = torch.Generator().manual_seed(seed)
    echoes, cone = simulated_ultrasound(window[None, None], generator, probe=direction, config=config)
    if dynamic_range_db is not None:
        echoes = b_mode(echoes, cone, dynamic_range_db)
    return _cropped(echoes[0, 0], cone[0, 0] > 0, grid)


def _opened(window: torch.Tensor, hu: torch.Tensor, direction: torch.Tensor, spacing: float,
            craniotomy: Craniotomy) -> torch.Tensor:
    """``window`` (the simulator's input, ``(N, N, N)``) with the bone near the probe's axis replaced: the axis runs
    along ``direction`` through the centroid of the foreground (``window > 0``, as the simulator finds it)."""
    points = affine_points(tuple(window.shape), torch.eye(3, dtype=window.dtype)[None])[0] * spacing  # mm, (x, y, z)
    foreground = (window > 0)[..., None]
    centroid = (points * foreground).sum((0, 1, 2)) / foreground.sum().clamp_min(1)
    offset = points - centroid
    along = offset @ direction
    radial = (offset - along[..., None] * direction).norm(dim=-1)
    cut = (hu > craniotomy.bone_hu) & (radial < craniotomy.radius_mm) & (along < 0)
    low, high = craniotomy.window
    return torch.where(cut, min(max((craniotomy.fill_hu - low) / (high - low), 0.0), 1.0), window)


def _cropped(echoes: torch.Tensor, cone: torch.Tensor, grid: CanonicalGrid) -> tuple[sitk.Image, sitk.Image]:
    """The echoes and the cone ``(N, N, N)`` as images on ``grid``, cropped to the cone's bounding box."""
    if not bool(cone.any()):
        raise InputError("the simulated cone of view holds no voxel of the grid; give a larger depth_range")
    inside = cone.nonzero()
    first, last = inside.amin(0).tolist(), inside.amax(0).tolist()  # torch order (z, y, x)
    crop = tuple(slice(a, b + 1) for a, b in zip(first, last))
    images = []
    for values, pixel in ((echoes[crop].float().numpy(), sitk.sitkFloat32),
                          (cone[crop].to(torch.uint8).numpy(), sitk.sitkUInt8)):
        image = sitk.Cast(sitk.GetImageFromArray(np.ascontiguousarray(values)), pixel)
        image.SetSpacing([grid.spacing] * 3)
        image.SetOrigin([o + index * grid.spacing for o, index in zip(grid.origin, first[::-1])])
        images.append(image)
    return images[0], images[1]
