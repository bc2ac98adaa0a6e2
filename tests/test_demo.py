"""`make demo` end to end, on the built-in CT / MR pair (no ../shared needed)."""

from __future__ import annotations

import re

from dpcn_med.cli import OUTPUT_NAMES
from dpcn_med.demo import main


def test_demo_registers_the_built_in_pair_and_says_where(tmp_path, capsys):
    assert main(["--output", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    output = captured.out
    assert "warning" not in captured.err and "false alarm" not in output, captured.err  # a right result, unflagged
    error = re.search(r"target registration error against the truth: ([\d.]+) mm after refinement", output)
    assert error, output
    assert float(error.group(1)) < 1.0
    assert f"results in {tmp_path / 'registration'}/" in output
    assert sorted(p.name for p in (tmp_path / "registration").iterdir()) == sorted(OUTPUT_NAMES)
    assert {p.name for p in (tmp_path / "inputs").iterdir()} == {"mr_t1.nii.gz", "ct_moved.nii.gz", "truth.tfm"}


def test_an_output_that_is_a_file_is_refused_before_the_pair_is_made(tmp_path, capsys):
    (tmp_path / "afile").write_text("mine")
    assert main(["--output", str(tmp_path / "afile")]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "afile/inputs: cannot be created" in captured.err, captured.err
    assert (tmp_path / "afile").read_text() == "mine"
