"""The registration API: round trips with known physical transforms, options, masks and errors."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.benchmark import CASES
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.geometry import homogeneous_matrix
from dpcn_med.models import DPCN, ModelConfig, save_model
from dpcn_med.preprocess import (
    Preprocessing,
    foreground_box,
    foreground_mask,
    pair_grids,
    prepare,
    resample_to_grid,
    to_tensor,
)
from dpcn_med.refine import Refinement
from dpcn_med.registration import (
    RegistrationResult,
    field_of_view_overlap,
    register,
    resample_moving,
    stored_pose_confidence,
)
from dpcn_med.samples import mni152_t1
from dpcn_med.solver import SolverConfig
from tests.conftest import shared_path


@functools.lru_cache(maxsize=1)
def mni_2mm() -> sitk.Image:
    """The MNI152 T1 averaged down to 2 mm: the same anatomy at an eighth of the voxels, for quick tests."""
    return sitk.BinShrink(mni152_t1(), [2, 2, 2])


def _round_trip(fixed: sitk.Image, mode: str, seed: int, **options) -> tuple[RegistrationResult, sitk.Transform,
                                                                          np.ndarray]:
    rng = np.random.default_rng(seed)
    truth = random_similarity(rng, foreground_box(fixed)[0], max_shift_mm=40.0,
                              scale_range=(0.85, 1.15) if mode == "similarity" else (1.0, 1.0))
    return register(fixed, moved_copy(fixed, truth), mode=mode, **options), truth, foreground_corners(fixed)


class TestRoundTrip:
    @pytest.mark.parametrize(("mode", "seed"), [("rigid", 0), ("similarity", 1)])
    def test_built_in_sample(self, mode, seed):
        result, truth, corners = _round_trip(mni_2mm(), mode, seed)
        assert target_registration_error(result.dpc_transform, truth, corners) < 2 * result.fixed_grid.spacing
        assert target_registration_error(result.fixed_to_moving, truth, corners) < 1.0
        assert result.refined and result.metric["refined"] <= result.metric["dpc"] < result.metric["stored"]
        expected = "VersorRigid3DTransform" if mode == "rigid" else "Similarity3DTransform"
        assert result.fixed_to_moving.GetName() == expected
        np.testing.assert_allclose(result.fixed_to_moving.GetFixedParameters(), result.fixed_grid.centre)

    @pytest.mark.shared_data
    @pytest.mark.parametrize("name", ["rire/training_001_mr_T1.mha", "mridir/mridir_ct_1p5mm.nii.gz"])
    def test_real_volumes(self, name):
        fixed = sitk.ReadImage(str(shared_path(name)))
        result, truth, corners = _round_trip(fixed, "similarity", 7)
        assert result.start == "phase correlation"  # the stored pose, refined to the same pose, does not win the tie
        assert target_registration_error(result.dpc_transform, truth, corners) < 2 * result.fixed_grid.spacing
        assert target_registration_error(result.fixed_to_moving, truth, corners) < 1.0

    @pytest.mark.shared_data
    def test_the_finest_level_starts_with_a_small_step(self):
        """benchmarks/register_roundtrip.py's 23rd MRI-DIR CT similarity pose: the coarser levels bring it to 0.65 mm;
        a 2 mm first step at full resolution went on to another optimum 1.90 mm off, 0.5 mm finishes it."""
        fixed = sitk.ReadImage(str(shared_path("mridir/mridir_ct_1p0mm.nii.gz")))
        rng, centre = np.random.default_rng(1), foreground_box(fixed)[0]
        truth = [random_similarity(rng, centre, max_shift_mm=40.0, scale_range=(0.85, 1.15)) for _ in range(23)][-1]
        result = register(fixed, moved_copy(fixed, truth), mode="similarity")
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 0.5

    def test_start_without_any_overlap(self):
        """Two scanner frames half a metre apart: no fixed point maps into the moving image as stored, so the stored
        pose has no metric (``None``), and the registration still finds the pose."""
        fixed = mni_2mm()
        truth = random_similarity(np.random.default_rng(5), foreground_box(fixed)[0], max_shift_mm=0.0)
        truth.SetTranslation((500.0, -300.0, 200.0))
        result = register(fixed, moved_copy(fixed, truth))
        assert result.metric["stored"] is None and result.refined
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 1.0

    def test_paths_and_images_give_the_same_result(self, tmp_path):
        fixed = mni_2mm()
        moving = moved_copy(fixed, random_similarity(np.random.default_rng(2), foreground_box(fixed)[0]))
        sitk.WriteImage(fixed, str(tmp_path / "fixed.nii.gz"))
        sitk.WriteImage(moving, str(tmp_path / "moving.nrrd"))
        from_images = register(fixed, moving, refine=False)
        from_paths = register(tmp_path / "fixed.nii.gz", str(tmp_path / "moving.nrrd"), refine=False)
        np.testing.assert_allclose(homogeneous_matrix(from_paths.dpc_transform),
                                   homogeneous_matrix(from_images.dpc_transform), atol=1e-3)

    def test_a_ct_padded_outside_its_field_of_view(self):
        """The MNI head T1 to its pseudo-CT written as scanners write a CT: -3024 HU outside the circular field of
        view. Otsu over the raw histogram split padding from air, took the field of view for the head, and three
        poses ended 54 to 266 mm off."""
        fixed, ct = CASES["mni-pseudo-ct"][2]()
        widened = sitk.ConstantPad(ct, [15, 10, 0], [15, 10, 0], -1000)  # air around the head, as in a scanner's field
        array = sitk.GetArrayFromImage(widened)
        _, rows, columns = array.shape
        y, x = np.mgrid[:rows, :columns]
        array[:, np.hypot(x - (columns - 1) / 2, y - (rows - 1) / 2) > min(rows, columns) / 2] = -3024
        padded = sitk.GetImageFromArray(array)
        padded.CopyInformation(widened)
        truth = random_similarity(np.random.default_rng(3), foreground_box(fixed)[0], max_shift_mm=30.0)
        result = register(fixed, moved_copy(padded, truth))
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 2.0

    def test_a_few_hot_voxels(self):
        """8 voxels at 300 times the maximum took Otsu's threshold (the foreground was 1 voxel); with the foreground
        found, they still squeezed the head into the first bin of the refinement's histogram: 232, then 231 mm off."""
        clean = mni_2mm()
        array = sitk.GetArrayFromImage(clean).astype(np.float32)
        array.flat[np.random.default_rng(0).choice(np.flatnonzero(array), 8, replace=False)] = 300 * array.max()
        fixed = sitk.GetImageFromArray(array)
        fixed.CopyInformation(clean)
        truth = random_similarity(np.random.default_rng(4), foreground_box(clean)[0], max_shift_mm=30.0)
        result = register(fixed, moved_copy(clean, truth))
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(clean)) < 1.0


