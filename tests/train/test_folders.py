"""dpcn_med.train.folders: pair discovery, ground truths (ITK and RIRE), poses on the grids, the dataset and crops."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med import io, samples
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.evaluation import moved_copy, random_similarity
from dpcn_med.geometry import CanonicalGrid, geodesic_distance, homogeneous_matrix, physical_transform, warp
from dpcn_med.preprocess import foreground_box
from dpcn_med.solver import PoseTarget, solve
from dpcn_med.synth import slab_mask
from dpcn_med.train.folders import (
    FolderPairs,
    collate_pairs,
    discover_pairs,
    parse_rire_standard,
    pose_on_grids,
    read_truth,
)
from tests.conftest import shared_path

BANDWIDTH = 32  # grids of 64^3 at about 9 mm: the solver below runs at bandwidth 16 on them
CUT_SLICES = 6  # fixed images lose their lowest slices, so the foreground centres differ: a non-zero translation


def _correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / (a.norm() * b.norm()))


def _touch(folder: Path, *names: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        if name.endswith("/"):
            (folder / name).mkdir()
        else:
            (folder / name).write_text("")
    return folder


def _write_standard(path: Path, from_points: np.ndarray, to_points: np.ndarray) -> None:
    rows = "\n".join(f"  {i + 1}  " + "  ".join(f"{v:.4f}" for v in (*p, *q))
                     for i, (p, q) in enumerate(zip(from_points, to_points)))
    path.write_text("From: CT\nTo: mr_T1\n\nPoint      x          y          z        new_x       new_y       new_z\n\n"
                    f"{rows}\n\n(All distances are in millimeters.)\n")


@pytest.fixture(scope="module")
def pairs_root(tmp_path_factory) -> Path:
    """Two pairs of the MNI template (4 mm) and a moved copy of it, ground truth as .tfm."""
    # Smoothed first: the ~9 mm grids are far coarser than the 4 mm voxels and linear resampling does not low-pass,
    # so unsmoothed grids alias and two exactly aligned grids would correlate poorly.
    base = sitk.BinShrink(sitk.SmoothingRecursiveGaussian(samples.mni152_t1(), 4.0), [4, 4, 4])
    centre, _ = foreground_box(base)
    cut = sitk.GetArrayFromImage(base)
    cut[:CUT_SLICES] = 0
    fixed = sitk.GetImageFromArray(cut)
    fixed.CopyInformation(base)
    root = tmp_path_factory.mktemp("pairs")
    for seed, name in enumerate(("b", "a")):
        truth = random_similarity(np.random.default_rng(seed), centre, max_shift_mm=20.0, scale_range=(0.9, 1.1))
        folder = _touch(root / name)
        io.write_image(fixed, folder / "fixed.nii.gz")
        io.write_image(moved_copy(base, truth), folder / "moving.nii.gz")
        io.write_transform(truth, folder / "transform.tfm")
    (root / "README").write_text("plain files in the root are ignored")
    return root


@pytest.fixture(scope="module")
def dataset(pairs_root) -> FolderPairs:
    return FolderPairs(pairs_root, BANDWIDTH)


class TestDiscoverPairs:
    def test_roles_and_order(self, tmp_path):
        _touch(tmp_path / "2", "fixed.nii.gz", "moving.nrrd", "transform.tfm", "notes.txt")
        _touch(tmp_path / "1", "CT.mhd", "ct.raw", "mr/", "ct_T1.standard")
        _touch(tmp_path / ".hidden", "anything")
        pairs = discover_pairs(tmp_path)
        assert [p.id for p in pairs] == ["1", "2"]
        assert (pairs[0].fixed.name, pairs[0].moving.name, pairs[0].truth.name) == ("CT.mhd", "mr", "ct_T1.standard")
        assert (pairs[1].fixed.name, pairs[1].moving.name, pairs[1].truth.name) == (
            "fixed.nii.gz", "moving.nrrd", "transform.tfm")

    def test_empty_or_missing_root(self, tmp_path):
        with pytest.raises(InputError, match="holds no pair folders"):
            discover_pairs(tmp_path)
        with pytest.raises(InputNotFoundError, match="not found"):
            discover_pairs(tmp_path / "none")

    def test_bad_folders_are_named(self, tmp_path):
        _touch(tmp_path / "good", "fixed.nii.gz", "us.mha", "t.h5")
        _touch(tmp_path / "p1", "fixed.nii.gz", "transform.tfm")
        _touch(tmp_path / "p2", "fixed.nii.gz", "ct.nrrd", "moving.nii", "transform.tfm")
        with pytest.raises(InputError, match=r"2 of 3 pair folders are unusable: .*p1: no moving image "
                                             r"\(moving\.\*, mr\.\*, us\.\*\); .*p2: 2 candidate fixed images "
                                             r"\(ct\.nrrd, fixed\.nii\.gz\): keep one"):
            discover_pairs(tmp_path)


class TestReadTruth:
    def test_tfm_is_returned_as_written(self, pairs_root):
        files = discover_pairs(pairs_root)[0]
        truth = read_truth(files.truth, io.read_image(files.fixed), io.read_image(files.moving))
        np.testing.assert_allclose(homogeneous_matrix(truth), homogeneous_matrix(sitk.ReadTransform(str(files.truth))))

    def test_non_similarity_tfm_is_refused(self, tmp_path):
        image = sitk.Image([4, 4, 4], sitk.sitkFloat32)
        sheared = sitk.AffineTransform(3)
        sheared.SetMatrix((1.0, 0.2, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
        io.write_transform(sheared, tmp_path / "shear.tfm")
        with pytest.raises(InputError, match=r"shear\.tfm: AffineTransform is not a similarity: .*shear or "
                                             r"anisotropic scale"):
            read_truth(tmp_path / "shear.tfm", image, image)
        mirrored = sitk.AffineTransform(3)
        mirrored.SetMatrix((-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
        io.write_transform(mirrored, tmp_path / "mirror.h5")
        with pytest.raises(InputError, match=r"mirror\.h5: .*reflects"):
            read_truth(tmp_path / "mirror.h5", image, image)

    def test_standard_honours_origins_and_directions(self, tmp_path):
        fixed, moving = sitk.Image([6, 6, 6], sitk.sitkFloat32), sitk.Image([4, 4, 4], sitk.sitkFloat32)
        fixed.SetSpacing((50.0, 50.0, 24.0))  # the points are its corners, within its extent
        fixed.SetOrigin((-120.0, 30.0, 15.0))
        fixed.SetDirection((0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0))
        moving.SetOrigin((8.0, -90.0, 44.0))
        moving.SetDirection((-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0))
        truth = sitk.VersorRigid3DTransform()
        truth.SetCenter((5.0, 40.0, -12.0))
        truth.SetRotation((0.3, -0.5, 0.8), 2.4)
        truth.SetTranslation((12.0, -7.0, 30.0))
        from_points = np.array([[0.0, 0.0, 0.0], [250.0, 0.0, 0.0], [0.0, 250.0, 0.0], [0.0, 0.0, 120.0],
                                [250.0, 250.0, 120.0]])
        physical = fixed.GetOrigin() + from_points @ np.reshape(fixed.GetDirection(), (3, 3)).T
        moved = np.array([truth.TransformPoint(p.tolist()) for p in physical])
        to_points = (moved - moving.GetOrigin()) @ np.reshape(moving.GetDirection(), (3, 3))
        _write_standard(tmp_path / "ct_T1.standard", from_points, to_points)
        found = read_truth(tmp_path / "ct_T1.standard", fixed, moving)
        np.testing.assert_allclose(homogeneous_matrix(found), homogeneous_matrix(truth), atol=1e-3)

    def test_real_rire_standard_equals_its_itk_transform(self):
        standard = shared_path("rire/ct_T1.standard")
        reference = sitk.ReadTransform(str(shared_path("rire/training_001_ct_to_mr_T1_ground_truth.tfm")))
        mr = io.read_image(shared_path("rire/training_001_mr_T1.mha"))
        ct = sitk.Image([512, 512, 29], sitk.sitkInt8)  # the CT is not shared: its geometry (origin 0, identity) does
        ct.SetSpacing((333.987 / 512, 333.987 / 512, 4.0))
        found = read_truth(standard, ct, mr)
        # Given as an MR-to-CT pair's truth, the file's CT corners lie past the MR: it gave the inverse, silently.
        with pytest.raises(InputError, match=r"ct_T1\.standard: its point 2 \(333\.987, 0, 0 mm\) lies outside the "
                                             r"fixed image \(extent 320, 320, 104 mm\).*roles swapped"):
            read_truth(standard, mr, ct)
        from_points, to_points = parse_rire_standard(standard.read_text(), str(standard))
        assert from_points.shape == (8, 3)
        for p, q in zip(from_points, to_points):
            # CT -> MR ("From" -> "To") with RIRE millimetres used as LPS points, as RIRE's own .tfm does
            assert np.linalg.norm(np.subtract(found.TransformPoint(p.tolist()), reference.TransformPoint(p.tolist()))
                                  ) < 0.5
            assert np.linalg.norm(np.subtract(found.TransformPoint(p.tolist()), q)) < 0.01

    @pytest.mark.parametrize("row,shown", [
        ("5  0.0  0.0  nan  4.8  -21.2  84.7", "'5  0.0  0.0  nan  4.8  -21.2  84.7'"),
        ("5  0.0  0.0  112.0  4.8  -21.2", "'5  0.0  0.0  112.0  4.8  -21.2'"),
        ("5  0,0  0,0  112,0  4,8  -21,2  84,7", "'5  0,0  0,0  112,0  4,8  -21,2  84,7'"),
        ("5  0.0  0.0  1e999  4.8  -21.2  84.7", "'5  0.0  0.0  1e999  4.8  -21.2  84.7'"),  # SVD failed on it
        ("4  0.0  0.0  112.0  4.8  -21.2  84.7", "'4  0.0  0.0  112.0  4.8  -21.2  84.7'"),  # index 4 twice
    ])
    def test_a_malformed_row_is_named(self, tmp_path, row, shown):
        """Rows that did not match were skipped, and the fit went on with the others."""
        image = sitk.Image([4, 4, 4], sitk.sitkFloat32)
        image.SetSpacing((40.0, 40.0, 40.0))
        corners = np.array([[x, y, z] for z in (0.0, 112.0) for y in (0.0, 100.0) for x in (0.0, 100.0)])
        _write_standard(tmp_path / "t.standard", corners, corners)
        lines = (tmp_path / "t.standard").read_text().splitlines()
        number = next(i for i, line in enumerate(lines) if line.strip().startswith("5 "))
        lines[number] = row
        (tmp_path / "t.standard").write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError, match=rf"t\.standard: line {number + 1}: {re.escape(shown)} is not a point "
                                             r"row \(an index not given before, then six finite numbers"):
            read_truth(tmp_path / "t.standard", image, image)

    def test_unusable_standard(self, tmp_path):
        image = sitk.Image([4, 4, 4], sitk.sitkFloat32)
        image.SetSpacing((30.0, 30.0, 30.0))
        (tmp_path / "garbage.standard").write_bytes(b"\x00\xffnot a table\n1 2 3\n")
        with pytest.raises(InputError, match=r"garbage\.standard: holds no point table"):
            read_truth(tmp_path / "garbage.standard", image, image)
        corners = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0]])
        _write_standard(tmp_path / "scaled.standard", corners, 1.1 * corners)
        with pytest.raises(InputError, match=r"scaled\.standard: its points do not move rigidly"):
            read_truth(tmp_path / "scaled.standard", image, image)
        with pytest.raises(InputNotFoundError, match="not found"):
            read_truth(tmp_path / "none.standard", image, image)


class TestPoseOnGrids:
    @pytest.mark.parametrize("rigid", [False, True], ids=["similarity", "rigid"])
    def test_inverse_of_physical_transform(self, rigid):
        rng = np.random.default_rng(7)
        fixed_grid = CanonicalGrid(32, 3.5, (10.0, -20.0, 5.0))
        moving_grid = CanonicalGrid(32, 3.5, (-4.0, 7.0, 30.0))
        truth = random_similarity(rng, np.array([1.0, 2.0, 3.0]), scale_range=(1.0, 1.0) if rigid else (0.8, 1.2))
        target = pose_on_grids(truth, fixed_grid, moving_grid)
        assert target.rotation.shape == (1, 3, 3) and target.scale.shape == (1,) and target.translation.shape == (1, 3)
        assert target.rotation.dtype == torch.float32
        back = physical_transform(target.rotation[0], None if rigid else float(target.scale[0]),
                                  target.translation[0], fixed_grid, moving_grid)
        np.testing.assert_allclose(homogeneous_matrix(back), homogeneous_matrix(truth), atol=1e-4)

    def test_refuses_shear_and_mixed_spacings(self):
        grid = CanonicalGrid(16, 2.0, (0.0, 0.0, 0.0))
        sheared = sitk.AffineTransform(3)
        sheared.SetMatrix((1.0, 0.0, 0.0, 0.0, 1.0, 0.3, 0.0, 0.0, 1.0))
        with pytest.raises(InputError, match="fixed_to_moving: AffineTransform is not a similarity"):
            pose_on_grids(sheared, grid, grid)
        with pytest.raises(InputError, match="grids must share one spacing"):
            pose_on_grids(sitk.Euler3DTransform(), grid, CanonicalGrid(16, 3.0, (0.0, 0.0, 0.0)))


class TestFolderPairs:
    def test_item_pose_is_exact(self, dataset):
        for index in range(len(dataset)):
            item, pair = dataset[index], dataset.grids(index)
            assert item["fixed"].shape == item["moving"].shape == (1, 64, 64, 64)
            assert item["fixed"].dtype == torch.float32 and item["scale"].shape == ()
            assert item["translation"].norm() > 1.0  # the pose is not the identity on the grids
            inside = pair.fixed_foreground[None]
            fixed, moving = item["fixed"][None], item["moving"][None]
            matrix = (item["scale"] * item["rotation"])[None]
            aligned = _correlation(fixed[inside], warp(moving, matrix, item["translation"][None])[inside])
            shifted = _correlation(fixed[inside], warp(moving, matrix, item["translation"][None] + 1.0)[inside])
            assert aligned > 0.9 and shifted < aligned - 0.1

    def test_learning_free_solver_recovers_the_pose(self, dataset):
        item = dataset[0]
        result = solve(item["fixed"][None], item["moving"][None], "similarity", bandwidth=16)
        assert math.degrees(float(geodesic_distance(result.rotation[0], item["rotation"]))) < 5.0
        assert float((result.translation[0] - item["translation"]).norm()) < 0.5
        assert abs(float(result.scale[0] / item["scale"]) - 1.0) < 0.02

    def test_dataloader_batches(self, dataset):
        loader = torch.utils.data.DataLoader(dataset, batch_size=2, collate_fn=collate_pairs)
        fixed, moving, target = next(iter(loader))
        assert fixed.shape == moving.shape == (2, 1, 64, 64, 64)
        assert isinstance(target, PoseTarget)
        assert target.rotation.shape == (2, 3, 3) and target.scale.shape == (2,) and target.translation.shape == (2, 3)
        torch.testing.assert_close(target.rotation[1], dataset.grids(1).target.rotation[0])

    def test_options_are_checked(self, pairs_root):
        with pytest.raises(InputError, match=r"crop is \(0\.8, 0\.5\)"):
            FolderPairs(pairs_root, BANDWIDTH, crop=(0.8, 0.5))
        with pytest.raises(InputError, match="bandwidth 2 is out of range"):
            FolderPairs(pairs_root, 2)


class TestCrops:
    def test_slab_keeps_the_fraction(self):
        foreground = torch.zeros(10, 6, 6, dtype=torch.bool)
        foreground[2:8, 1:5, 1:5] = True  # 6 equal slices along z
        kept = (slab_mask(foreground, 0.5, 0, from_end=True) * foreground).sum() / foreground.sum()
        assert float(kept) == 0.5
        assert slab_mask(foreground, 0.5, 0, from_end=True)[:5].sum() == 0  # the high end is kept

    def test_crops_keep_the_fraction_and_are_reproducible(self, pairs_root, dataset):
        low, high = 0.5, 0.7
        cropping = FolderPairs(pairs_root, BANDWIDTH, crop=(low, high), seed=3)
        again = FolderPairs(pairs_root, BANDWIDTH, crop=(low, high), seed=3)
        seen = set()
        for epoch in range(4):
            cropping.set_epoch(epoch)
            again.set_epoch(epoch)
            for index in range(len(cropping)):
                cropped, whole = cropping[index]["fixed"], dataset.grids(index).fixed
                foreground = dataset.grids(index).fixed_foreground
                torch.testing.assert_close(cropped, again[index]["fixed"], rtol=0, atol=0)
                assert torch.all((cropped == whole) | (cropped == 0))
                slice_share = max(float(foreground.sum([a for a in (1, 2, 3) if a != axis]).max())
                                  for axis in (1, 2, 3)) / float(foreground.sum())
                kept = float((foreground & (cropped != 0)).sum() / foreground.sum())
                assert low <= kept <= high + slice_share
                seen.add((index, int((cropped != 0).sum())))
        assert len(seen) > len(cropping)  # the crops change with the epoch

    def test_no_crop_is_deterministic(self, dataset):
        torch.testing.assert_close(dataset[1]["fixed"], dataset.grids(1).fixed, rtol=0, atol=0)
