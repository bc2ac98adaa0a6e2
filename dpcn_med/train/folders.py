"""Real registered pairs from a folder: discovery, ground truth, and a dataset on the solver's canonical grids.

Layout::

    ROOT/
      PAIR_ID/                    one folder per pair (plain files and hidden folders in ROOT are ignored)
        fixed.*   or ct.*         the fixed image
        moving.*  or mr.*, us.*   the moving image
        exactly one ground truth:
          *.tfm, *.h5, *.hdf5     an ITK transform mapping FIXED physical points to MOVING ones (what
                                  ``dpcn-med register`` writes), rigid or similarity (an affine file is accepted when
                                  its matrix is a similarity, as Slicer saves every linear transform as affine)
          *.standard              a RIRE ground-truth file: the "From" volume is the fixed one (CT or PET in RIRE)

An image is any file or folder :func:`dpcn_med.io.read_image` reads: ``.nii.gz``, ``.nii``, ``.nrrd``, ``.nhdr``,
``.mha``, ``.mhd`` (its ``.raw`` beside it), or a folder of DICOM slices (``ct/``). Its role is the part of its name
before the first dot, case-insensitive: ``CT.nii.gz`` is the fixed image, ``mr/`` a DICOM moving image. The names
``ct``, ``mr`` and ``us`` also set the intensity normalisation (:func:`dpcn_med.preprocess.prepare`); ``fixed`` and
``moving`` leave it to detection, as ``dpcn-med register`` does by default.

A RIRE ``.standard`` file lists points of the "From" volume in its own frame (millimetres along its voxel axes from
the centre of voxel 0, i.e. ``index * spacing``) and their positions in the "To" frame. They become physical points
through each image's origin and direction (``x = origin + direction @ p``): RIRE's MetaImage files have origin 0 and
identity direction, so RIRE millimetres are then ITK's LPS points, as in RIRE's own ITK transforms. Reoriented copies
(voxel order changed, e.g. to RAS) and cropped copies (the points count from the original voxel 0) break this;
converted copies with another origin or direction do not. "From" points outside the fixed image are refused (roles
swapped, or a crop).

Convention:
    Physical space is ITK's LPS in millimetres and ground truths map fixed to moving, as in :mod:`dpcn_med.geometry`;
    poses on the grids follow the solver's contract ``fixed(p) ~ moving(scale * rotation @ p + translation)``.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from dpcn_med import io
from dpcn_med.arguments import check_pair
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.geometry import CanonicalGrid, homogeneous_matrix, scale_and_rotation, similarity_transform
from dpcn_med.preprocess import (
    MODALITIES,
    PreparedImage,
    Preprocessing,
    pair_grids,
    prepare,
    resample_to_grid,
    to_tensor,
)
from dpcn_med.solver import PoseTarget
from dpcn_med.solver.validation import check_grid_bandwidth
from dpcn_med.synth import slab_mask

FIXED_NAMES = ("fixed", "ct")
"""Names (before the first dot) of a pair's fixed image."""
MOVING_NAMES = ("moving", "mr", "us")
"""Names of a pair's moving image."""
IMAGE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")
"""Image files a pair folder may hold (besides DICOM folders)."""
TRUTH_SUFFIXES = (".tfm", ".h5", ".hdf5", ".standard")
"""Ground-truth files: ITK transforms and RIRE ``.standard`` files (``.txt`` is left out: it is usually notes)."""
RIGID_FIT_TOLERANCE_MM = 0.5
"""Largest distance (mm) between a RIRE "To" point and the fitted rigid image of its "From" point."""

_TABLE_HEADER = re.compile(r"^\s*Point\s+x\s+y\s+z\s+new_x\s+new_y\s+new_z\s*$", re.IGNORECASE)
_ROW_START = re.compile(r"^\s*\d")