@pytest.fixture(scope="module")
def result() -> RegistrationResult:
    return _round_trip(mni_2mm(), "rigid", 3, resample=True)[0]


class TestResult:
    def test_inverse(self, result):
        point = [10.0, -20.0, 15.0]
        back = result.moving_to_fixed.TransformPoint(result.fixed_to_moving.TransformPoint(point))
        np.testing.assert_allclose(back, point, atol=1e-6)

    def test_resampled_on_the_fixed_grid(self, result):
        resampled, fixed = result.resampled, result.fixed_image
        assert resampled.GetSize() == fixed.GetSize() and resampled.GetOrigin() == fixed.GetOrigin()
        assert resampled.GetPixelID() == result.moving_image.GetPixelID()
        a, b = sitk.GetArrayFromImage(resampled), sitk.GetArrayFromImage(fixed)
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99

    def test_the_foregrounds_found_cover_each_head(self, result):
        """They are what the overview draws its windows from (not found again)."""
        for foreground, image in ((result.fixed_foreground, result.fixed_image),
                                  (result.moving_foreground, result.moving_image)):
            values = sitk.GetArrayViewFromImage(foreground)
            assert set(np.unique(values)) == {0, 1} and 0.2 < values.mean() < 0.9
            inside = sitk.Resample(foreground, image, sitk.Transform(), sitk.sitkNearestNeighbor)
            head = sitk.GetArrayViewFromImage(image)[sitk.GetArrayViewFromImage(inside) > 0]
            assert head.mean() > 2 * sitk.GetArrayViewFromImage(image).mean()  # brighter than the whole, background in

    def test_integer_images_are_rounded_not_truncated(self):
        """Truncated towards zero, an int16 CT moved by half a voxel was up to 0.9 HU off, biased by 0.44 HU."""
        values = np.random.default_rng(3).integers(-1000, 1000, size=(12, 12, 12)).astype(np.int16)
        image = sitk.GetImageFromArray(values)
        shift = sitk.TranslationTransform(3, (0.37, -0.5, 0.21))
        resampled = resample_moving(image, image, shift)
        exact = sitk.GetArrayFromImage(sitk.Resample(sitk.Cast(image, sitk.sitkFloat64), image, shift,
                                                     sitk.sitkLinear, float(values.min())))
        assert resampled.GetPixelID() == sitk.sitkInt16
        assert np.abs(sitk.GetArrayFromImage(resampled) - exact).max() <= 0.5

    def test_summary_is_json(self, result):
        summary = json.loads(json.dumps(result.to_dict()))
        assert summary["mode"] == "rigid" and summary["final"]["scale"] == pytest.approx(1.0)
        assert set(summary["mattes_mutual_information"]) == {"stored", "dpc", "refined"}
        assert summary["timings_s"]["solve"] > 0 and any(k.startswith("solver.") for k in summary["timings_s"])

    def test_no_refinement_keeps_the_dpc_estimate(self):
        result = _round_trip(mni_2mm(), "rigid", 4, refine=False)[0]
        assert not result.refined and result.metric["refined"] is None
        assert result.fixed_to_moving is result.dpc_transform


