"""dpcn_med.models.dpcn: the model config and the DPCN++ network (the learning-free solver until trained)."""

from __future__ import annotations

import json

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import geodesic_distance
from dpcn_med.models import DPCN, ModelConfig, load_model, pose_loss, save_model
from dpcn_med.models.dpcn import ranking_loss
from dpcn_med.solver import LossWeights
from dpcn_med.preprocess import Preprocessing
from dpcn_med.solver import SolverConfig, solve
from tests.models.conftest import TINY, pairs


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
        # A solver recorded before extra_degree_two_weights and the entropy sources existed ran without them, and
        # still does.
        recorded = TINY.to_json()
        for key in ("extra_degree_two_weights", "entropy_bins", "extra_entropy_bins"):
            del recorded["solver"][key]
        assert ModelConfig.from_json(recorded).solver_config() == SolverConfig(
            bandwidth=8, extra_degree_two_weights=(), entropy_bins=0, extra_entropy_bins=())
        assert ModelConfig.from_json(TINY.to_json()).solver_config() == SolverConfig(bandwidth=8)
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
                              "scale_l1", "candidate_ranking", "total"}
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


class TestCandidateRanking:
    """The learned choice among the solver's candidates (../shared/LEARNING.md, change 1)."""

    def test_training_scores_the_solver_s_candidates_with_gradients(self):
        fixed, moving, target = pairs(16, 2, seed=6)
        model = DPCN(TINY).train()
        output = model(fixed, moving, target, generator=torch.Generator().manual_seed(0))
        ranking = output.stage.ranking
        assert output.candidate_scores.shape == ranking.score.shape == output.candidate_errors.shape
        dropped = ranking.score == float("-inf")
        assert (output.candidate_scores[dropped] == float("-inf")).all()
        assert (output.candidate_errors[dropped] == float("inf")).all()
        assert torch.isfinite(output.candidate_scores[:, 0]).all()  # the chosen candidate is never dropped
        # The errors are each candidate's angle to the truth.
        torch.testing.assert_close(output.candidate_errors[:, 0].double(), torch.rad2deg(geodesic_distance(
            ranking.rotation[:, 0].double(), target.rotation.double())), rtol=0, atol=1e-3)
        weights = LossWeights(candidate_ranking=2.0, candidate_degrees=180.0)
        terms = pose_loss(output, target, weights)
        assert terms["candidate_ranking"] > 0
        terms["candidate_ranking"].backward()
        # The ranking reaches the translation extractors (which choose at inference) and the ranking temperature.
        for extractor in (model.translation_fixed, model.translation_moving):
            assert extractor.gain.grad is not None and extractor.gain.grad != 0
        assert torch.isfinite(model.ranking_temperature.grad) and model.ranking_temperature.grad != 0

    def test_eval_mode_has_no_ranking_term(self):
        fixed, moving, target = pairs(16, 1, seed=7)
        with torch.no_grad():
            output = DPCN(TINY).eval()(fixed, moving)
        assert output.candidate_scores is None
        assert pose_loss(output, target)["candidate_ranking"] == 0

    @staticmethod
    def _output(scores, errors, temperature=0.01):
        from dpcn_med.models import DPCNOutput
        return DPCNOutput(rotation=None, scale=None, translation=None, confidence=None, stage=None,
                          translation_estimate=None, compensation=None, candidate_scores=scores,
                          candidate_errors=errors, ranking_temperature=torch.tensor(temperature, requires_grad=True))

    def test_lower_when_the_nearest_candidate_ranks_first(self):
        inf = float("inf")
        errors = torch.tensor([[3.0, 90.0, 180.0, inf]])
        right = ranking_loss(self._output(torch.tensor([[0.3, 0.1, 0.05, -inf]]), errors), 15.0)
        wrong = ranking_loss(self._output(torch.tensor([[0.05, 0.3, 0.1, -inf]]), errors), 15.0)
        assert 0 <= right.item() < 0.01 < wrong.item()

    def test_zero_without_a_near_candidate_and_finite_gradients_with_dropped_ones(self):
        inf = float("inf")
        scores = torch.tensor([[0.3, 0.1, -inf], [0.2, 0.25, -inf]], requires_grad=True)
        output = self._output(scores, torch.tensor([[40.0, 90.0, inf], [2.0, 50.0, inf]]))
        loss = ranking_loss(output, 15.0)
        assert loss[0] == 0 and loss[1] > 0
        loss.sum().backward()
        # Before: -inf / temperature gave the temperature a NaN gradient, and the next step NaN weights.
        assert torch.isfinite(output.ranking_temperature.grad)
        assert torch.isfinite(scores.grad).all() and (scores.grad[0] == 0).all()