def derived_seed(*parts: int) -> int:
    """A seed for one stream of draws named by ``parts`` (non-negative integers: a seed, a rank, an index, a step),
    through numpy's SeedSequence: streams of different parts do not overlap, as sums of scaled parts can."""
    return int(np.random.SeedSequence(parts).generate_state(1)[0])


@dataclass(frozen=True)
class PairFiles:
    """The files of one pair folder.

    Attributes:
        id: the folder's name.
        fixed: fixed image (file or DICOM folder).
        moving: moving image.
        truth: ground-truth transform file (fixed to moving).
    """

    id: str
    fixed: Path
    moving: Path
    truth: Path


@dataclass(frozen=True)
class PairGrids:
    """A pair on its two canonical grids, prepared as :func:`dpcn_med.register` prepares its inputs.

    Attributes:
        files: where it came from.
        fixed: ``(1, N, N, N)`` float32 fixed grid (torch order z, y, x).
        moving: ``(1, N, N, N)`` float32 moving grid.
        fixed_foreground: ``(1, N, N, N)`` bool, the fixed image's foreground on its grid.
        fixed_grid: the fixed grid in physical space (centre ``c_f``, spacing ``h``).
        moving_grid: the moving grid (centre ``c_m``, the same spacing).
        fixed_to_moving: the ground truth, LPS mm.
        target: the ground truth on the grids (:func:`pose_on_grids`), batch 1.
    """

    files: PairFiles
    fixed: Tensor
    moving: Tensor
    fixed_foreground: Tensor
    fixed_grid: CanonicalGrid
    moving_grid: CanonicalGrid
    fixed_to_moving: sitk.Transform
    target: PoseTarget


# ------------------------------------------------------------------------------------------------------- discovery
def discover_pairs(root: str | os.PathLike) -> list[PairFiles]:
    """Every pair folder under ``root`` (layout in the module docstring), sorted by id.

    Raises:
        InputNotFoundError: ``root`` does not exist.
        InputError: ``root`` is not a folder or holds no pair folders, or some pair folders lack a role or hold two
            candidates for one; the message names every such folder and what is wrong there.
    """
    folder = Path(root)
    if not folder.exists():
        raise InputNotFoundError(f"{folder}: not found (no such folder); check the path")
    if not folder.is_dir():
        raise InputError(f"{folder}: is a file; expected a folder holding one subfolder per pair")
    entries = sorted((entry for entry in folder.iterdir() if entry.is_dir() and not entry.name.startswith(".")),
                     key=lambda entry: entry.name)
    if not entries:
        raise InputError(f"{folder}: holds no pair folders; expected ROOT/PAIR_ID/ folders each holding fixed.*, "
                         "moving.* and a ground-truth transform (layout: dpcn_med.train.folders)")
    pairs, problems = [], []
    for entry in entries:
        try:
            pairs.append(_pair_files(entry))
        except InputError as error:
            problems.append(str(error))
    if problems:
        raise InputError(f"{folder}: {len(problems)} of {len(entries)} pair folders are unusable: "
                         + "; ".join(problems))
    return pairs


def _role(path: Path) -> str:
    return path.name.split(".")[0].lower()


def _pair_files(folder: Path) -> PairFiles:
    entries = sorted(folder.iterdir())
    images = [e for e in entries if e.is_dir() or e.name.lower().endswith(IMAGE_SUFFIXES)]
    found = {
        "fixed image": ([e for e in images if _role(e) in FIXED_NAMES], "fixed.*, ct.*"),
        "moving image": ([e for e in images if _role(e) in MOVING_NAMES], "moving.*, mr.*, us.*"),
        "ground truth": ([e for e in entries if e.is_file() and e.name.lower().endswith(TRUTH_SUFFIXES)],
                         ", ".join(f"*{s}" for s in TRUTH_SUFFIXES)),
    }
    problems = []
    for what, (candidates, names) in found.items():
        if not candidates:
            problems.append(f"no {what} ({names})")
        elif len(candidates) > 1:
            problems.append(f"{len(candidates)} candidate {what}s ({', '.join(c.name for c in candidates)}): "
                            "keep one")
    if problems:
        raise InputError(f"{folder}: {', '.join(problems)}")
    (fixed,), (moving,), (truth,) = (candidates for candidates, _ in found.values())
    return PairFiles(folder.name, fixed, moving, truth)