def coronal_slab() -> tuple[sitk.Image, sitk.Image]:
    """A slab 18 mm thick (a tenth of the 2 mm MNI head from front to back) cut out of the whole head, and the head:
    the pair is aligned as stored, but the slab's cut faces dominate its spectrum and phase correlation misses."""
    whole = mni_2mm()
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(foreground_mask(whole))
    box = stats.GetBoundingBox(1)
    length = box[4] // 10
    start = box[1] + (box[4] - length) // 2
    return sitk.RegionOfInterest(whole, [whole.GetSize()[0], length, whole.GetSize()[2]], [0, start, 0]), whole


class TestStoredStart:
    """The stored pose (identity) as one more start of the refinement (:attr:`Refinement.stored_start`)."""

    def test_inputs_aligned_as_stored_stay_aligned(self):
        slab, whole = coronal_slab()
        corners, identity = foreground_corners(slab), sitk.Transform(3, sitk.sitkIdentity)
        without = register(slab, whole, refinement=Refinement(stored_start=False))
        assert target_registration_error(without.fixed_to_moving, identity, corners) > 20
        result = register(slab, whole)
        assert target_registration_error(result.fixed_to_moving, identity, corners) < 0.5
        assert result.start == "stored pose" and result.candidate == len(result.candidate_metrics) - 1
        assert len(result.candidate_metrics) == len(without.candidate_metrics) + 1
        np.testing.assert_allclose(homogeneous_matrix(result.dpc_transform), np.eye(4))
        assert result.confidence > 0.5  # the slab's translation correlation with its head, as stored, is sharp
        assert result.to_dict()["start"] == "stored pose"

    def test_dropped_where_the_stored_frames_do_not_overlap(self):
        fixed = mni_2mm()
        truth = sitk.Euler3DTransform((0.0, 0.0, 0.0), 0.0, 0.0, 0.0, (0.0, 0.0, 1000.0))  # unrelated scanner frames
        result = register(fixed, moved_copy(fixed, truth))
        assert result.metric["stored"] is None and result.candidate_metrics[-1] is None
        assert result.start == "phase correlation"
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 1.0

    def test_confidence_on_a_learned_model_s_features(self, tmp_path):
        """An untrained model's UNets are at zero gain (their features are the grids): its stored-pose confidence is
        the learning-free one; against noise there is no translation peak to be sure of."""
        model = DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)).eval()
        prepared = prepare(mni_2mm())
        grid = pair_grids(prepared, prepared, 32, Preprocessing())[0]
        volume = to_tensor(resample_to_grid(prepared.image, grid))
        noise = torch.rand(volume.shape, generator=torch.Generator().manual_seed(0))
        aligned = stored_pose_confidence(volume, volume, None, None)
        assert aligned > 0.9
        assert stored_pose_confidence(volume, volume, model, None) == pytest.approx(aligned, rel=1e-4)
        assert stored_pose_confidence(volume, noise, None, None) < 0.01


