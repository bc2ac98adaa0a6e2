"""`dpcn-med`: outputs, exit codes, bad inputs (message, code 2, nothing written), batches and interoperability."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med import __version__
from dpcn_med.cli import OUTPUT_NAMES, main
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.preprocess import foreground_box
from tests.conftest import shared_path
from tests.test_registration import coronal_slab, mni_2mm


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path, sitk.Transform]:
    """The 2 mm MNI template and a copy of it moved by a known large similarity transform, as files."""
    folder = tmp_path_factory.mktemp("pair")
    fixed = mni_2mm()
    truth = random_similarity(np.random.default_rng(11), foreground_box(fixed)[0], max_shift_mm=40.0)
    sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
    sitk.WriteImage(moved_copy(fixed, truth), str(folder / "moving.nrrd"))
    return folder / "fixed.nii.gz", folder / "moving.nrrd", truth


@pytest.fixture(scope="module")
def registered(pair, tmp_path_factory) -> tuple[Path, int]:
    output = tmp_path_factory.mktemp("run") / "out"
    code = main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--quiet"])
    return output, code


class TestRegister:
    def test_writes_every_output_and_exits_0(self, registered):
        output, code = registered
        assert code == 0
        assert sorted(p.name for p in output.iterdir()) == sorted(OUTPUT_NAMES)
        assert not list(output.parent.glob(".dpcn-med-*"))  # no staging folder left behind

    def test_skipped_outputs_are_neither_written_nor_left_from_an_earlier_run(self, pair, tmp_path, capsys):
        output = tmp_path / "out"
        assert main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine", "-q"]) == 0
        earlier = json.loads((output / "report.json").read_text())["final"]
        assert main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine", "--no-overview",
                     "--no-resampled"]) == 0
        written = [name for name in OUTPUT_NAMES if name not in ("overview.png", "moving_resampled.nii.gz")]
        assert sorted(p.name for p in output.iterdir()) == sorted(written)
        report = json.loads((output / "report.json").read_text())
        assert report["outputs"] == written and report["final"] == earlier
        assert f"outputs in {output}/: {', '.join(written)}" in capsys.readouterr().out

    def test_a_file_of_yours_that_no_run_listed_stays(self, pair, tmp_path):
        """overview.png and moving_resampled.nii.gz of the user's own, in the output folder, were deleted."""
        output = tmp_path / "out"
        output.mkdir()
        (output / "overview.png").write_text("my figure")
        shutil.copy(pair[1], output / "moving_resampled.nii.gz")
        assert main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine", "--no-overview",
                     "--no-resampled", "-q"]) == 0
        assert (output / "overview.png").read_text() == "my figure"
        assert (output / "moving_resampled.nii.gz").read_bytes() == pair[1].read_bytes()

    def test_transform_files_recover_the_truth(self, registered, pair):
        output, _ = registered
        corners = foreground_corners(mni_2mm())
        for name in ("transform.tfm", "transform.h5"):
            transform = sitk.ReadTransform(str(output / name))
            assert target_registration_error(transform, pair[2], corners) < 1.0
        inverse = sitk.ReadTransform(str(output / "inverse.tfm"))
        point = [5.0, 10.0, -20.0]
        np.testing.assert_allclose(inverse.TransformPoint(pair[2].TransformPoint(point)), point, atol=1.0)

    def test_report(self, registered, pair):
        report = json.loads((registered[0] / "report.json").read_text())
        assert report["inputs"]["fixed"]["path"] == str(pair[0])
        assert report["status"] == "ok" and report["success_probability"] >= report["min_success_probability"]
        assert report["dpc"]["type"] == report["final"]["type"] == "VersorRigid3DTransform"
        assert report["start"] == "phase correlation"  # the copy was moved far from the stored pose
        assert report["mattes_mutual_information"]["refined"] <= report["mattes_mutual_information"]["dpc"]
        assert report["version"] == __version__

    def test_resampled_volume_on_the_fixed_grid(self, registered):
        resampled = sitk.ReadImage(str(registered[0] / "moving_resampled.nii.gz"))
        fixed = mni_2mm()
        assert resampled.GetSize() == fixed.GetSize()
        np.testing.assert_allclose(resampled.GetOrigin(), fixed.GetOrigin(), atol=1e-4)
        a, b = sitk.GetArrayFromImage(resampled).ravel(), sitk.GetArrayFromImage(fixed).ravel()
        assert np.corrcoef(a, b)[0, 1] > 0.99

    def test_overview_is_a_png(self, registered):
        assert (registered[0] / "overview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    @pytest.mark.parametrize("name", ["transform.tfm", "transform.h5"])
    def test_itk_reads_the_same_transform(self, registered, pair, name):
        itk = pytest.importorskip("itk", reason="the itk package (the test extra) is not installed")
        path = str(registered[0] / name)
        transform = itk.transformread(path)[0]
        fixed = itk.imread(str(pair[0]), itk.F)
        moving = itk.imread(str(pair[1]), itk.F)
        resampled = itk.resample_image_filter(moving, transform=transform, use_reference_image=True,
                                              reference_image=fixed)
        expected = sitk.Resample(sitk.Cast(sitk.ReadImage(str(pair[1])), sitk.sitkFloat32),
                                 sitk.ReadImage(str(pair[0])), sitk.ReadTransform(path), sitk.sitkLinear, 0.0)
        np.testing.assert_allclose(itk.array_from_image(resampled), sitk.GetArrayFromImage(expected), atol=1e-3)

    def test_masks_are_used_and_reported(self, pair, tmp_path):
        from dpcn_med.preprocess import foreground_mask

        mask = tmp_path / "fixed_mask.nii.gz"
        sitk.WriteImage(foreground_mask(sitk.ReadImage(str(pair[0]))), str(mask))
        code = main(["register", str(pair[0]), str(pair[1]), "--fixed-mask", str(mask), "-o", str(tmp_path / "o"),
                     "-q"])
        report = json.loads((tmp_path / "o" / "report.json").read_text())
        assert code == 0 and report["inputs"]["fixed_mask"] == str(mask)
        transform = sitk.ReadTransform(str(tmp_path / "o" / "transform.tfm"))
        assert target_registration_error(transform, pair[2], foreground_corners(mni_2mm())) < 1.0

    def test_a_pair_aligned_as_stored_says_so(self, tmp_path, capsys):
        slab, whole = coronal_slab()
        sitk.WriteImage(slab, str(tmp_path / "slab.nii.gz"))
        sitk.WriteImage(whole, str(tmp_path / "whole.nii.gz"))
        assert main(["register", str(tmp_path / "slab.nii.gz"), str(tmp_path / "whole.nii.gz"), "-o",
                     str(tmp_path / "o"), "--no-overview", "--no-resampled"]) == 0
        assert "refined from the stored pose" in capsys.readouterr().out
        report = json.loads((tmp_path / "o" / "report.json").read_text())
        assert report["start"] == "stored pose" and report["final"]["rotation_degrees"] < 0.5

    def test_python_dash_m_and_version(self):
        done = subprocess.run([sys.executable, "-m", "dpcn_med", "--version"], capture_output=True, text=True,
                              check=False)
        assert done.returncode == 0 and done.stdout.strip() == f"dpcn-med {__version__}"


def _exiting(body: str) -> subprocess.CompletedProcess:
    """A child Python that runs ``body`` (with ``exit_now`` imported), its output captured."""
    return subprocess.run([sys.executable, "-c", "import atexit, sys, threading, time\n"
                           "from dpcn_med.cli import exit_now\n" + textwrap.dedent(body)],
                          capture_output=True, text=True, check=False, timeout=60)


class TestExit:
    def test_exit_handlers_run_and_buffered_output_is_flushed(self):
        done = _exiting("""
            atexit.register(lambda: print("handler ran", file=sys.stderr))
            sys.stdout.write("no line end yet")
            exit_now(3)
        """)
        assert done.returncode == 3 and done.stdout == "no line end yet" and done.stderr == "handler ran\n"

    def test_a_running_thread_is_waited_for(self):
        done = _exiting("""
            threading.Thread(target=lambda: (time.sleep(0.3), print("thread done", flush=True))).start()
            exit_now(0)
        """)
        assert done.returncode == 0 and done.stdout == "thread done\n"

    def test_output_that_cannot_be_flushed_is_not_success(self):
        broken = """
            class Broken:
                def write(self, text): return len(text)
                def flush(self): raise BrokenPipeError(32, "Broken pipe")
            sys.stdout = Broken()
            exit_now({code})
        """
        assert _exiting(broken.format(code=0)).returncode == 120
        assert _exiting(broken.format(code=2)).returncode == 2

    def test_the_command_ends_through_it(self):
        assert "run()" in (Path(__file__).parents[1] / "dpcn_med" / "__main__.py").read_text()
        pyproject = (Path(__file__).parents[1] / "pyproject.toml").read_text()
        assert re.search(r'^dpcn-med = "dpcn_med\.cli:run"$', pyproject, re.MULTILINE)


def _constant(path: Path) -> None:
    sitk.WriteImage(sitk.Image([20, 20, 20], sitk.sitkInt16) + 7, str(path))


def _nan(path: Path) -> None:
    array = np.random.default_rng(0).random((20, 20, 20)).astype(np.float32)
    array[3, 4, 5] = np.nan
    sitk.WriteImage(sitk.GetImageFromArray(array), str(path))


def _two_d(path: Path) -> None:
    sitk.WriteImage(sitk.GetImageFromArray(np.random.default_rng(0).random((30, 30)).astype(np.float32)), str(path))


def _four_d(path: Path) -> None:
    volumes = [sitk.GetImageFromArray(np.random.default_rng(i).random((10, 10, 10)).astype(np.float32)) for i in (0, 1)]
    sitk.WriteImage(sitk.JoinSeries(volumes), str(path))


def _spacing(path: Path) -> None:
    image = sitk.GetImageFromArray(np.random.default_rng(0).random((20, 20, 20)).astype(np.float32))
    image.SetSpacing((1.0, 1.0, 1e-5))
    sitk.WriteImage(image, str(path))


def _truncated(path: Path) -> None:
    sitk.WriteImage(mni_2mm(), str(path))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _truncated_header(path: Path) -> None:
    # Cut inside its gzip-compressed header: SimpleITK alone reads this as a volume of zeros.
    sitk.WriteImage(mni_2mm(), str(path))
    path.write_bytes(path.read_bytes()[:300])


def _sheared(path: Path) -> None:
    image = sitk.GetImageFromArray(np.random.default_rng(0).random((20, 20, 20)).astype(np.float32))
    image.SetDirection((1, 0, 0, 0, 1, 0.3, 0, 0, 0.954))
    sitk.WriteImage(image, str(path))


def _garbage(path: Path) -> None:
    path.write_bytes(b"this is not an image" * 100)


def _huge(path: Path) -> None:
    # A header-only MetaImage claiming 100000^2 x 1000 voxels: refused before any pixel is read.
    path.write_text("ObjectType = Image\nNDims = 3\nDimSize = 100000 100000 1000\nElementType = MET_FLOAT\n"
                    "ElementSpacing = 1 1 1\nElementDataFile = huge.raw\n")


BAD_INPUTS = {
    "missing": (None, "moving.nii.gz", "not found|does not exist|no such"),
    "garbage": (_garbage, "moving.nii.gz", "in none of the formats read here"),
    "truncated": (_truncated, "moving.nii.gz", "truncated"),
    "truncated_header": (_truncated_header, "moving.nii.gz", "truncated"),
    "sheared": (_sheared, "moving.nrrd", "not orthonormal"),
    "two_d": (_two_d, "moving.nii.gz", "2-D"),
    "four_d": (_four_d, "moving.nii.gz", "4-D"),
    "constant": (_constant, "moving.nii.gz", "constant|all voxels"),
    "nan": (_nan, "moving.nii.gz", "NaN"),
    "spacing": (_spacing, "moving.nii.gz", "spacing"),
    "too_large": (_huge, "moving.mhd", "memory"),
}


class TestBadInput:
    @pytest.mark.parametrize("case", list(BAD_INPUTS))
    def test_exit_2_one_line_nothing_written(self, case, pair, tmp_path, capsys):
        make, name, message = BAD_INPUTS[case]
        bad = tmp_path / name
        if make is not None:
            make(bad)
        output = tmp_path / "out"
        code = main(["register", str(pair[0]), str(bad), "-o", str(output)])
        err = capsys.readouterr().err.strip()
        assert code == 2
        assert len(err.splitlines()) == 1 and str(bad) in err
        assert re.search(message, err, flags=re.IGNORECASE), err
        assert not output.exists() and not list(tmp_path.glob(".dpcn-med-*"))

    def test_several_dicom_series_are_listed(self, pair, tmp_path, capsys):
        folder = tmp_path / "dicom"
        folder.mkdir()
        for series, offset in (("1.2.826.0.1.3680043.2.1125.1", 0), ("1.2.826.0.1.3680043.2.1125.2", 100)):
            _write_dicom_series(folder, series, offset)
        code = main(["register", str(pair[0]), str(folder), "-o", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert code == 2 and "1.2.826.0.1.3680043.2.1125.1" in err and "1.2.826.0.1.3680043.2.1125.2" in err
        assert "@" in err and not (tmp_path / "out").exists()

    def test_output_over_an_input_is_refused(self, pair, tmp_path, capsys):
        folder = tmp_path / "case"
        folder.mkdir()
        moving = folder / "report.json"  # an input named like an output, inside the output folder
        moving.write_bytes(pair[1].read_bytes())
        before = moving.read_bytes()
        code = main(["register", str(pair[0]), str(moving), "-o", str(folder)])
        assert code == 2 and "never overwritten" in capsys.readouterr().err
        assert moving.read_bytes() == before

    def test_output_spelt_through_a_missing_folder_is_refused(self, pair, tmp_path, capsys):
        # case/x/../case names case once x exists: the run would make x, then write over the moving image
        folder = tmp_path / "case"
        folder.mkdir()
        moving = folder / "moving_resampled.nii.gz"
        sitk.WriteImage(sitk.ReadImage(str(pair[1])), str(moving))
        before = moving.read_bytes()
        code = main(["register", str(pair[0]), str(moving), "-o", f"{folder}/x/../../case", "--no-refine"])
        assert code == 2 and "moving_resampled.nii.gz: is an input of this run" in capsys.readouterr().err
        assert moving.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == [moving.name]

    def test_bad_mask(self, pair, tmp_path, capsys):
        mask = tmp_path / "mask.nii.gz"
        sitk.WriteImage(sitk.Image([5, 5, 5], sitk.sitkUInt8) + 1, str(mask))
        code = main(["register", str(pair[0]), str(pair[1]), "--fixed-mask", str(mask), "-o", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert code == 2 and str(mask) in err and not (tmp_path / "o").exists()

    @pytest.mark.parametrize("where", ["under_a_file", "over_a_file"])
    def test_unusable_output_folder_is_refused_before_any_work(self, where, pair, tmp_path, capsys, monkeypatch):
        from dpcn_med import registration

        monkeypatch.setattr(registration, "register",
                            lambda *args, **kwargs: pytest.fail("registered"))
        (tmp_path / "notes.txt").write_text("x")
        output = tmp_path / "notes.txt" / "out" if where == "under_a_file" else tmp_path / "notes.txt"
        assert main(["register", str(pair[0]), str(pair[1]), "-o", str(output)]) == 2
        assert re.search(r"notes\.txt.*(is a file|is not a folder)", capsys.readouterr().err)
        assert (tmp_path / "notes.txt").read_text() == "x"

    def test_output_through_a_dangling_link_is_refused_before_any_work(self, pair, tmp_path, capsys, monkeypatch):
        from dpcn_med import registration

        monkeypatch.setattr(registration, "register",
                            lambda *args, **kwargs: pytest.fail("registered"))
        (tmp_path / "link").symlink_to(tmp_path / "gone")
        assert main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "link" / "out")]) == 2
        assert re.search(r"link/out: cannot be created: \S+link is a link to \S+gone, which does not exist",
                         capsys.readouterr().err)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["link"]

    @pytest.mark.parametrize("command", ["register", "register-batch", "benchmark"])
    def test_an_empty_output_name_is_refused(self, command, pair, tmp_path, capsys, monkeypatch):
        """``-o "$OUT"`` with ``OUT`` unset must not write into the working folder."""
        monkeypatch.chdir(tmp_path)
        inputs = {"register": [str(pair[0]), str(pair[1])], "register-batch": [str(tmp_path / "pairs.csv")],
                  "benchmark": []}[command]
        with pytest.raises(SystemExit) as caught:
            main([command, *inputs, "-o", ""])
        assert caught.value.code == 2 and "an empty output folder" in capsys.readouterr().err
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("value,message", [("nan", "'nan' is not a finite number"),
                                               ("high", "'high' is not a number")])  # was "invalid _finite_float"
    def test_min_confidence_must_be_finite(self, pair, tmp_path, capsys, value, message):
        with pytest.raises(SystemExit) as caught:
            main(["register", str(pair[0]), str(pair[1]), "--min-confidence", value, "-o", str(tmp_path / "o")])
        assert caught.value.code == 2 and message in capsys.readouterr().err

    def test_missing_model_file(self, pair, tmp_path, capsys):
        code = main(["register", str(pair[0]), str(pair[1]), "--model", str(tmp_path / "ct_mr"), "-o",
                     str(tmp_path / "o")])
        assert code == 2 and "ct_mr: no such model (neither ct_mr.safetensors nor ct_mr.json" in capsys.readouterr().err
        assert not (tmp_path / "o").exists()

    def test_integer_model_weights(self, pair, tmp_path, capsys):
        from safetensors.torch import load_file, save_file

        from dpcn_med.models import DPCN, ModelConfig, save_model

        weights, _ = save_model(DPCN(ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)),
                                tmp_path / "ct_mr")
        save_file({k: v.to(torch.int32) for k, v in load_file(str(weights)).items()}, str(weights),
                  metadata={"format": "dpcn_med.model/1"})
        code = main(["register", str(pair[0]), str(pair[1]), "--model", str(tmp_path / "ct_mr"), "-o",
                     str(tmp_path / "o")])
        assert code == 2 and re.search(r"ct_mr\.safetensors: tensor \S+ is int32, expected floating point",
                                       capsys.readouterr().err)
        assert not (tmp_path / "o").exists()


def _write_dicom_series(folder: Path, series_uid: str, offset: int) -> None:
    array = (np.random.default_rng(offset).random((4, 16, 16)) * 1000).astype(np.int16)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for index in range(array.shape[0]):
        image = sitk.GetImageFromArray(array[index])
        for tag, value in (("0020|000e", series_uid), ("0020|000d", "1.2.826.0.1.3680043.2.1125.9"),
                           ("0008|0060", "CT"), ("0008|103e", f"series {offset}"),
                           ("0020|0032", f"0\\0\\{index * 2.0}"), ("0020|0013", str(index + 1)),
                           ("0008|0018", f"{series_uid}.{index + 1}"), ("0028|0030", "1\\1")):
            image.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"{offset + index:04d}.dcm"))
        writer.Execute(image)