# ---------------------------------------------------------------------------------------------------- ground truth
def read_truth(path: str | os.PathLike, fixed_image: sitk.Image, moving_image: sitk.Image) -> sitk.Transform:
    """A pair's ground truth ``fixed_to_moving`` from an ITK transform file or a RIRE ``.standard`` file.

    Args:
        path: ``.tfm``, ``.h5``, ``.hdf5`` (fixed to moving), or ``.standard`` ("From" = fixed, "To" = moving).
        fixed_image: the fixed image; its origin and direction place a ``.standard``'s "From" points.
        moving_image: the moving image; places the "To" points.

    Returns:
        The transform file's own transform, or for a ``.standard`` the least-squares rigid fit of its points (a
        ``VersorRigid3DTransform`` centred on the "From" points).

    Raises:
        InputNotFoundError: the file does not exist.
        InputError: unreadable, or not a similarity (shear, anisotropic scale, reflection, non-linear), or a
            ``.standard`` without a point table, with a malformed row, with fewer than three non-collinear points,
            whose "From" points lie outside the fixed image (roles swapped, or a cropped copy), or whose points do not
            move rigidly; the message names the file.

    Convention:
        LPS millimetres, fixed to moving (:mod:`dpcn_med.geometry`); RIRE coordinates as in the module docstring.
    """
    name = os.fspath(path)
    if not name.lower().endswith(".standard"):
        transform = io.read_transform(name)
        _similarity_matrix(transform, name)
        return transform
    # latin-1 decodes any bytes, so a binary file fails in the parser as "no point table".
    from_points, to_points = parse_rire_standard(io.read_text(name, encoding="latin-1"), name)
    _check_within(from_points, fixed_image, name)
    fixed_points = _rire_to_physical(from_points, fixed_image)
    moving_points = _rire_to_physical(to_points, moving_image)
    fixed_centre, moving_centre = fixed_points.mean(0), moving_points.mean(0)
    # Kabsch fit; scipy's align_vectors(a, b) returns the proper rotation R minimising sum |a_i - R b_i|^2.
    rotation = Rotation.align_vectors(moving_points - moving_centre, fixed_points - fixed_centre)[0].as_matrix()
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = moving_centre - rotation @ fixed_centre
    residual = float(np.linalg.norm(fixed_points @ rotation.T + matrix[:3, 3] - moving_points, axis=1).max())
    if residual > RIGID_FIT_TOLERANCE_MM:
        raise InputError(f"{name}: its points do not move rigidly (a point lies {residual:.2f} mm from the best rigid "
                         f"fit, more than {RIGID_FIT_TOLERANCE_MM} mm); check the point table")
    return similarity_transform(matrix, fixed_centre, rigid=True)