class TestLearnedModel:
    def test_a_model_file_registers_and_is_reported(self, tmp_path):
        """An untrained model is the learning-free solver with its UNets at zero gain: through a file it must give
        the same registration, and the result names the model."""
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)), tmp_path / "untrained")
        fixed = mni_2mm()
        truth = random_similarity(np.random.default_rng(4), foreground_box(fixed)[0])
        moving = moved_copy(fixed, truth)
        learned = register(fixed, moving, model=tmp_path / "untrained.safetensors", bandwidth=16,
                           refinement=Refinement(stored_start=False))
        assert learned.model == str(tmp_path / "untrained.safetensors") and learned.to_dict()["model"] == learned.model
        assert target_registration_error(learned.fixed_to_moving, truth, foreground_corners(fixed)) < 1.0
        assert len(learned.candidate_metrics) > 1  # the model's runner-ups reach the refinement too
        plain = register(fixed, moving, bandwidth=16, refine=False)
        np.testing.assert_allclose(homogeneous_matrix(register(fixed, moving, model=tmp_path / "untrained",
                                                               bandwidth=16, refine=False).dpc_transform),
                                   homogeneous_matrix(plain.dpc_transform), atol=1e-3)
        assert plain.model == "learning-free"

    def test_a_model_is_loaded_once_for_its_registrations(self, tmp_path, monkeypatch):
        """A batch (or a Dask worker) registers many pairs with one model: its files are read once, and again only
        when their contents change."""
        import dpcn_med.models

        loads, load = [], dpcn_med.models.load_model
        monkeypatch.setattr(dpcn_med.models, "load_model", lambda *args, **kwargs: loads.append(1) or load(*args,
                                                                                                          **kwargs))
        torch.manual_seed(0)
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)), tmp_path / "model")
        fixed = mni_2mm()
        first = register(fixed, fixed, model=tmp_path / "model", bandwidth=16, refine=False)
        again = register(fixed, fixed, model=str(tmp_path / "model.json"), bandwidth=16, refine=False)
        assert len(loads) == 1 and again.confidence == first.confidence
        torch.manual_seed(1)
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)), tmp_path / "model")
        register(fixed, fixed, model=tmp_path / "model", bandwidth=16, refine=False)
        assert len(loads) == 2

    def test_the_model_s_grid_preprocessing_is_used(self, tmp_path):
        """A model trained on grids whose foreground spans 0.6 of the side gets such grids (finer spacing than the
        defaults' 0.5), unless the caller passes other settings."""
        config = ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0, preprocessing={"fill": 0.6})
        save_model(DPCN(config), tmp_path / "fill")
        fixed = mni_2mm()
        plain = register(fixed, fixed, bandwidth=16, refine=False).fixed_grid.spacing
        learned = register(fixed, fixed, model=tmp_path / "fill", bandwidth=16, refine=False).fixed_grid.spacing
        assert learned == pytest.approx(plain * 0.5 / 0.6)
        chosen = register(fixed, fixed, model=tmp_path / "fill", bandwidth=16, refine=False,
                          preprocessing=Preprocessing()).fixed_grid.spacing
        assert chosen == pytest.approx(plain)


    # Before: a CT -> MR model registered two ultrasound volumes, exit 0.
    def test_inputs_of_other_modalities_refused(self, tmp_path):
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)), tmp_path / "ct_mr")
        with pytest.raises(InputError, match=r"ct_mr: this model was trained for ct \(fixed\) and mr \(moving\); "
                                             r"the inputs are us and us \(fixed_modality 'us', moving_modality 'us'\)"):
            register(mni_2mm(), mni_2mm(), model=tmp_path / "ct_mr", bandwidth=16, refine=False,
                     fixed_modality="us", moving_modality="us")

    # Before: finite weights whose features overflow were reported as "fixed contains NaN or Inf values" or gave a
    # NaN rotation.
    def test_features_that_overflow_name_the_model(self, tmp_path):
        model = DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0))
        with torch.no_grad():
            model.translation_moving.gain.fill_(3e38)
        save_model(model, tmp_path / "overflow")
        with pytest.raises(InputError, match=r"overflow: the translation_moving features hold NaN or Inf values"):
            register(mni_2mm(), mni_2mm(), model=tmp_path / "overflow", bandwidth=16, refine=False)

    # Before: a NaN pose or confidence went on to the report, exit 0.
    def test_a_non_finite_solution_is_refused(self, monkeypatch):
        from dataclasses import replace

        from dpcn_med import registration as module
        real = module.solve
        monkeypatch.setattr(module, "solve", lambda *args, **kwargs: replace(
            real(*args, **kwargs), confidence=torch.tensor([float("nan")])))
        with pytest.raises(InputError, match=r"^the solver produced a non-finite pose or confidence \(NaN or Inf\)"):
            register(mni_2mm(), mni_2mm(), bandwidth=16, refine=False)


