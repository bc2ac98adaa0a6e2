"""dpcn_med.models: the DPCN++ network (starts as the learning-free solver, trains end to end) and its weights."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.geometry import geodesic_distance
from dpcn_med.models import DPCN, FeatureExtractor, ModelConfig, load_model, model_paths, pose_loss, save_model
from dpcn_med.preprocess import Preprocessing
from dpcn_med.solver import PoseTarget, SolverConfig, solve
from dpcn_med.synth import random_poses
from tests.conftest import volume_grid

TINY = ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)


def pairs(size: int, count: int, seed: int, mode: str = "similarity") -> tuple[torch.Tensor, torch.Tensor, PoseTarget]:
    """The MNI template on a ``size^3`` grid and moved copies with known poses (small shifts, all of SO(3))."""
    base = volume_grid("mni", size)
    poses = random_poses(count, size, seed, similarity=mode == "similarity", scale_range=(0.9, 1.1),
                         max_shift=0.1 * size)
    moving = torch.cat([pose.moving_from(base) for pose in poses])
    target = PoseTarget(torch.stack([p.rotation for p in poses]).float(), torch.tensor([p.scale for p in poses]),
                        torch.stack([p.translation for p in poses]).float())
    return base.expand(count, -1, -1, -1, -1), moving, target


class TestModelConfig:
    def test_json_round_trip(self):
        config = ModelConfig(bandwidth=16, channels=(4, 8), modalities=("us", "ct"), share_weights=True)
        assert ModelConfig.from_json(json.loads(json.dumps(config.to_json()))) == config

    @pytest.mark.parametrize(("options", "message"), [
        ({"modalities": ("ct", "pet")}, "modalities .* expected two of ct, mr, us"),
        ({"channels": (8,)}, "need at least two levels"),
        ({"bandwidth": 10, "channels": (4, 8, 16, 32)}, "grid size 20 must be divisible by 2\\^3"),
        ({"bandwidth": 6}, r"bandwidth 6 is out of range: use an integer in \[8, 128\]"),  # a 12^3 grid
        ({"mode": "affine"}, "affine"),
    ])
    def test_refuses_bad_values(self, options, message):
        with pytest.raises(InputError, match=message):
            ModelConfig(**options)

    def test_records_the_grid_preprocessing(self):
        assert ModelConfig().grid_preprocessing() == Preprocessing()
        config = ModelConfig(preprocessing={"fill": 0.6})  # the rest at the defaults, and written down
        assert config.grid_preprocessing() == Preprocessing(fill=0.6)
        assert ModelConfig.from_json(json.loads(json.dumps(config.to_json()))) == config
        assert ModelConfig.from_json({**TINY.to_json(), "preprocessing": {}}).grid_preprocessing() == Preprocessing()
        with pytest.raises(InputError, match="preprocessing has unknown keys \\['spacing'\\]"):
            ModelConfig(preprocessing={"spacing": 2.0})

    def test_records_the_solver_settings(self, tmp_path):
        assert ModelConfig().solver_config() == SolverConfig(bandwidth=32)
        assert "bandwidth" not in ModelConfig().solver and "extra_sphere_bands" in ModelConfig().solver
        bands = {"extra_sphere_bands": ((0.2, 0.6), (0.4, 0.95)), "peaks": 6}
        config = ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0, solver=bands)
        assert config.solver_config() == SolverConfig(bandwidth=8, **bands)
        # Nested JSON lists come back as the dataclass's tuples, through a saved model too.
        assert ModelConfig.from_json(json.loads(json.dumps(config.to_json()))) == config
        save_model(DPCN(config), tmp_path / "bands")
        assert load_model(tmp_path / "bands").solver == SolverConfig(bandwidth=8, **bands)
        # A config saved before the key existed: today's defaults.
        old = {k: v for k, v in TINY.to_json().items() if k != "solver"}
        assert ModelConfig.from_json(old).solver_config() == SolverConfig(bandwidth=8)
        with pytest.raises(InputError, match="solver has unknown keys \\['band'\\]"):
            ModelConfig(solver={"band": (0.1, 0.5)})
        with pytest.raises(InputError, match="solver sets \\['bandwidth'\\]: a model does not record"):
            ModelConfig(solver={"bandwidth": 16})

    def test_unknown_keys_refused(self):
        with pytest.raises(InputError, match="unknown keys \\['learning_rate'\\]"):
            ModelConfig.from_json({**TINY.to_json(), "learning_rate": 0.1})

    # Before: {} loaded as a bandwidth-32 model whatever the weights were.
    @pytest.mark.parametrize("key", ["bandwidth", "channels", "residual_units", "modalities", "share_weights", "mode",
                                     "preprocessing"])
    def test_keys_that_define_the_model_are_required(self, key):
        with pytest.raises(InputError, match=f"model config lacks \\['{key}'\\]; a saved model must state"):
            ModelConfig.from_json({k: v for k, v in TINY.to_json().items() if k != key})

    # Before: a JSON list raised AttributeError ('tuple' object has no attribute 'items'), "no" shared weights, and
    # channels of 10^6 built gigabytes of UNet.
    @pytest.mark.parametrize(("options", "message"), [
        ({"preprocessing": []}, r"preprocessing is \(\) \(tuple\); expected a mapping of Preprocessing settings"),
        ({"solver": [1]}, r"solver is \(1,\) \(tuple\); expected a mapping of SolverConfig settings"),
        ({"solver": None}, r"solver is None \(NoneType\); expected a mapping of SolverConfig settings"),
        ({"share_weights": "no"}, r"share_weights is 'no' \(str\); expected True or False"),
        ({"version": 7}, r"version is 7 \(int\); expected a string"),
        ({"channels": [4, 8, 10 ** 6]}, r"channels \(4, 8, 1000000\): expected positive integers <= 1024"),
        ({"channels": [True, True]}, r"channels \(True, True\): expected positive integers"),
        ({"residual_units": 10 ** 7}, r"residual_units is 10000000; expected an integer >= 0 and <= 8"),
        ({"solver": {"peaks": 10 ** 9}}, r"peaks is 1000000000; expected an integer >= 1 and <= 64"),
    ], ids=["preprocessing-list", "solver-list", "solver-null", "share-string", "version-int", "channels-huge",
            "channels-bool", "residual-huge", "peaks-huge"])
    def test_unusable_json_values_refused(self, options, message):
        with pytest.raises(InputError, match=message):
            ModelConfig.from_json({**TINY.to_json(), **options})


class TestFeatureExtractor:
    def test_starts_as_the_identity_and_keeps_the_shape(self):
        extractor = FeatureExtractor((4, 8), residual_units=0)
        volume = torch.rand(2, 1, 16, 16, 16)
        assert torch.equal(extractor(volume), volume)
        with torch.no_grad():
            extractor.gain.fill_(1.0)
        assert extractor(volume).shape == volume.shape and not torch.equal(extractor(volume), volume)


class TestDPCN:
    def test_untrained_model_is_the_learning_free_solver(self):
        fixed, moving, _ = pairs(16, 2, seed=3)
        model = DPCN(TINY).eval()
        with torch.no_grad():
            output = model(fixed, moving)
            # Its temperatures, stored as softplus parameters, equal the defaults to float rounding, which a soft
            # arg-max over a flat correlation peak can show; compare at the model's own.
            reference = solve(fixed, moving, "similarity", bandwidth=8, temperatures=model.temperatures())
        torch.testing.assert_close(output.rotation, reference.rotation)
        torch.testing.assert_close(output.scale, reference.scale)
        torch.testing.assert_close(output.translation, reference.translation, atol=1e-4, rtol=0)
        torch.testing.assert_close(output.confidence, reference.confidence)

    def test_training_compensates_with_the_noisy_truth(self):
        fixed, moving, target = pairs(16, 2, seed=4, mode="rigid")
        model = DPCN(ModelConfig(**{**TINY.to_json(), "mode": "rigid", "channels": (4, 8, 16)})).train()
        output = model(fixed, moving, target, generator=torch.Generator().manual_seed(0))
        angle = geodesic_distance(output.compensation.double(), target.rotation.double())
        assert (angle > 0).all() and (angle < torch.deg2rad(torch.tensor(10.0))).all()  # noisy, near the truth
        terms = pose_loss(output, target)
        assert set(terms) == {"rotation_kl", "rotation_l1", "translation_kl", "translation_l1", "scale_kl",
                              "scale_l1", "total"}
        terms["total"].backward()
        for extractor in (model.rotation_fixed, model.rotation_moving, model.translation_fixed,
                          model.translation_moving):
            assert extractor.gain.grad is not None and extractor.gain.grad != 0

    def test_shared_weights(self):
        model = DPCN(ModelConfig(**{**TINY.to_json(), "share_weights": True, "channels": (4, 8, 16)}))
        assert model.rotation_moving is model.rotation_fixed and model.translation_moving is model.translation_fixed
        assert sum(p.numel() for p in model.parameters()) < sum(p.numel() for p in DPCN(TINY).parameters())

    # Before: a gain of 3e38 overflowed the features to Inf, which the solver turned into a NaN rotation.
    def test_features_that_overflow_refused(self):
        model = DPCN(TINY).eval()
        with torch.no_grad():
            model.rotation_fixed.gain.fill_(3e38)
        fixed, moving, _ = pairs(16, 1, seed=3)
        with torch.no_grad(), pytest.raises(InputError, match="the rotation_fixed features hold NaN or Inf values"):
            model(fixed, moving)

    def test_wrong_grid_refused(self):
        with pytest.raises(InputError, match="this model takes \\(B, 1, 16, 16, 16\\) pairs"):
            DPCN(TINY)(torch.rand(1, 1, 32, 32, 32), torch.rand(1, 1, 32, 32, 32))

    # Before: the training loop's autocast covered the solver too, which returned bfloat16 rotations and
    # log-probabilities, off by degrees.
    def test_the_caller_s_autocast_leaves_the_solver_in_float32(self):
        fixed, moving, target = pairs(16, 2, seed=7)
        model = DPCN(TINY).train()
        reference = model(fixed, moving, target, generator=torch.Generator().manual_seed(0))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            output = model(fixed, moving, target, generator=torch.Generator().manual_seed(0))
        assert output.rotation.dtype == output.stage.rotation_log_prob.dtype == torch.float32
        for name in ("rotation", "scale", "translation", "confidence"):
            torch.testing.assert_close(getattr(output, name), getattr(reference, name))
        torch.testing.assert_close(output.stage.rotation_log_prob, reference.stage.rotation_log_prob)

    def test_amp_runs_only_the_extractors_in_bfloat16(self):
        """An untrained model's features are its inputs (gains 0), so the pose is the float32 one exactly."""
        fixed, moving, target = pairs(16, 2, seed=7)
        model = DPCN(TINY).train()
        unet_dtypes = []
        model.rotation_fixed.unet.register_forward_hook(lambda module, args, output: unet_dtypes.append(output.dtype))
        reference = model(fixed, moving, target, generator=torch.Generator().manual_seed(0))
        output = model(fixed, moving, target, generator=torch.Generator().manual_seed(0), amp=True)
        assert unet_dtypes == [torch.float32, torch.bfloat16]
        assert output.rotation.dtype == output.stage.rotation_log_prob.dtype == torch.float32
        for name in ("rotation", "scale", "translation", "confidence"):
            torch.testing.assert_close(getattr(output, name), getattr(reference, name))
        torch.testing.assert_close(output.stage.rotation_log_prob, reference.stage.rotation_log_prob)
        pose_loss(output, target)["total"].backward()
        assert model.rotation_fixed.gain.grad.dtype == torch.float32 and model.rotation_fixed.gain.grad != 0

    # Before: these failed inside MONAI or the solver with raw RuntimeErrors, or (float64) as a dtype mismatch.
    @pytest.mark.parametrize(("shape", "dtype", "message"), [
        ((1, 2, 16, 16, 16), torch.float32, r"grids \(1, 2, 16, 16, 16\) and \(1, 2, 16, 16, 16\): this model takes"),
        ((1, 16, 16, 16), torch.float32, r"grids \(1, 16, 16, 16\) and \(1, 16, 16, 16\): this model takes \(B, 1, "),
        ((16, 16, 16), torch.float32, r"grids \(16, 16, 16\) and \(16, 16, 16\): this model takes"),
        ((1, 1, 16, 16, 16), torch.int32, r"fixed is int32; this model takes .* floating-point grids"),
        ((1, 1, 16, 16, 16), torch.bool, r"fixed is bool; this model takes .* floating-point grids"),
        ((1, 1, 16, 16, 16), torch.complex64, r"fixed is complex64; this model takes .* floating-point grids")])
    def test_grids_that_are_not_batched_single_channel_floats_refused(self, shape, dtype, message):
        volume = torch.ones(shape, dtype=dtype)
        with pytest.raises(InputError, match=message):
            DPCN(TINY).eval()(volume, volume)

    def test_other_float_dtypes_are_cast_to_the_parameters(self):
        fixed, moving, _ = pairs(16, 1, seed=3)
        model = DPCN(TINY).eval()
        with torch.no_grad():
            reference = model(fixed, moving)
            for dtype in (torch.float64, torch.float16):
                output = model(fixed.to(dtype), moving.to(dtype))
                assert output.rotation.dtype == output.translation.dtype == torch.float32
                if dtype == torch.float64:  # numpy's float64 holds the float32 grids exactly
                    torch.testing.assert_close(output.rotation, reference.rotation)
                    torch.testing.assert_close(output.translation, reference.translation)

    def test_a_grid_that_is_not_a_tensor_refused(self):
        fixed, _, _ = pairs(16, 1, seed=3)
        with pytest.raises(InputError, match=r"moving is .*\(ndarray\); this model takes \(B, 1, 16, 16, 16\) pairs"):
            DPCN(TINY).eval()(fixed, fixed.numpy())

    # The training loop passes its generator (one per rank, advanced by the step), not the global RNG.
    def test_compensation_noise_follows_the_generator(self):
        fixed, moving, target = pairs(16, 2, seed=4)
        model = DPCN(TINY).train()

        def compensation(seed: int) -> torch.Tensor:
            torch.manual_seed(0)  # the global RNG fixed: only the generator may change the noise
            return model(fixed, moving, target, generator=torch.Generator().manual_seed(seed)).compensation

        first, again, other = compensation(1), compensation(1), compensation(2)
        torch.testing.assert_close(again, first, rtol=0, atol=0)
        assert not torch.allclose(other, first)

    def test_a_few_steps_lower_the_loss(self):
        """A tiny model on a fixed batch of heterogeneous pairs (the moving image's contrast inverted): AdamW
        lowers the pose loss within a few steps."""
        torch.manual_seed(0)
        fixed, moving, target = pairs(16, 8, seed=5)
        moving = torch.where(moving > 0, 1.0 - moving, moving)  # bright becomes dark inside the head
        model = DPCN(TINY).train()
        optimiser = torch.optim.AdamW(model.parameters(), lr=3e-2)
        losses = []
        for step in range(8):
            optimiser.zero_grad()
            loss = pose_loss(model(fixed, moving, target, generator=torch.Generator().manual_seed(step)),
                             target)["total"]
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        assert min(losses[-3:]) < 0.9 * losses[0], losses


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