class TestLowConfidence:
    # Before: `confidence < min_confidence` is False for NaN, so a NaN confidence exited 0.
    def test_a_nan_confidence_is_never_confident(self, pair, tmp_path, monkeypatch, capsys):
        from dataclasses import replace

        from dpcn_med import registration as module
        real = module.register
        monkeypatch.setattr(module, "register",
                            lambda *args, **kwargs: replace(real(*args, **kwargs), confidence=float("nan")))
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "o"), "--no-refine",
                     "--no-overview"])
        assert code == 3 and "below" in capsys.readouterr().err

    def test_unrelated_volumes_exit_3_with_outputs(self, pair, tmp_path, capsys):
        rng = np.random.default_rng(0)
        noise = sitk.GetImageFromArray((rng.random((40, 48, 36)) * 100).astype(np.float32))
        noise.SetSpacing((3.0, 3.0, 3.0))
        sitk.WriteImage(noise, str(tmp_path / "noise.nii.gz"))
        output = tmp_path / "out"
        code = main(["register", str(pair[0]), str(tmp_path / "noise.nii.gz"), "-o", str(output), "--no-refine"])
        assert code == 3 and "below" in capsys.readouterr().err
        report = json.loads((output / "report.json").read_text())
        assert report["status"] == "low confidence" and report["confidence"] < report["min_confidence"]
        # Without the overview the warning does not send the user to a file that is not there.
        lean = tmp_path / "lean"
        assert main(["register", str(pair[0]), str(tmp_path / "noise.nii.gz"), "-o", str(lean), "--no-refine",
                     "--no-overview"]) == 3
        assert "rerun without --no-overview" in capsys.readouterr().err and not (lean / "overview.png").exists()


