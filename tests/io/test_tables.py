"""Tests for dpcn_med.io.tables: text, JSON and CSV files."""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import numpy as np
import pytest

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError


class TestReadText:
    def test_reads_and_names_the_problem(self, tmp_path):
        (tmp_path / "a.txt").write_text("Point 1\n")
        assert io.read_text(tmp_path / "a.txt") == "Point 1\n"
        (tmp_path / "b.txt").write_bytes(b"\xff\xfe\x00")
        with pytest.raises(InputError, match=r"b\.txt: not a utf-8 text file"):
            io.read_text(tmp_path / "b.txt")
        assert io.read_text(tmp_path / "b.txt", encoding="latin-1") == "\xff\xfe\x00"
        (tmp_path / "pairs.csv").write_bytes(gzip.compress(b"\x00\xff" * 100))  # a .nii.gz given for the pairs file
        with pytest.raises(InputError, match=r"^\S*pairs\.csv: is a gzip-compressed \(\.gz\) file, not text$"):
            io.read_text(tmp_path / "pairs.csv")
        with pytest.raises(InputNotFoundError, match=r"c\.txt: not found"):
            io.read_text(tmp_path / "c.txt")


class TestWriteText:
    def test_exact_content(self, tmp_path):
        path = tmp_path / "summary.csv"
        io.write_text("id,status\nα,ok\n", path)
        assert path.read_bytes() == "id,status\nα,ok\n".encode()