def parse_rire_standard(text: str, source: str = "RIRE file") -> tuple[np.ndarray, np.ndarray]:
    """The point table of a RIRE ``.standard`` file: rows ``index x y z new_x new_y new_z``.

    Args:
        text: the file's content.
        source: the file's name, for messages.

    Returns:
        ``(from_points, to_points)``, both ``(K, 3)`` mm: ``(x, y, z)`` in the "From" volume's frame and
        ``(new_x, new_y, new_z)`` in the "To" volume's frame.

    Raises:
        InputError: no point table (its header ``Point x y z new_x new_y new_z``, then the rows), a row that is not
            an index and six finite numbers, an index given twice, or fewer than three non-collinear points.
    """
    lines = text.splitlines()
    start = next((number for number, line in enumerate(lines, start=1) if _TABLE_HEADER.match(line)), None)
    if start is None:
        raise InputError(f"{source}: holds no point table (a header 'Point x y z new_x new_y new_z', then rows "
                         "'index x y z new_x new_y new_z'); expected a RIRE .standard ground-truth file")
    rows, indices = [], set()
    for number, line in enumerate(lines[start:], start=start + 1):
        if not line.strip():
            continue
        if not _ROW_START.match(line):
            break  # the table ends ("(All distances are in millimeters.)")
        # Every row is read: a row skipped for a NaN, a missing column or a decimal comma changed the fit silently.
        cells = line.split()
        try:
            index, values = int(cells[0]), [float(cell) for cell in cells[1:]]
        except ValueError:
            index, values = None, []
        if len(values) != 6 or not all(math.isfinite(v) for v in values) or index in indices:
            raise InputError(f"{source}: line {number}: {line.strip()!r} is not a point row (an index not given "
                             "before, then six finite numbers x y z new_x new_y new_z)")
        indices.add(index)
        rows.append(values)
    table = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    from_points, to_points = table[:, :3], table[:, 3:]
    if len(rows) < 3 or (spread := np.linalg.svd(from_points - from_points.mean(0), compute_uv=False))[1] <= (
            1e-6 * spread[0]):
        raise InputError(f"{source}: its {len(rows)} points are fewer than three or collinear; a rigid transform "
                         "needs at least three points not on one line")
    return from_points, to_points


def _check_within(points: np.ndarray, image: sitk.Image, source: str) -> None:
    """Refuse "From" points ``(K, 3)`` (RIRE millimetres) outside the fixed image's extent, one voxel of slack.

    RIRE's points are the corners of the "From" volume: past its fixed image, the file belongs to the other role or
    the image is a cropped copy (docs/design_notes/training.md).

    Raises:
        InputError: naming the first point outside.
    """
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
    extent = np.asarray(image.GetSize()) * spacing
    outside = (points < -spacing) | (points > extent + spacing)
    if outside.any():
        row = int(np.flatnonzero(outside.any(1))[0])
        raise InputError(f"{source}: its point {row + 1} ({', '.join(f'{v:g}' for v in points[row])} mm) lies "
                         f"outside the fixed image (extent {', '.join(f'{v:g}' for v in extent)} mm): its 'From' "
                         "volume is not this pair's fixed image (roles swapped? a cropped or resampled copy?)")


def _rire_to_physical(points: np.ndarray, image: sitk.Image) -> np.ndarray:
    """``(K, 3)`` RIRE millimetres along ``image``'s voxel axes -> LPS points: ``origin + direction @ p``."""
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    return np.asarray(image.GetOrigin(), dtype=np.float64) + points @ direction.T


def _similarity_matrix(transform: sitk.Transform, source: str) -> np.ndarray:
    """``(4, 4)`` matrix of ``transform``, checked to be a similarity ``mu R`` with ``det R = +1``."""
    try:
        matrix = homogeneous_matrix(transform)
    except ValueError as error:
        raise InputError(f"{source}: {error}; the ground truth must be rigid or a similarity") from None
    scale_and_rotation(matrix[:3, :3], f"{source}: {transform.GetName()}")  # raises naming the problem
    return matrix