class TestSecondSphereBand:
    @pytest.mark.shared_data
    def test_a_slab_that_the_first_band_alone_misses(self):
        """One pose of benchmarks/partial_fov.py: a slab of the seg3d pseudo-CT keeping 60% along x (cut through
        the head), the whole T1 moved. The band from 0.05 of Nyquist alone offers no candidate near the truth (the
        cut changes the outline that its low radii carry); with the default second band (higher radii) as well, the
        registration lands."""
        from dpcn_med.synth import pseudo_ct

        mr = sitk.ReadImage(str(shared_path("seg3d/MR.nii.gz")))
        bone, brain = (sitk.ReadImage(str(shared_path(f"seg3d/{name}.nii.gz"))) for name in ("skull_mask",
                                                                                             "brain_mask"))
        fixed = sitk.RegionOfInterest(pseudo_ct(mr, bone=bone, brain=brain, seed=0), [96, 232, 160], [31, 0, 0])
        truth = sitk.Similarity3DTransform()
        truth.SetCenter((309.76, -22.2003, 476.8467))
        truth.SetRotation((-0.652855, 0.278081, 0.258473, 0.655471))
        truth.SetTranslation((-0.9135, 5.4924, 9.4228))
        moving = moved_copy(mr, truth)
        corners = foreground_corners(fixed)
        assert target_registration_error(register(fixed, moving).fixed_to_moving, truth, corners) < 2.0
        one_band = register(fixed, moving, solver=SolverConfig(extra_sphere_bands=(), extra_degree_two_weights=(),
                                                               entropy_bins=0))
        assert target_registration_error(one_band.fixed_to_moving, truth, corners) > 20.0


class TestSolverSettings:
    def test_they_reach_the_solver(self):
        """One rotation peak of one band and one weighting, without its half-turn twins, leaves a single candidate
        for the refinement, where the defaults offer several."""
        fixed = mni_2mm()
        truth = random_similarity(np.random.default_rng(4), foreground_box(fixed)[0])
        moving = moved_copy(fixed, truth)
        single = register(fixed, moving, solver=SolverConfig(peaks=1, half_turns=False, extra_sphere_bands=(),
                                                             extra_degree_two_weights=(), entropy_bins=0),
                          refinement=Refinement(stored_start=False))
        assert len(single.candidate_metrics) == 1
        assert len(register(fixed, moving, refinement=Refinement(stored_start=False)).candidate_metrics) > 1

    def test_refused_with_a_learned_model(self, tmp_path):
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8, 16), residual_units=0)), tmp_path / "untrained")
        with pytest.raises(InputError, match="its own solver settings"):
            register(mni_2mm(), mni_2mm(), model=tmp_path / "untrained", bandwidth=16, solver=SolverConfig())