class TestReadJson:
    def test_reads_and_names_the_problem(self, tmp_path):
        (tmp_path / "a.json").write_text('{"k": [1, 2]}')
        assert io.read_json(tmp_path / "a.json") == {"k": [1, 2]}
        (tmp_path / "b.json").write_text("{not json")
        with pytest.raises(InputError, match=r"b\.json: not a JSON file"):
            io.read_json(tmp_path / "b.json")
        with pytest.raises(InputNotFoundError, match=r"c\.json: not found"):
            io.read_json(tmp_path / "c.json")

    # Before: RecursionError and a ValueError of Python's limit on integer digits, as internal errors.
    def test_json_python_cannot_hold_is_refused(self, tmp_path):
        (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
        with pytest.raises(InputError, match=r"deep\.json: JSON nested too deeply to read"):
            io.read_json(tmp_path / "deep.json")
        (tmp_path / "digits.json").write_text('{"bandwidth": ' + "1" * 5000 + "}")
        with pytest.raises(InputError, match=r"digits\.json: unreadable JSON \(Exceeds the limit"):
            io.read_json(tmp_path / "digits.json")


class TestWriteJson:
    def test_numpy_values_and_paths(self, tmp_path):
        path = tmp_path / "report.json"
        io.write_json({"matrix": np.eye(2), "score": np.float32(0.5), "count": np.int64(3), "ok": np.bool_(True),
                       "input": Path("a/b.nii.gz"), "shape": (1, 2)}, path)
        text = path.read_text()
        assert json.loads(text) == {"matrix": [[1.0, 0.0], [0.0, 1.0]], "score": 0.5, "count": 3, "ok": True,
                                    "input": "a/b.nii.gz", "shape": [1, 2]}
        assert text.startswith('{\n  "matrix": [\n') and text.endswith("}\n")

    def test_unserialisable_leaves_nothing(self, tmp_path):
        with pytest.raises(TypeError, match="set is not JSON serialisable"):
            io.write_json({"bad": {1, 2}}, tmp_path / "report.json")
        assert os.listdir(tmp_path) == []


class TestReadCsv:
    def test_spreadsheet_byte_order_mark_and_spaced_header(self, tmp_path):
        path = tmp_path / "t.csv"
        path.write_bytes("\ufeffid, fixed ,moving\nx,a.nii,b.nii\n".encode())
        assert io.read_csv(path, {"fixed": str, "moving": str}) == [(2, {"id": "x", "fixed": "a.nii",
                                                                          "moving": "b.nii"})]

    def test_blank_lines_are_skipped_and_rows_carry_their_own_line(self, tmp_path):
        path = tmp_path / "t.csv"
        path.write_text('\n\nid,fixed\n\n \n"a\nb",x.nii\n,,\nc,y.nii\n')
        assert io.read_csv(path, {"fixed": str}) == [(7, {"id": "a\nb", "fixed": "x.nii"}),
                                                      (9, {"id": "c", "fixed": "y.nii"})]

    def test_a_short_row_has_none_for_its_missing_cells(self, tmp_path):
        (tmp_path / "t.csv").write_text("id,fixed,mask\na,x.nii\n")
        assert io.read_csv(tmp_path / "t.csv", {"fixed": str}) == [(2, {"id": "a", "fixed": "x.nii", "mask": None})]

    @pytest.mark.parametrize("text, message", [
        ("id,fixed,fixed\na,x,y\n", r"t\.csv: column 'fixed' appears more than once in the header"),
        ("fixed\nx.nii,y.nii\n", r"t\.csv: line 2: 2 cells under 1 columns \(a comma in a value needs the value in "
                                  r"double quotes\)"),
        ("id,fixed,fixed-mask\na,x,y\n", r"t\.csv: unknown column 'fixed-mask' \(the columns are fixed, id, "
                                         r"fixed_mask\)"),
    ])
    def test_refuses_a_header_or_row_that_would_lose_a_value(self, tmp_path, text, message):
        (tmp_path / "t.csv").write_text(text)
        with pytest.raises(InputError, match=message):
            io.read_csv(tmp_path / "t.csv", {"fixed": str}, allowed=("id", "fixed_mask"))

    def test_folder(self, tmp_path):
        with pytest.raises(InputError, match=r": is a folder; expected a file"):
            io.read_csv(tmp_path, {"fixed": str})


class TestCsv:
    def test_header_from_the_first_row_or_the_columns_given(self, tmp_path):
        rows = [{"id": "a", "tre_mm": 0.5, "note": "x"}, {"id": "b", "tre_mm": 2.0, "note": "y"}]
        io.write_csv(rows, tmp_path / "all.csv")
        assert (tmp_path / "all.csv").read_bytes() == b"id,tre_mm,note\na,0.5,x\nb,2.0,y\n"
        io.write_csv(rows, tmp_path / "some.csv", ["tre_mm", "id"])
        assert (tmp_path / "some.csv").read_text() == "tre_mm,id\n0.5,a\n2.0,b\n"

    def test_no_rows(self, tmp_path):
        io.write_csv([], tmp_path / "empty.csv", ["id", "tre_mm"])
        assert (tmp_path / "empty.csv").read_text() == "id,tre_mm\n"
        with pytest.raises(ValueError, match=r"none\.csv: no rows and no columns"):  # was an IndexError
            io.write_csv([], tmp_path / "none.csv")
        assert not (tmp_path / "none.csv").exists()

    def test_read_back_with_the_types_given(self, tmp_path):
        rows = [{"id": "a", "trial": 0, "tre_mm": 0.5}, {"id": "b", "trial": 1, "tre_mm": 2.25}]
        io.write_csv(rows, tmp_path / "rows.csv")
        assert io.read_csv(tmp_path / "rows.csv", {"trial": int, "tre_mm": float}) == list(zip([2, 3], rows))
        assert io.read_csv(tmp_path / "rows.csv", {"tre_mm": float})[1][1]["trial"] == "1"  # other columns: strings
        with pytest.raises(InputError, match=r"rows\.csv: no column seconds, method: its header row is 'id,trial,"
                                             r"tre_mm'; expected a header row naming trial, seconds, method"):
            io.read_csv(tmp_path / "rows.csv", {"trial": int, "seconds": float, "method": str})
        (tmp_path / "semicolons.csv").write_text("fixed;moving\na.nii;b.nii\n")  # a spreadsheet's other separator
        with pytest.raises(InputError, match=r"no column fixed, moving: its header row is 'fixed;moving'; expected a "
                                             r"header row naming fixed, moving, cells separated by commas$"):
            io.read_csv(tmp_path / "semicolons.csv", {"fixed": str, "moving": str})
        (tmp_path / "bad.csv").write_text("id,trial\na,0\nb,one\n")
        with pytest.raises(InputError, match=r"bad\.csv: line 3: invalid literal for int"):
            io.read_csv(tmp_path / "bad.csv", {"trial": int})
        with pytest.raises(InputNotFoundError, match=r"none\.csv: not found"):
            io.read_csv(tmp_path / "none.csv", {"trial": int})
        (tmp_path / "huge.csv").write_text("id,trial\n" + "a" * 200_000 + ",0\n")  # over csv's field size limit
        with pytest.raises(InputError, match=r"huge\.csv: not a readable CSV file \(field larger than field limit"):
            io.read_csv(tmp_path / "huge.csv", {"trial": int})

    def test_a_row_with_an_unknown_key_leaves_no_file(self, tmp_path):
        with pytest.raises(ValueError, match="fields not in fieldnames"):
            io.write_csv([{"id": "a"}, {"id": "b", "other": 1}], tmp_path / "bad.csv")
        assert list(tmp_path.iterdir()) == []
