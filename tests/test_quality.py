"""dpcn_med.quality: the signals of a registration, the logistic fit, the shipped model and its guard."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dpcn_med.errors import InputError
from dpcn_med.outputs import RegistrationSettings, model_identity
from dpcn_med.quality import SIGNAL_NAMES, QualityModel, fit, shipped_model, signals


class TestSignals:
    def test_each_signal_from_a_registrations_numbers(self):
        values = signals(0.01, 0.9, {"refined": -0.6, "dpc": -0.4}, 3.0, [-0.5, -0.1, -0.3, None])
        assert values == pytest.approx({"log_confidence": -2.0, "information_share": 0.2,
                                        "log_information_share": np.log10(0.2), "overlap": 0.9, "candidate_lead": 0.6})
        assert list(values) == list(SIGNAL_NAMES)

    def test_limits(self):
        # A confidence of 0 or NaN is the floor; one start leads nobody; a share is at most 1.
        values = signals(0.0, 1.2, {"refined": None, "dpc": -5.0}, 2.0, [-0.5])
        assert values == {"log_confidence": -4.0, "information_share": 1.0, "log_information_share": 0.0,
                          "overlap": 1.0, "candidate_lead": 0.0}
        assert signals(0.5, 1.0, {"refined": 0.0}, 2.0, [])["log_information_share"] == -3.0
        assert signals(float("nan"), 1.0, {"refined": -1.0}, 2.0, [])["log_confidence"] == -4.0

    @pytest.mark.parametrize("metric, entropy", [({"refined": None, "dpc": None}, 3.0), ({"refined": -1.0}, None),
                                                 ({"refined": float("inf")}, 3.0)])
    def test_nothing_to_judge_without_a_final_similarity(self, metric, entropy):
        assert signals(0.5, 1.0, metric, entropy, []) is None


def _separable(rng: np.random.Generator, count: int) -> tuple[list[dict], list[bool]]:
    good = rng.random(count) < 0.6
    share = np.where(good, rng.uniform(0.15, 0.7, count), rng.uniform(0.0, 0.12, count))
    rows = [{"log_confidence": float(rng.uniform(-4, 0)), "information_share": float(s),
             "log_information_share": float(np.log10(s)), "overlap": float(rng.uniform(0.8, 1)),
             "candidate_lead": float(rng.uniform(0, 1))} for s in share]
    return rows, good.tolist()


class TestFit:
    def test_learns_the_signal_that_separates(self):
        rows, good = _separable(np.random.default_rng(0), 200)
        mean, scale, coefficients, intercept = fit(rows, good, SIGNAL_NAMES)
        model = QualityModel(SIGNAL_NAMES, mean, scale, coefficients, intercept, threshold=0.5)
        weights = dict(zip(SIGNAL_NAMES, coefficients))
        assert max(weights, key=lambda name: abs(weights[name])) in ("information_share", "log_information_share")
        assert weights["information_share"] > 0 and weights["log_information_share"] > 0
        held_out, truth = _separable(np.random.default_rng(1), 200)
        predicted = [model.probability(row) >= 0.5 for row in held_out]
        assert np.mean(np.equal(predicted, truth)) > 0.95

    def test_needs_both_outcomes(self):
        rows, _ = _separable(np.random.default_rng(0), 10)
        with pytest.raises(InputError, match="both successes and failures"):
            fit(rows, [True] * 10, SIGNAL_NAMES)


class TestShippedModel:
    def test_loads_and_has_a_threshold_fitted_on_data(self):
        model = shipped_model()
        assert set(model.names) <= set(SIGNAL_NAMES) and 0 < model.threshold < 1
        assert model.fitted["registrations"] >= 80 and 0 < model.fitted["successes"] < model.fitted["registrations"]
        assert "benchmarks/quality_fit.py" in model.fitted["by"]

    def test_was_fitted_for_the_default_registration_model(self):
        """Refit (benchmarks/quality_fit.py, docs/benchmarks/quality.md) whenever the default model changes."""
        identity = model_identity(RegistrationSettings().model)
        expected = identity if isinstance(identity, str) else identity.get("weights_sha256")
        assert shipped_model().solver_model == expected

    def test_a_clear_success_and_a_clear_failure(self):
        model = shipped_model()
        success = signals(1.0, 1.0, {"refined": -1.5}, 3.0, [-1.4, -0.3, -0.2])
        failure = signals(0.0005, 0.8, {"refined": -0.08}, 3.0, [-0.06, -0.05, -0.055])
        assert model.probability(success) > model.threshold > model.probability(failure)

    def test_round_trip_and_bad_files(self, tmp_path):
        path = tmp_path / "model.json"
        shipped_model().save(path)
        assert QualityModel.load(path) == shipped_model()
        (tmp_path / "text.json").write_text("not json")
        with pytest.raises(InputError, match="text.json: not a quality model"):
            QualityModel.load(tmp_path / "text.json")
        data = json.loads(path.read_text())
        data["names"] = ["log_confidence", "age"]
        (tmp_path / "other.json").write_text(json.dumps(data))
        with pytest.raises(InputError, match="other.json: a quality model's inputs"):
            QualityModel.load(tmp_path / "other.json")
        assert math.isfinite(shipped_model().intercept)