class TestFieldOfViewOverlap:
    def test_share_of_the_fixed_foreground_inside_the_moving_image(self):
        """Crop the moving copy to its upper half along z: the overlap is the share of the fixed foreground voxels
        whose z index lies in that half (counted directly), whatever the pose."""
        fixed = mni_2mm()
        truth = random_similarity(np.random.default_rng(8), foreground_box(fixed)[0], max_shift_mm=0.0)
        foreground = foreground_mask(fixed)
        moved = moved_copy(fixed, truth)  # the same voxels, placed by the pose
        half = moved.GetSize()[2] // 2
        cropped = sitk.RegionOfInterest(moved, [*moved.GetSize()[:2], moved.GetSize()[2] - half], [0, 0, half])
        mask = sitk.GetArrayViewFromImage(foreground) > 0
        expected = mask[half:].sum() / mask.sum()
        assert field_of_view_overlap(foreground, cropped, truth, samples=10 ** 9) == pytest.approx(expected, abs=0.01)
        assert field_of_view_overlap(foreground, moved, truth) == 1.0

    def test_a_slab_registers_to_the_whole_volume(self):
        """Partial field of view: the fixed image is a slab keeping 60% of the head's height (its field of view
        ends at the cuts), the moving image the whole head in another pose."""
        whole = mni_2mm()
        stats = sitk.LabelShapeStatisticsImageFilter()
        stats.Execute(foreground_mask(whole))
        box = stats.GetBoundingBox(1)
        length = int(0.6 * box[5])
        fixed = sitk.RegionOfInterest(whole, [*whole.GetSize()[:2], length], [0, 0, box[2] + (box[5] - length) // 2])
        truth = random_similarity(np.random.default_rng(12), foreground_box(fixed)[0], max_shift_mm=30.0)
        result = register(fixed, moved_copy(whole, truth))
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 2.0
        assert result.overlap == 1.0  # the slab lies inside the whole moving head

    def test_reported_by_register(self):
        result = register(mni_2mm(), mni_2mm(), refine=False)
        assert result.overlap == 1.0 and result.to_dict()["overlap_fraction"] == 1.0


class TestMasks:
    def test_fixed_mask_restricts_what_is_registered(self):
        fixed = mni_2mm()
        mask = sitk.Image(fixed.GetSize(), sitk.sitkUInt8)
        mask.CopyInformation(fixed)
        size = fixed.GetSize()
        mask[:, :, size[2] // 2:] = 1  # the upper half of the head only
        truth = random_similarity(np.random.default_rng(5), foreground_box(fixed)[0], max_shift_mm=20.0)
        result = register(fixed, moved_copy(fixed, truth), fixed_mask=mask)
        assert result.fixed_grid.centre[2] > foreground_box(fixed)[0][2]  # centred on the masked half
        corners = foreground_corners(fixed, mask)
        assert target_registration_error(result.fixed_to_moving, truth, corners) < 1.0


class TestSurfaceMesh:
    @pytest.mark.parametrize("space", ["LPS", "RAS"])
    def test_a_closed_surface_registers_to_its_volume(self, tmp_path, space):
        """The head's surface (marching cubes of its foreground), moved by a known transform and saved as STL.

        RAS: saved as 3D Slicer saves a model in RAS, x and y negated and 'SPACE=RAS' in the STL header.
        """
        pv = pytest.importorskip("pyvista")
        from dpcn_med.preprocess import foreground_mask

        fixed = mni_2mm()
        mask = sitk.ConstantPad(foreground_mask(fixed), [1, 1, 1], [1, 1, 1], 0)  # padded: the surface closes
        grid = pv.ImageData(dimensions=mask.GetSize())
        grid.point_data["mask"] = sitk.GetArrayFromImage(mask).astype(np.float32).ravel()
        surface = grid.contour([0.5], scalars="mask")
        index = np.asarray(surface.points, dtype=np.float64)  # continuous (x, y, z) indices of the padded mask
        physical = np.array([mask.TransformContinuousIndexToPhysicalPoint(p) for p in index.tolist()])
        truth = random_similarity(np.random.default_rng(8), foreground_box(fixed)[0], max_shift_mm=30.0)
        surface.points = np.array([truth.TransformPoint(p) for p in physical.tolist()])
        if space == "LPS":
            surface.save(str(tmp_path / "head.stl"))
        else:
            import vtk

            writer = vtk.vtkSTLWriter()
            writer.SetInputData(surface.transform(np.diag([-1.0, -1.0, 1.0, 1.0]), inplace=False))
            writer.SetHeader("3D Slicer output. SPACE=RAS")
            writer.SetFileTypeToBinary()
            writer.SetFileName(str(tmp_path / "head.stl"))
            assert writer.Write() == 1
        result = register(fixed, tmp_path / "head.stl")
        # Within one voxel of the 2 mm image: the surface is a marching-cubes model of its binary mask, voxelised
        # again at 1 mm, not the image itself.
        assert target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)) < 2.0

    @pytest.mark.parametrize(("points", "message"), [
        # One stray point 3 m away asked for 3101^3 voxels (111 GiB): MemoryError or a machine out of memory.
        ([[0, 0, 0], [10, 10, 10], [3000, 3000, 3000]],
         r"cloud\.vtp voxelised at 1 mm \(its points span 3000 x 3000 x 3000 mm: a stray point, or not in mm\?\): "
         r"size \(3021, 3021, 3021\)"),
        ([[0, 0, 0], [10, 10, 10], [np.nan, 0, 0]], r"cloud\.vtp: has points with NaN or infinite coordinates"),
    ])
    def test_unusable_point_clouds_are_refused_by_name(self, tmp_path, points, message):
        pv = pytest.importorskip("pyvista")
        pv.PolyData(np.asarray(points, dtype=np.float64)).save(tmp_path / "cloud.vtp")
        with pytest.raises(InputError, match=message):
            register(mni_2mm(), tmp_path / "cloud.vtp")

    def test_a_surface_saved_in_metres_is_refused_by_name(self, tmp_path):
        """A head-sized sphere in metres: 0.2 mm across, no voxel inside at 1 mm; the error named no file."""
        pv = pytest.importorskip("pyvista")
        pv.Sphere(radius=0.1).save(tmp_path / "head.stl")
        with pytest.raises(InputError, match=r"^.*head\.stl: "):
            register(mni_2mm(), tmp_path / "head.stl")


class TestStartup:
    def test_learning_free_registration_skips_slow_imports(self):
        # MONAI (seconds) and sympy (torch.unravel_index's first call, 0.6 s) were once imported by every
        # command-line registration of a CT; the learning-free path needs neither.
        script = (
            "import sys\n"
            "import numpy as np, SimpleITK as sitk\n"
            "from dpcn_med.registration import register\n"
            "array = np.full((40, 40, 40), -1000, np.int16)\n"
            "array[8:30, 10:34, 12:28] = 40\n"
            "array[12:20, 14:22, 15:25] = 900\n"
            "ct = sitk.GetImageFromArray(array)\n"
            "register(ct, ct, bandwidth=16, refine=False, moving_modality='ct')\n"
            "print(sorted({name.split('.')[0] for name in sys.modules} & {'monai', 'sympy'}))\n")
        result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
        assert result.stdout.strip().splitlines()[-1] == "[]", result.stdout


class TestErrors:
    def test_unknown_mode(self):
        with pytest.raises(InputError, match="mode 'affine' is not supported"):
            register(mni_2mm(), mni_2mm(), mode="affine")

    def test_missing_model_files(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"ct_mr: no such model \(neither ct_mr\.safetensors nor "):
            register(mni_2mm(), mni_2mm(), model=tmp_path / "ct_mr")

    def test_model_trained_at_another_bandwidth(self, tmp_path):
        save_model(DPCN(ModelConfig(bandwidth=16, channels=(4, 8))), tmp_path / "b16")
        with pytest.raises(InputError, match="trained at bandwidth 16; register with bandwidth=16"):
            register(mni_2mm(), mni_2mm(), model=tmp_path / "b16", bandwidth=32)
        # Unless named, the bandwidth is the model's (it was 32, refused), and the learning-free default 32.
        assert register(mni_2mm(), mni_2mm(), model=tmp_path / "b16", refine=False).bandwidth == 16
        assert register(mni_2mm(), mni_2mm(), refine=False).bandwidth == 32

    @pytest.mark.parametrize("bandwidth", [0, 3, 7, 129])  # 4-7 made grids under 16^3, refused after preprocessing
    def test_bandwidth_out_of_range(self, bandwidth):
        with pytest.raises(InputError, match=rf"bandwidth {bandwidth} is out of range: use an integer in \[8, 128\]$"):
            register(mni_2mm(), mni_2mm(), bandwidth=bandwidth)

    def test_unknown_modality(self):
        with pytest.raises(InputError, match="fixed_modality 'pet'"):
            register(mni_2mm(), mni_2mm(), fixed_modality="pet")

    def test_two_dimensional_image(self):
        with pytest.raises(InputError, match="fixed image: is 2-D"):
            register(sitk.Image([8, 8], sitk.sitkFloat32), mni_2mm())

    def test_with_both_images_bad_the_fixed_one_is_named(self, tmp_path):
        # The two are read at once; the error is the fixed image's, as when they were read one after the other.
        (tmp_path / "cut.nii.gz").write_bytes(b"\x1f\x8b" + bytes(40))
        with pytest.raises(InputNotFoundError, match="absent.nii.gz: not found"):
            register(tmp_path / "absent.nii.gz", tmp_path / "cut.nii.gz")
        with pytest.raises(InputError, match="cut.nii.gz"):
            register(tmp_path / "cut.nii.gz", tmp_path / "absent.nii.gz")

    def test_images_in_memory_get_the_checks_of_files(self):
        complex_image = sitk.RealAndImaginaryToComplex(sitk.Cast(mni_2mm(), sitk.sitkFloat32),
                                                       sitk.Cast(mni_2mm(), sitk.sitkFloat32))
        with pytest.raises(InputError, match="moving image: has complex voxels"):
            register(mni_2mm(), complex_image)

    def test_masks_in_memory_get_the_checks_of_files(self):
        fixed = mni_2mm()
        labels = sitk.Image(fixed.GetSize(), sitk.sitkUInt8)
        labels.CopyInformation(fixed)
        labels[10:20, 10:20, 10:20] = 5
        labels[30:40, 30:40, 30:40] = 2
        with pytest.raises(InputError, match="fixed_mask argument: fixed mask is not binary"):
            register(fixed, fixed, fixed_mask=labels)
        with pytest.raises(InputError, match="moving_mask argument: moving mask is not on its image's voxel grid"):
            register(fixed, fixed, moving_mask=sitk.BinShrink(labels, [2, 2, 2]))

    def test_a_mask_over_background_only_is_named(self, tmp_path):
        fixed = mni_2mm()
        mask = sitk.Image(fixed.GetSize(), sitk.sitkUInt8)
        mask.CopyInformation(fixed)
        mask[0:3, 0:3, 0:3] = 1  # a corner of air
        sitk.WriteImage(mask, str(tmp_path / "corner.nii.gz"))
        with pytest.raises(InputError, match=r"corner\.nii\.gz: holds no foreground of its image"):
            register(fixed, fixed, fixed_mask=tmp_path / "corner.nii.gz")

    def test_a_volume_thinner_than_four_voxels_is_refused_by_name(self):
        """Three slices passed every check, then ITK's recursive Gaussian raised in the refinement's pyramid."""
        fixed = mni_2mm()
        with pytest.raises(InputError, match=r"^moving image: is 3 voxels thick \(size \(98, 116, 3\)\); registering "
                           "needs at least 4 along each axis"):
            register(fixed, fixed[:, :, 45:48])

    @pytest.mark.parametrize("role", ["fixed", "moving"])
    def test_a_mask_too_small_to_refine_is_refused_by_name(self, role):
        """ITK's metric failed on masks 1 to 5 voxels wide (an internal error, not a message); the refinement's
        coarsest level needs 4 of its voxels along each axis: 16 voxels, 32 mm on the 2 mm head."""
        fixed = mni_2mm()
        mask = sitk.Image(fixed.GetSize(), sitk.sitkUInt8)
        mask.CopyInformation(fixed)
        mask[40:56, 50:66, 40:55] = 1  # 15 voxels along z
        masks = {f"{role}_mask": mask}
        with pytest.raises(InputError, match=rf"{role}_mask argument: too small to refine: its box is 32 x 32 x 30 mm; "
                           r"the refinement needs at least 32 x 32 x 32 mm .*--no-refine"):
            register(fixed, fixed, **masks)
        assert register(fixed, fixed, refine=False, **masks).confidence > 0  # without refinement: the solver says
        mask[40:56, 50:66, 55] = 1  # 16 voxels: refined, and the stored pose (the truth here) wins
        result = register(fixed, fixed, **masks)
        assert target_registration_error(result.fixed_to_moving, sitk.Transform(3, sitk.sitkIdentity),
                                         foreground_corners(fixed)) < 0.5


def _small_volume() -> sitk.Image:
    """A 6^3 volume with a random 4^3 core: registers in a fraction of a second."""
    array = np.zeros((6, 6, 6), np.float32)
    array[1:5, 1:5, 1:5] = np.random.default_rng(0).random((4, 4, 4)) * 100 + 50
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((4.0, 4.0, 4.0))
    return image


class TestArguments:
    @pytest.mark.parametrize(("changes", "message"), [
        ({"fixed": None},
         r"^fixed is None \(NoneType\); expected a path \(str or os\.PathLike\) or a SimpleITK image$"),
        ({"moving": np.zeros((4, 4, 4))}, r"^moving is array\(.*\(ndarray\); expected a path .*GetImageFromArray"),
        ({"fixed_mask": 1}, r"^fixed_mask is 1 \(int\); expected a path"),
        ({"moving_mask": torch.ones(4, 4, 4)}, r"^moving_mask is tensor\(.*\(Tensor\); expected a path"),
        ({"refine": "false"}, r"^refine is 'false' \(str\); expected True or False$"),
        ({"resample": 1}, r"^resample is 1 \(int\); expected True or False$"),
        ({"bandwidth": 32.0}, r"^bandwidth is 32\.0 \(float\); expected an integer$"),
        ({"bandwidth": True}, r"^bandwidth is True \(bool\); expected an integer$"),
        ({"refinement": {"starts": 1}},
         r"^refinement is \{'starts': 1\} \(dict\); expected a Refinement or None "
         r"\(from a dict: Refinement\(\*\*values\)\)$"),
        ({"preprocessing": Refinement()}, r"^preprocessing is Refinement\(.*\); expected a Preprocessing or None$"),
        ({"solver": {}}, r"^solver is \{\} \(dict\); expected a SolverConfig or None"),
        ({"progress": "log"}, r"^progress is 'log' \(str\); expected a function progress\(stage, fraction\) or None$"),
        ({"device": None}, r"^device is None \(NoneType\); expected auto, cpu, cuda or cuda:N \(or a torch\.device\)$"),
        ({"model": ""}, r"^model is '' \(str\); expected the path of a model .*, or None or 'none'"),
        ({"model": 0}, r"^model is 0 \(int\); expected the path of a model"),
    ])
    def test_bad_arguments_are_refused_before_any_work(self, changes, message):
        arguments = {"fixed": _small_volume(), "moving": _small_volume(), **changes}
        with pytest.raises(InputError, match=message):
            register(arguments.pop("fixed"), arguments.pop("moving"), **arguments)

    def test_typical_values_are_taken(self):
        calls = []
        result = register(_small_volume(), _small_volume(), bandwidth=np.int64(8), refine=np.bool_(False),
                          resample=True, device=torch.device("cpu"), model="none", preprocessing=Preprocessing(),
                          refinement=Refinement(), solver=SolverConfig(),
                          progress=lambda stage, fraction: calls.append(stage))
        assert result.bandwidth == 8 and type(result.bandwidth) is int and not result.refined
        assert result.resampled is not None and calls[-1] == "done"