class TestQualityFlag:
    def test_a_head_against_noise_exits_3_and_says_what_to_check(self, pair, tmp_path, capsys):
        rng = np.random.default_rng(0)
        noise = sitk.SmoothingRecursiveGaussian(
            sitk.GetImageFromArray((rng.random((40, 48, 36)) * 100).astype(np.float32)), 2.0)
        noise.SetSpacing((3.0, 3.0, 3.0))
        sitk.WriteImage(noise, str(tmp_path / "noise.nii.gz"))
        output = tmp_path / "out"
        code = main(["register", str(pair[0]), str(tmp_path / "noise.nii.gz"), "-o", str(output), "--no-overview"])
        err = capsys.readouterr().err
        assert code == 3 and "likely wrong" in err and "same anatomy" in err and "flipped left to right" in err
        report = json.loads((output / "report.json").read_text())
        assert report["status"] == "low confidence"
        assert report["success_probability"] < report["min_success_probability"]

    def test_a_head_against_a_phantom_exits_3(self, tmp_path, capsys):
        """A wrong body part: the seg3d head MR against the MRI-DIR porcine phantom's CT (real volumes)."""
        head, phantom = shared_path("seg3d/MR.nii.gz"), shared_path("mridir/mridir_ct_3p0mm.nii.gz")
        output = tmp_path / "out"
        assert main(["register", str(head), str(phantom), "-o", str(output), "--no-overview", "--no-resampled"]) == 3
        assert "likely wrong" in capsys.readouterr().err
        assert json.loads((output / "report.json").read_text())["success_probability"] < 0.5

    def test_a_mirrored_moving_volume_is_named(self, tmp_path, capsys):
        """The stroke FLAIR with its voxels flipped left to right (the header kept), moved, against the T1: flagged,
        and the mirror check says so."""
        from dpcn_med.registration import mirrored_copy

        fixed, flair = shared_path("stroke/T1.nii.gz"), sitk.ReadImage(str(shared_path("stroke/FLAIR.nii.gz")))
        truth = random_similarity(np.random.default_rng(3), foreground_box(flair)[0], max_shift_mm=30.0)
        sitk.WriteImage(moved_copy(mirrored_copy(flair), truth), str(tmp_path / "flair.nii.gz"))
        output = tmp_path / "out"
        assert main(["register", str(fixed), str(tmp_path / "flair.nii.gz"), "-o", str(output), "--no-overview",
                     "--no-resampled"]) == 3
        assert "looks mirrored" in capsys.readouterr().err
        assert json.loads((output / "report.json").read_text())["mirrored"]["likely"] is True

    def test_mirrored_copy_flips_the_voxels_nearest_left_right(self):
        image = sitk.GetImageFromArray(np.arange(24, dtype=np.float32).reshape(2, 3, 4))
        image.SetDirection((0, 1, 0, 1, 0, 0, 0, 0, 1))  # voxel axis 1 (y) runs along LPS x
        image.SetOrigin((5.0, -2.0, 1.0))
        from dpcn_med.registration import mirrored_copy

        mirrored = mirrored_copy(image)
        assert mirrored.GetDirection() == image.GetDirection() and mirrored.GetOrigin() == image.GetOrigin()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(mirrored), sitk.GetArrayFromImage(image)[:, ::-1, :])

    def test_min_probability_overrides_the_models_threshold(self, registered, pair, tmp_path, capsys):
        probability = json.loads((registered[0] / "report.json").read_text())["success_probability"]
        assert probability < 1
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "o"), "--no-overview",
                     "--no-resampled", "--min-probability", "1"])
        assert code == 3 and "below 100%" in capsys.readouterr().err

    @pytest.mark.parametrize("value", ["1.5", "-0.1", "nan"])
    def test_min_probability_is_a_probability(self, pair, tmp_path, capsys, value):
        with pytest.raises(SystemExit) as exit_:
            main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "o"), "--min-probability", value])
        assert exit_.value.code == 2 and "--min-probability" in capsys.readouterr().err
        assert not (tmp_path / "o").exists()


