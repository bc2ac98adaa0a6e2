"""dpcn_med.models.weights: saving and loading models."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.models import DPCN, ModelConfig, load_model, model_paths, save_model
from tests.models.conftest import TINY, pairs


class TestWeights:
    def test_round_trip_gives_the_same_registration(self, tmp_path):
        model = DPCN(TINY)
        with torch.no_grad():
            for extractor in (model.rotation_fixed, model.translation_moving):
                extractor.gain.fill_(0.5)
        weights, config = save_model(model, tmp_path / "ct_mr", record={"steps": 3})
        assert (weights.name, config.name) == ("ct_mr.safetensors", "ct_mr.json")
        assert json.loads(config.read_text())["record"] == {"steps": 3}
        loaded = load_model(weights)
        assert not loaded.training and loaded.config == TINY
        fixed, moving, _ = pairs(16, 1, seed=6)
        with torch.no_grad():
            torch.testing.assert_close(loaded(fixed, moving).translation, model.eval()(fixed, moving).translation)

    # Before: "auto" failed in torch and "cuda" without a GPU in an assertion, after the files were read.
    def test_devices_as_register_reads_them(self, tmp_path):
        save_model(DPCN(TINY), tmp_path / "model")
        expected = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        assert {p.device.type for p in load_model(tmp_path / "model", device="auto").parameters()} == {expected.type}
        if not torch.cuda.is_available():
            with pytest.raises(InputError, match="device 'cuda' asked for, but this torch build sees no CUDA GPU"):
                load_model(tmp_path / "model", device="cuda")
        with pytest.raises(InputError, match="device 'tpu' is not valid"):  # refused before the (absent) files
            load_model(tmp_path / "absent", device="tpu")

    def test_shared_extractors_are_stored_once(self, tmp_path):
        from safetensors import safe_open

        model = DPCN(ModelConfig(**{**TINY.to_json(), "share_weights": True, "channels": (4, 8, 16)}))
        with torch.no_grad():  # weights no fresh model has: loading, not initialisation, must give them
            for index, parameter in enumerate(model.parameters()):
                parameter.add_(0.3 + 0.01 * index)
        weights, _ = save_model(model, tmp_path / "mr_mr")
        with safe_open(str(weights), "pt") as stored:
            names = list(stored.keys())
        assert not any(name.startswith(("rotation_moving.", "translation_moving.")) for name in names)
        loaded = load_model(tmp_path / "mr_mr.json")
        assert loaded.rotation_moving is loaded.rotation_fixed and loaded.translation_moving is loaded.translation_fixed
        saved_state, loaded_state = model.state_dict(), loaded.state_dict()
        assert list(loaded_state) == list(saved_state)
        for name, tensor in saved_state.items():
            assert torch.equal(loaded_state[name], tensor), name

    @pytest.mark.parametrize("suffix", [".pt", ".pth", ".ckpt"])
    def test_pickles_are_refused(self, tmp_path, suffix):
        path = tmp_path / f"model{suffix}"
        torch.save({"x": torch.zeros(1)}, path)
        with pytest.raises(InputError, match=f"model\\{suffix}: a pickled file"):
            load_model(path)

    def test_missing_or_foreign_files(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"nothing\.safetensors: no such model \(neither "
                                                     r"nothing\.safetensors nor nothing\.json exists in "):
            load_model(tmp_path / "nothing.safetensors")
        save_model(DPCN(TINY), tmp_path / "a")
        (tmp_path / "a.safetensors").rename(tmp_path / "lone.safetensors")  # one file of the pair lost
        with pytest.raises(InputNotFoundError, match=r"lone\.json: not found"):
            load_model(tmp_path / "lone")
        save_model(DPCN(TINY), tmp_path / "a")
        (tmp_path / "a.json").write_text(json.dumps({"format": "something else"}))
        with pytest.raises(InputError, match="a.json: not a dpcn_med model config"):
            load_model(tmp_path / "a")
        save_model(DPCN(TINY), tmp_path / "b")
        other = ModelConfig(**{**TINY.to_json(), "channels": (4, 16, 16)})
        save_model(DPCN(other), tmp_path / "c")
        (tmp_path / "c.safetensors").replace(tmp_path / "b.safetensors")
        with pytest.raises(InputError, match="b.safetensors: does not fit b.json"):
            load_model(tmp_path / "b")

    @pytest.mark.parametrize(("edit", "message"), [
        (lambda d: d.pop("config"), "a\\.json: lacks the 'config' key"),
        (lambda d: d.update(config=[1, 2]), "a\\.json: 'config' is a list, expected a mapping"),
        (lambda d: d["config"].update(bandwidth="8"), "a\\.json: .*(model config|bandwidth)"),
        (lambda d: d["config"].update(learning_rate=0.1), "a\\.json: model config has unknown keys"),
    ], ids=["no-config", "config-list", "string-bandwidth", "unknown-key"])
    def test_unusable_configs_name_the_file(self, tmp_path, edit, message):
        _, config = save_model(DPCN(TINY), tmp_path / "a")
        description = json.loads(config.read_text())
        edit(description)
        config.write_text(json.dumps(description))
        with pytest.raises(InputError, match=message):
            load_model(tmp_path / "a")

    @pytest.mark.parametrize(("edit", "message"), [
        (lambda t: t.to(torch.int32), "is int32, expected floating point"),
        (lambda t: torch.full_like(t, float("nan")), "holds NaN or Inf values"),
        (lambda t: t.index_fill(0, torch.tensor([0]), float("inf")), "holds NaN or Inf values"),
    ], ids=["int32", "nan", "inf"])
    def test_unusable_weights_name_the_file_and_tensor(self, tmp_path, edit, message):
        from safetensors.torch import load_file, save_file

        weights, _ = save_model(DPCN(TINY), tmp_path / "a")
        save_file({k: edit(v) for k, v in load_file(str(weights)).items()}, str(weights),
                  metadata={"format": "dpcn_med.model/1"})
        with pytest.raises(InputError, match=f"a\\.safetensors: tensor [\\w.]+ {message}"):
            load_model(tmp_path / "a")

    # Before: 1e300 in float64 passed the check and became Inf in the float32 model.
    def test_float64_weights_are_checked_as_float32(self, tmp_path):
        from safetensors.torch import load_file, save_file

        weights, _ = save_model(DPCN(TINY), tmp_path / "a")
        tensors = load_file(str(weights))
        tensors["rotation_fixed.gain"] = torch.tensor(1e300, dtype=torch.float64)
        save_file(tensors, str(weights), metadata={"format": "dpcn_med.model/1"})
        with pytest.raises(InputError, match=r"a\.safetensors: tensor rotation_fixed\.gain holds NaN or Inf values "
                                             r"\(as float32\)"):
            load_model(tmp_path / "a")

    # Before: softplus(-200) is 0 in float32, and the model registered ~200 mm off with confidence NaN, exit 0.
    def test_zero_learned_temperature_refused(self, tmp_path):
        model = DPCN(TINY)
        with torch.no_grad():
            model.temperatures.raw["translation"].fill_(-200.0)
        save_model(model, tmp_path / "a")
        with pytest.raises(InputError, match=r"a\.safetensors: the learned translation temperature is 0\.0 "
                                             r"\(softplus of temperatures\.raw\.translation\); expected a finite "
                                             r"number > 0"):
            load_model(tmp_path / "a")

    # Before: weights and config of different trainings loaded silently when their shapes agreed.
    def test_weights_of_another_config_refused(self, tmp_path):
        from safetensors.torch import load_file, save_file

        save_model(DPCN(TINY), tmp_path / "a")
        save_model(DPCN(ModelConfig(**{**TINY.to_json(), "preprocessing": {"fill": 0.6}})), tmp_path / "b")
        (tmp_path / "b.safetensors").replace(tmp_path / "a.safetensors")
        with pytest.raises(InputError, match=r"a\.safetensors: saved with another config than \S+a\.json"):
            load_model(tmp_path / "a")
        # Weights written before the hash existed load as before; a later format is refused.
        weights = tmp_path / "a.safetensors"
        tensors = load_file(str(weights))
        save_file(tensors, str(weights), metadata={"format": "dpcn_med.model/1"})
        assert load_model(tmp_path / "a").config.grid_preprocessing().fill == 0.5
        save_file(tensors, str(weights), metadata={"format": "dpcn_med.model/2"})
        with pytest.raises(InputError, match=r"a\.safetensors: weights of format 'dpcn_med\.model/2'; this version"):
            load_model(tmp_path / "a")

    # Before: OSError (File name too long) from Path.exists, an internal error.
    def test_a_name_the_file_system_refuses(self, tmp_path):
        with pytest.raises(InputError, match=r"x{300}: not a usable model path \(File name too long\)"):
            load_model(tmp_path / ("x" * 300))

    def test_paths(self):
        assert [p.name for p in model_paths("dir/model.v2.json")] == ["model.v2.safetensors", "model.v2.json"]
        assert model_paths(Path("dir") / "model") == (Path("dir/model.safetensors"), Path("dir/model.json"))

    # Before: None, 3 and b"x" raised TypeError, "" and "." a ValueError about PosixPath('.'), "runs/" became
    # runs.safetensors beside the folder.
    @pytest.mark.parametrize(("path", "message"), [
        (None, r"model path is None \(NoneType\); expected a model file: NAME, NAME\.safetensors or NAME\.json"),
        (3, r"model path is 3 \(int\); expected a model file"),
        (b"model", r"model path is b'model' \(bytes\); expected a model file"),
        ("", r"model path is empty; expected a model file"),
        (".", r"model path '\.' names a folder, not a file"),
        ("/", r"model path '/' names a folder, not a file"),
        ("runs/", r"model path 'runs/' names a folder, not a file"),
        ("runs/..", r"model path 'runs/\.\.' names a folder, not a file"),
    ])
    def test_bad_paths_are_refused(self, path, message):
        with pytest.raises(InputError, match=message):
            model_paths(path)
        with pytest.raises(InputError, match=message):
            load_model(path)
