"""Tests for dpcn_med.io.tensors: .safetensors files."""

from __future__ import annotations

import os

import pytest

from dpcn_med import io
from dpcn_med.errors import InputError, InputNotFoundError


class TestTensors:
    def test_round_trip_and_atomic(self, tmp_path):
        import torch

        tensors = {"a": torch.arange(6.0).reshape(2, 3), "b": torch.ones(4, dtype=torch.int64)}
        io.write_tensors(tensors, tmp_path / "t.safetensors", metadata={"format": "x"})
        read = io.read_tensors(tmp_path / "t.safetensors")
        assert set(read) == {"a", "b"} and all(torch.equal(read[k], tensors[k]) for k in tensors)
        assert [p.name for p in tmp_path.iterdir()] == ["t.safetensors"]

    def test_permissions_follow_the_umask(self, tmp_path):
        import torch

        mask = os.umask(0o027)
        try:
            io.write_tensors({"a": torch.zeros(2)}, tmp_path / "t.safetensors")
            io.write_json({}, tmp_path / "t.json")
        finally:
            os.umask(mask)
        modes = [(tmp_path / name).stat().st_mode & 0o777 for name in ("t.safetensors", "t.json")]
        assert modes == [0o640, 0o640]  # safetensors alone would make its file 0600

    def test_refuses_pickles_and_garbage(self, tmp_path):
        import torch

        torch.save({"a": torch.zeros(1)}, tmp_path / "w.pt")
        with pytest.raises(InputError, match=r"w\.pt: a pickled file; dpcn_med only reads \.safetensors"):
            io.read_tensors(tmp_path / "w.pt")
        (tmp_path / "g.safetensors").write_bytes(b"\x00" * 40)
        with pytest.raises(InputError, match=r"g\.safetensors: not a readable \.safetensors file"):
            io.read_tensors(tmp_path / "g.safetensors")
        with pytest.raises(InputNotFoundError, match=r"none\.safetensors: not found"):
            io.read_tensors(tmp_path / "none.safetensors")
        with pytest.raises(InputError, match=r"x\.npy: tensors are written as \.safetensors"):
            io.write_tensors({}, tmp_path / "x.npy")