class TestProgress:
    def test_json_lines_for_programs(self, pair, tmp_path, capsys):
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "out"), "--no-refine", "-q",
                     "--progress", "json"])
        assert code == 0
        events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert [e["stage"] for e in events][0] == "reading" and events[-1] == {"stage": "done", "fraction": 1.0,
                                                                                 "pair": ""}
        fractions = [e["fraction"] for e in events]
        assert fractions == sorted(fractions) and {"solving", "resampling"} <= {e["stage"] for e in events}


class TestFailureLeavesNothing:
    def test_internal_error_while_writing(self, pair, tmp_path, monkeypatch, capsys):
        import dpcn_med.report

        def broken(*args, **kwargs):
            raise RuntimeError("disk on fire\nsecond line of the message")

        monkeypatch.setattr(dpcn_med.report, "overview_figure", broken)
        output = tmp_path / "out"
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine"])
        error = capsys.readouterr().err
        assert code == 1 and "disk on fire second line of the message" in error and error.count("\n") == 1
        assert not output.exists() and not list(tmp_path.glob(".dpcn-med-*"))

    def test_the_resampled_volume_failing_in_its_thread_is_the_commands_error(self, pair, tmp_path, monkeypatch,
                                                                                capsys):
        """It is written on a thread while the overview is drawn; its error must not be lost there."""
        from dpcn_med import io

        write_image = io.write_image

        def broken(image, path, **kwargs):
            if Path(path).name == "moving_resampled.nii.gz":
                raise OSError("disk full while compressing")
            return write_image(image, path, **kwargs)

        monkeypatch.setattr(io, "write_image", broken)
        output = tmp_path / "out"
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine"])
        assert code == 1 and "disk full while compressing" in capsys.readouterr().err
        assert not output.exists() and not list(tmp_path.glob(".dpcn-med-*"))

    def test_folders_it_created_are_removed(self, pair, tmp_path, monkeypatch, capsys):
        import dpcn_med.report

        monkeypatch.setattr(dpcn_med.report, "overview_figure", lambda *args, **kwargs: 1 / 0)
        (tmp_path / "kept").mkdir()
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "kept" / "a" / "b"), "--no-refine"])
        assert code == 1 and "ZeroDivisionError" in capsys.readouterr().err
        assert list(tmp_path.iterdir()) == [tmp_path / "kept"] and not list((tmp_path / "kept").iterdir())

    def test_terminated_while_writing(self, pair, tmp_path, monkeypatch, capsys):
        """SIGTERM (the Slicer module's Cancel) unwinds like Ctrl-C: the staged files go, nothing is left."""
        import os
        import signal

        import dpcn_med.report

        monkeypatch.setattr(dpcn_med.report, "overview_figure",
                            lambda *args, **kwargs: os.kill(os.getpid(), signal.SIGTERM))
        handler = signal.getsignal(signal.SIGTERM)
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "out"), "--no-refine"])
        assert code == 130 and "interrupted" in capsys.readouterr().err
        assert not (tmp_path / "out").exists() and signal.getsignal(signal.SIGTERM) == handler

    def test_terminated_while_moving_into_place(self, pair, tmp_path, monkeypatch, capsys):
        """A signal between two renames waited for the last: before, the folder held the earlier run's report.json
        beside this run's first transforms."""
        import os
        import signal

        import dpcn_med.outputs

        output = tmp_path / "out"
        assert main(["register", str(pair[0]), str(pair[0]), "-o", str(output), "--no-refine", "--no-overview",
                     "--no-resampled"]) == 0
        renamed, rename = [], os.replace

        def interrupted(source, target):
            if Path(target).parent == output:  # a move into place, not an atomic write into the staging folder
                renamed.append(Path(target).name)
                if len(renamed) == 2:
                    os.kill(os.getpid(), signal.SIGTERM)
            rename(source, target)

        monkeypatch.setattr(dpcn_med.outputs.os, "replace", interrupted)
        handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(output), "--no-refine", "--no-overview",
                     "--no-resampled"])
        assert code == 130 and "interrupted" in capsys.readouterr().err
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
        assert renamed[-1] == "report.json" and json.loads((output / "report.json").read_text())["inputs"]["moving"][
            "path"].endswith("moving.nrrd")
        matrix = np.asarray(json.loads((output / "report.json").read_text())["final"]["fixed_to_moving_lps"])
        written = sitk.ReadTransform(str(output / "transform.tfm"))
        np.testing.assert_allclose(written.TransformPoint((1.0, 2.0, 3.0)), matrix[:3, :3] @ (1, 2, 3) + matrix[:3, 3],
                                   atol=1e-6)

    def test_an_output_name_taken_by_a_folder_is_refused_before_the_work(self, pair, tmp_path, capsys):
        (tmp_path / "out" / "report.json").mkdir(parents=True)
        code = main(["register", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "out"), "--no-refine"])
        assert code == 2 and "report.json: exists and is a folder" in capsys.readouterr().err
        assert [p.name for p in (tmp_path / "out").iterdir()] == ["report.json"]