def pose_on_grids(fixed_to_moving: sitk.Transform, fixed_grid: CanonicalGrid, moving_grid: CanonicalGrid
                  ) -> PoseTarget:
    """The solver's pose on two canonical grids of a physical ``fixed_to_moving``: the inverse of
    :func:`dpcn_med.geometry.physical_transform`.

    Args:
        fixed_to_moving: ``T(x) = M x + b``, ``M = mu R``, LPS mm.
        fixed_grid: the fixed grid (centre ``c_f``, spacing ``h``).
        moving_grid: the moving grid (centre ``c_m``, the same spacing).

    Returns:
        rotation ``(1, 3, 3)``, scale ``(1,)`` and translation ``(1, 3)`` voxels ``(x, y, z)``, float32.

    Raises:
        InputError: the grids' spacings differ, or ``M`` is not a similarity.

    Notes:
        With voxel offsets ``u = (x - c_f) / h`` and ``v = (T(x) - c_m) / h``: ``v = M u + (M c_f + b - c_m) / h``,
        so ``scale * rotation = M`` and ``translation = (M c_f + b - c_m) / h``.

    Convention:
        Voxel offsets from the grid centres, ``fixed(p) ~ moving(scale * rotation @ p + translation)``, as in
        :mod:`dpcn_med.geometry`.
    """
    spacing = fixed_grid.spacing
    if not math.isclose(spacing, moving_grid.spacing, rel_tol=1e-9):
        raise InputError(f"grids must share one spacing, got {spacing} and {moving_grid.spacing} mm")
    matrix = _similarity_matrix(fixed_to_moving, "fixed_to_moving")
    scale, rotation = scale_and_rotation(matrix[:3, :3])
    translation = (matrix[:3, :3] @ np.asarray(fixed_grid.centre) + matrix[:3, 3]
                   - np.asarray(moving_grid.centre)) / spacing
    return PoseTarget(torch.tensor(rotation[None], dtype=torch.float32), torch.tensor([scale], dtype=torch.float32),
                      torch.tensor(translation[None], dtype=torch.float32))


# --------------------------------------------------------------------------------------------------------- dataset
def _prepared(path: Path, image: sitk.Image, preprocessing: Preprocessing) -> PreparedImage:
    """``image`` prepared as by :func:`dpcn_med.register`, the modality taken from its name when it says one."""
    role = _role(path)
    try:
        return prepare(image, modality=role if role in MODALITIES else "auto", config=preprocessing)
    except InputError as error:
        raise InputError(f"{path}: {error}") from None


def load_pair(files: PairFiles, bandwidth: int, preprocessing: Preprocessing | None = None) -> PairGrids:
    """Read a pair and its ground truth and put both images on their canonical grids, as :func:`dpcn_med.register`
    does (prepare, :func:`~dpcn_med.preprocess.pair_grids` with one spacing, linear resampling).

    Args:
        files: from :func:`discover_pairs`.
        bandwidth: solver bandwidth ``B``; grids are ``(2B)^3``.
        preprocessing: canonical-grid and intensity settings (default :class:`Preprocessing`).

    Raises:
        InputError: an unreadable image or ground truth, or an image without foreground (the message names it).
    """
    preprocessing = preprocessing or Preprocessing()
    fixed_image, moving_image = io.read_image(files.fixed), io.read_image(files.moving)
    fixed_to_moving = read_truth(files.truth, fixed_image, moving_image)
    fixed = _prepared(files.fixed, fixed_image, preprocessing)
    moving = _prepared(files.moving, moving_image, preprocessing)
    fixed_grid, moving_grid = pair_grids(fixed, moving, 2 * bandwidth, preprocessing)
    foreground = to_tensor(resample_to_grid(sitk.Cast(fixed.foreground, sitk.sitkFloat32), fixed_grid))[0] >= 0.5
    return PairGrids(files=files, fixed=to_tensor(resample_to_grid(fixed.image, fixed_grid))[0],
                     moving=to_tensor(resample_to_grid(moving.image, moving_grid))[0], fixed_foreground=foreground,
                     fixed_grid=fixed_grid, moving_grid=moving_grid, fixed_to_moving=fixed_to_moving,
                     target=pose_on_grids(fixed_to_moving, fixed_grid, moving_grid))


def check_crop(crop: tuple[float, float] | None, name: str = "crop") -> None:
    """Refuse a slab crop that is neither ``None`` nor ``(low, high)`` with ``0 < low <= high <= 1``."""
    if crop is not None:
        check_pair(name, crop, minimum=0.0, maximum=1.0, above=True, equal=True,
                   note=" (the fraction of the fixed foreground kept), or None for no crop")


