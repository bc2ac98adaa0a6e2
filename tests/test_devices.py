"""The device a user names, checked against this machine."""

from __future__ import annotations

import pytest
import torch

from dpcn_med.devices import resolve_device
from dpcn_med.errors import InputError


class TestResolveDevice:
    @pytest.mark.parametrize(("device", "message"), [
        ("tpu", "not valid|not supported"), ("cuda:0", "no CUDA GPU"), (None, r"device is None \(NoneType\)"),
        (0, r"device is 0 \(int\); expected auto, cpu, cuda or cuda:N"), ("", "device '' is not valid")])
    def test_devices(self, device, message):
        import torch

        if str(device).startswith("cuda") and torch.cuda.is_available():
            pytest.skip("a CUDA GPU is present")
        with pytest.raises(InputError, match=message):
            resolve_device(device)

    def test_a_gpu_index_this_machine_lacks(self, monkeypatch):
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
        assert resolve_device(torch.device("cuda:0")) == torch.device("cuda:0")
        with pytest.raises(InputError, match=r"'cuda:1' asked for, but this machine has 1 CUDA GPU; use cuda:0$"):
            resolve_device("cuda:1")