class TestBatch:
    def test_resumable_with_summary(self, pair, tmp_path, capsys):
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\ngood,{pair[0]},{pair[1]}\nbroken,{pair[0]},missing.nii.gz\n")
        output = tmp_path / "cohort"
        assert main(["register-batch", str(table), "-o", str(output), "--no-refine"]) == 2
        # said before the first pair, not only in its turn
        err = capsys.readouterr().err
        assert err.index(f"1 path(s) of the pairs file do not exist (broken: {tmp_path / 'missing.nii.gz'})") < (
            err.index("[2/2] broken bad input"))
        rows = list(csv.DictReader((output / "summary.csv").open()))
        assert [r["status"] for r in rows] == ["ok", "bad input"] and "missing.nii.gz" in rows[1]["message"]
        assert (output / "good" / "report.json").is_file() and not (output / "broken").exists()
        capsys.readouterr()
        first = rows[0]
        assert main(["register-batch", str(table), "-o", str(output), "--no-refine"]) == 2
        rows = list(csv.DictReader((output / "summary.csv").open()))
        assert rows[0] == {**first, "status": "done earlier"}  # the earlier run's numbers, read from its report
        (tmp_path / "good.csv").write_text(f"id,fixed,moving\ngood,{pair[0]},{pair[1]}\n")
        assert main(["register-batch", str(tmp_path / "good.csv"), "-o", str(output), "--no-refine",
                     "--min-confidence", "2"]) == 3
        rows = list(csv.DictReader((output / "summary.csv").open()))
        assert rows[0]["status"] == "done earlier, low confidence"

    def test_an_earlier_result_of_other_inputs_or_settings_is_not_reused(self, pair, tmp_path, capsys):
        """Default ids follow the rows' order, so a shortened file gives pair 2 the id pair 1 had; an edited row or
        another mode keeps its id. Each is registered again, and says so."""
        flipped = tmp_path / "s2" / "moving.nrrd"
        flipped.parent.mkdir()
        sitk.WriteImage(sitk.Flip(sitk.ReadImage(str(pair[1])), (True, False, False)), str(flipped))
        table, output = tmp_path / "pairs.csv", tmp_path / "cohort"
        table.write_text(f"fixed,moving\n{pair[0]},{pair[1]}\n{pair[0]},{flipped}\n")
        assert main(["register-batch", str(table), "-o", str(output), "--no-refine", "--no-overview"]) in (0, 3)
        assert sorted(p.name for p in output.iterdir()) == ["001-moving", "002-moving", "summary.csv"]
        capsys.readouterr()
        table.write_text(f"fixed,moving\n{pair[0]},{flipped}\n")  # 001-moving now names the second pair
        for mode in ("rigid", "similarity", "similarity"):
            main(["register-batch", str(table), "-o", str(output), "--no-refine", "--no-overview", "--mode", mode])
            report = json.loads((output / "001-moving" / "report.json").read_text())
            assert report["request"]["moving"] == str(flipped.resolve()) and report["mode"] == mode
        out = capsys.readouterr().out
        assert out.count("replaced an earlier result of other inputs or settings") == 2
        assert out.count("done earlier") == 1
        # With the overview asked for, the same inputs and settings: registered again, and not said to differ.
        main(["register-batch", str(table), "-o", str(output), "--no-refine", "--mode", "similarity"])
        assert "registered again: the earlier result lacks overview.png" in capsys.readouterr().out

    def test_one_pairs_output_never_replaces_another_pairs_input(self, pair, tmp_path, capsys):
        """Pair b reads a file where pair a would write its resampled volume: before, b registered a's output (or,
        with --no-resampled, found its input deleted)."""
        (tmp_path / "cohort" / "a").mkdir(parents=True)
        shutil.copy(pair[1], tmp_path / "cohort" / "a" / "moving_resampled.nii.gz")
        before = (tmp_path / "cohort" / "a" / "moving_resampled.nii.gz").read_bytes()
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\na,{pair[0]},{pair[1]}\nb,{pair[0]},cohort/a/moving_resampled.nii.gz\n")
        for options in ([], ["--no-resampled"]):
            assert main(["register-batch", str(table), "-o", str(tmp_path / "cohort"), *options]) == 2
            assert re.search(r"cohort/a/moving_resampled\.nii\.gz: is the moving of pair 'b', which this run would "
                             r"replace", capsys.readouterr().err)
        assert (tmp_path / "cohort" / "a" / "moving_resampled.nii.gz").read_bytes() == before
        assert sorted(p.name for p in (tmp_path / "cohort").rglob("*")) == ["a", "moving_resampled.nii.gz"]

    @pytest.mark.parametrize("options, message", [
        (["--bandwidth", "-5"], "bandwidth -5 is out of range"),
        (["--model", "nosuch"], "nosuch"),
        (["--device", "tpu"], "tpu"),
    ])
    def test_options_are_checked_once_before_any_pair(self, options, message, pair, tmp_path, capsys):
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\na,{pair[0]},{pair[1]}\nb,{pair[0]},{pair[1]}\n")
        assert main(["register-batch", str(table), "-o", str(tmp_path / "o"), *options]) == 2
        err = capsys.readouterr().err
        assert err.startswith("dpcn-med: error: ") and err.count("\n") == 1 and message in err, err
        assert not (tmp_path / "o").exists()

    def test_a_summary_that_is_a_folder_is_refused_before_the_work(self, pair, tmp_path, capsys):
        (tmp_path / "o" / "summary.csv").mkdir(parents=True)
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\na,{pair[0]},{pair[1]}\n")
        assert main(["register-batch", str(table), "-o", str(tmp_path / "o")]) == 2
        assert "summary.csv: exists and is not a file" in capsys.readouterr().err
        assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["summary.csv"]

    def test_the_summary_lists_what_an_interrupted_run_finished(self, pair, tmp_path, capsys, monkeypatch):
        import dpcn_med.batch

        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\na,{pair[0]},{pair[1]}\nb,{pair[0]},{pair[1]}\n")
        register_pair = dpcn_med.batch.register_to_folder

        def interrupted_at_b(fixed, moving, output, *args, **kwargs):
            if output.name == "b":
                raise KeyboardInterrupt
            return register_pair(fixed, moving, output, *args, **kwargs)

        monkeypatch.setattr(dpcn_med.batch, "register_to_folder", interrupted_at_b)
        assert main(["register-batch", str(table), "-o", str(tmp_path / "o"), "--no-refine", "--no-overview"]) == 130
        assert [row["id"] for row in csv.DictReader((tmp_path / "o" / "summary.csv").open())] == ["a"]

    def test_staging_left_by_a_killed_run_is_removed(self, pair, tmp_path):
        stale = tmp_path / "o" / "a" / ".dpcn-med-killed"
        stale.mkdir(parents=True)
        (stale / "transform.tfm").write_text("half")
        os.utime(stale, (time.time() - 1, time.time() - 1))  # before this registration began
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\na,{pair[0]},{pair[1]}\n")
        main(["register-batch", str(table), "-o", str(tmp_path / "o"), "--no-refine", "--no-overview"])
        assert (tmp_path / "o" / "a" / "report.json").is_file() and not stale.exists()

    def test_errors_go_to_stderr_even_when_quiet(self, pair, tmp_path, capsys):
        table = tmp_path / "pairs.csv"
        table.write_text(f"id,fixed,moving\nbroken,{pair[0]},missing.nii.gz\n")
        assert main(["register-batch", str(table), "-o", str(tmp_path / "cohort"), "-q"]) == 2
        out, err = capsys.readouterr()
        assert out == "" and re.fullmatch(r"dpcn-med: warning: 1 path\(s\) of the pairs file do not exist .*\n"
                                          r"\[1/1\] broken bad input \S*missing\.nii\.gz: not found.*\n", err)

    def test_the_pairs_file_is_never_the_summary(self, pair, tmp_path, capsys):
        (tmp_path / "cohort").mkdir()
        table = tmp_path / "cohort" / "summary.csv"
        table.write_text(f"id,fixed,moving\ngood,{pair[0]},{pair[1]}\n")
        before = table.read_bytes()
        for output in (tmp_path / "cohort", f"{tmp_path}/new/../cohort"):
            assert main(["register-batch", str(table), "-o", str(output), "--no-refine"]) == 2
            assert "summary.csv: is this run's pairs file" in capsys.readouterr().err
        assert table.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["cohort"]

    def test_a_model_is_known_by_its_contents_not_by_the_path_given(self, tmp_path, monkeypatch):
        """A model trained again into the same folder had the earlier model's results reused ('done earlier')."""
        from dpcn_med.outputs import model_identity as _model_identity
        from dpcn_med.models import DPCN, ModelConfig, save_model

        config = ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)
        (tmp_path / "run").mkdir()
        torch.manual_seed(0)
        save_model(DPCN(config), tmp_path / "run" / "model")
        first = _model_identity(str(tmp_path / "run" / "model"))
        monkeypatch.chdir(tmp_path / "run")
        assert _model_identity("model.safetensors") == first  # the same files by another path
        torch.manual_seed(1)
        save_model(DPCN(config), tmp_path / "run" / "model")
        again = _model_identity("model")
        assert again["weights"] == first["weights"] and again["weights_sha256"] != first["weights_sha256"]
        assert _model_identity("None") == _model_identity("learning-free") == "none"

    def test_a_tilde_is_the_home_folder_and_other_paths_are_from_the_pairs_folder(self, tmp_path, monkeypatch):
        from dpcn_med.batch import read_pairs as _read_pairs

        monkeypatch.setenv("HOME", str(tmp_path / "home"))
        (tmp_path / "pairs.csv").write_text("fixed,moving,moving_mask\n~/ct.nii.gz,mr.nii.gz,/abs/m.nii\n")
        assert _read_pairs(tmp_path / "pairs.csv") == [{
            "id": "001-mr", "fixed": str(tmp_path / "home" / "ct.nii.gz"), "moving": str(tmp_path / "mr.nii.gz"),
            "fixed_mask": None, "moving_mask": "/abs/m.nii"}]

    @pytest.mark.parametrize("text, message", [
        ("a,b\n1,2\n", r"pairs\.csv: no column fixed, moving"),
        ("fixed,moving\n", r"pairs\.csv: no pairs"),
        ("id,fixed,moving\nfirst,a.nii\n", r"pairs\.csv: line 2: a fixed or moving path is missing"),
        ("fixed,moving\na.nii,b.nii\n , c.nii\n", r"pairs\.csv: line 3: a fixed or moving path is missing"),
        ("id,fixed,moving\nx,a.nii,b.nii\nx,c.nii,d.nii\n", r"pairs\.csv: line 3: id 'x' is repeated \(case aside\): "
                                                          r"line 2 has it; give every pair its own id$"),
        ("id,fixed,moving\nSub01,a.nii,b.nii\nsub01,c.nii,d.nii\n", r"line 3: id 'sub01' is repeated \(case aside\): "
         r"line 2 has it \('Sub01': ids that differ only in case share a folder on macOS and Windows\)"),
        # a spreadsheet's byte-order mark and spaces in the header are read through
        ("\ufeffid, fixed, moving\n..,a.nii,b.nii\n", r"pairs\.csv: line 2: id '\.\.' is not a folder name"),
        ("id,fixed,moving\nsummary.csv,a.nii,b.nii\n", r"line 2: id 'summary\.csv' is not a folder name"),
        ('id,fixed,moving\n"a\nb",a.nii,b.nii\n', r"line 3: id 'a\\nb' is not a folder name"),
        (f"id,fixed,moving\n{'x' * 256},a.nii,b.nii\n", r"line 2: id 'x{256}' is not a folder name"),
        ("\n\nfixed,moving\n\na.nii,b.nii\n,c.nii\n", r"pairs\.csv: line 6: a fixed or moving path is missing"),
        ("id,fixed,moving\nx,a\0.nii,b.nii\n", r"pairs\.csv: line 2: a path holds a NUL character"),
        ("id,fixed,moving,moving\nx,a.nii,b.nii,c.nii\n", r"pairs\.csv: column 'moving' appears more than once"),
        ("id,fixed,moving,fixed-mask\nx,a.nii,b.nii,c.nii\n", r"pairs\.csv: unknown column 'fixed-mask' \(the "
         r"columns are fixed, moving, id, fixed_mask, moving_mask\)"),
        ("fixed,moving\na.nii,b.nii,m.nii\n", r"pairs\.csv: line 2: 3 cells under 2 columns"),
        (None, r"pairs\.csv: not found"),
        ("", r"pairs\.csv: is a folder"),
    ])
    def test_bad_pairs_file(self, text, message, tmp_path, capsys):
        table = tmp_path / "pairs.csv"
        if text == "":
            table.mkdir()
        elif text is not None:
            table.write_text(text, encoding="utf-8")
        assert main(["register-batch", str(table), "-o", str(tmp_path / "o")]) == 2
        assert re.search(message, capsys.readouterr().err) and not (tmp_path / "o").exists()