class FolderPairs(torch.utils.data.Dataset):
    """The pairs of a folder (layout in the module docstring) on the solver's canonical grids, with their poses.

    Each pair is read and prepared once, on first use, and kept (per process: DataLoader workers each fill their
    own copy). With ``crop``, the fixed grid is cut to a random slab keeping a random fraction of its foreground
    (zero beyond it), as the paper crops its training pairs; the draws come from a generator seeded by
    ``(seed, index, epoch)``, so an epoch's items are reproducible (call :meth:`set_epoch` before each epoch; with
    ``persistent_workers`` the workers keep the epoch they started with).

    Args:
        root: the folder of pair folders.
        bandwidth: solver bandwidth ``B``; grids are ``(2B)^3``.
        preprocessing: canonical-grid and intensity settings, the ones used at inference (default
            :class:`Preprocessing`).
        crop: ``(low, high)``, ``0 < low <= high <= 1``: fraction of the fixed foreground kept, uniform in it;
            ``None`` for whole, deterministic items.
        seed: seed of the crops.

    Raises:
        InputError: as :func:`discover_pairs`, a bandwidth out of range, or a malformed ``crop``.

    Items:
        ``{"fixed": (1, N, N, N), "moving": (1, N, N, N), "rotation": (3, 3), "scale": (), "translation": (3,)}``
        float32, ``fixed(p) ~ moving(scale * rotation @ p + translation)``; batch them with :func:`collate_pairs`.
    """

    def __init__(self, root: str | os.PathLike, bandwidth: int, *, preprocessing: Preprocessing | None = None,
                 crop: tuple[float, float] | None = None, seed: int = 0) -> None:
        check_grid_bandwidth(bandwidth)
        check_crop(crop)
        self.pairs = discover_pairs(root)
        self.bandwidth = bandwidth
        self.preprocessing = preprocessing or Preprocessing()
        self.crop = crop
        self.seed = seed
        self.epoch = 0
        self._cache: dict[int, PairGrids] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    def set_epoch(self, epoch: int) -> None:
        """Draw the crops of ``epoch`` from now on."""
        self.epoch = epoch

    def grids(self, index: int) -> PairGrids:
        """Pair ``index`` on its grids, uncropped, with its physical grids and ground truth (cached)."""
        index = range(len(self.pairs))[index]
        if index not in self._cache:
            self._cache[index] = load_pair(self.pairs[index], self.bandwidth, self.preprocessing)
        return self._cache[index]

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        index = range(len(self.pairs))[index]
        pair = self.grids(index)
        fixed = pair.fixed
        if self.crop is not None:
            seed = derived_seed(self.seed, index, self.epoch)
            generator = torch.Generator().manual_seed(seed)
            low, high = self.crop
            fraction = low + (high - low) * float(torch.rand((), generator=generator))
            axis, from_end = (int(torch.randint(n, (), generator=generator)) for n in (3, 2))
            fixed = fixed * slab_mask(pair.fixed_foreground[0], fraction, axis, bool(from_end))
        return {"fixed": fixed, "moving": pair.moving, "rotation": pair.target.rotation[0],
                "scale": pair.target.scale[0], "translation": pair.target.translation[0]}


def collate_pairs(items: list[dict[str, Tensor]]) -> tuple[Tensor, Tensor, PoseTarget]:
    """Batch :class:`FolderPairs` items: ``(fixed (B, 1, N, N, N), moving (B, 1, N, N, N), PoseTarget)``, the form of
    :func:`dpcn_med.synth.synthetic_pairs` (use as a DataLoader's ``collate_fn``)."""
    stacked = {key: torch.stack([item[key] for item in items]) for key in items[0]}
    return stacked["fixed"], stacked["moving"], PoseTarget(stacked["rotation"], stacked["scale"],
                                                           stacked["translation"])