class TestInfo:
    def test_prints_geometry_and_range(self, pair, capsys):
        assert main(["info", str(pair[0])]) == 0
        out = capsys.readouterr().out
        assert re.search(r"spacing\s+\(2\.0, 2\.0, 2\.0\)", out) and "orientation" in out, out

    def test_missing_file(self, tmp_path, capsys):
        assert main(["info", str(tmp_path / "nope.nii")]) == 2
        assert "nope.nii" in capsys.readouterr().err

    @pytest.mark.parametrize("command", ["info", "train", "benchmark"])
    def test_internal_errors_offer_a_traceback_the_command_can_give(self, command, pair, tmp_path, capsys, monkeypatch):
        """Every command's internal error says 'rerun with --verbose'; train, benchmark and info had no such option."""
        import dpcn_med.benchmark
        import dpcn_med.io
        import dpcn_med.train

        def broken(*args, **kwargs):
            raise RuntimeError("broken on purpose")

        target = {"info": (dpcn_med.io, "image_summary"), "train": (dpcn_med.train, "load_config"),
                  "benchmark": (dpcn_med.benchmark, "run_benchmark")}[command]
        monkeypatch.setattr(*target, broken)
        arguments = {"info": [str(pair[0])], "train": ["--config", str(tmp_path / "c.yaml")],
                     "benchmark": ["-o", str(tmp_path / "b")]}[command]
        assert main([command, *arguments]) == 1
        assert capsys.readouterr().err == ("dpcn-med: internal error: RuntimeError: broken on purpose (rerun with "
                                           "--verbose for the traceback)\n")
        assert main([command, *arguments, "--verbose"]) == 1
        err = capsys.readouterr().err
        assert err.startswith("Traceback (most recent call last)") and "broken on purpose" in err
