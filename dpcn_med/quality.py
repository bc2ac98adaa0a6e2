"""How likely a registration is right: a logistic model of the result's own numbers.

The model is fitted on the benchmarks' registrations, successes and failures alike, and deliberate failures where no
right answer exists (``benchmarks/quality_fit.py``; data, calibration and choice of inputs:
docs/benchmarks/quality.md), and ships with the package as ``quality_model.json``. Its inputs are numbers every
refined registration already has (:func:`signals`); it adds no image work.

Convention:
    ``probability`` is the modelled chance that the result is a success (a TRE under 2 mm). A result is flagged
    (the command line's exit code 3) when it is below the model's ``threshold``. Without refinement there is no final
    similarity to judge, and :func:`success_probability` returns ``None``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from dpcn_med.errors import InputError
from dpcn_med.io import write_text

MODEL_FILE = "quality_model.json"
"""The shipped model, inside the package."""

SIGNAL_NAMES = ("log_confidence", "information_share", "log_information_share", "overlap", "candidate_lead")
"""What :func:`signals` measures; a model uses some of them (:attr:`QualityModel.names`)."""


def signals(confidence: float, overlap: float, metric: dict[str, float | None], fixed_entropy: float | None,
            candidate_metrics: list[float | None]) -> dict[str, float] | None:
    """The model's inputs from a registration's numbers (those of :class:`dpcn_med.RegistrationResult`), or ``None``
    without a final similarity (no refinement, or no overlap at the result):

    - ``log_confidence``: ``log10`` of the solver's confidence in the start kept, clamped to ``[1e-4, 1]``;
    - ``information_share``: Mattes mutual information at the result over the fixed samples' entropy, in ``[0, 1]``:
      how much of the fixed image's intensity information the moving image explains there, on the pair's own scale;
    - ``log_information_share``: its ``log10``, clamped below at ``-3`` (right results span 0.17-0.7 from CT-MR to
      the same modality, wrong ones 0.02-0.13);
    - ``overlap``: the share of the fixed foreground mapped inside the moving field of view;
    - ``candidate_lead``: how far the best start led the median of the others after the coarsest level, relative to
      the best (0 where there was one start): a pose that wins clearly, against one among equals.
    """
    final = metric.get("refined") if metric.get("refined") is not None else metric.get("dpc")
    if final is None or not fixed_entropy or not math.isfinite(final):
        return None
    scored = sorted(value for value in candidate_metrics if value is not None and math.isfinite(value))
    lead = 0.0
    if len(scored) > 1 and scored[0] < 0:
        lead = float(np.clip((float(np.median(scored[1:])) - scored[0]) / -scored[0], 0.0, 1.0))
    share = float(np.clip(-final / fixed_entropy, 0.0, 1.0))
    return {"log_confidence": math.log10(min(max(confidence, 1e-4), 1.0)) if math.isfinite(confidence) else -4.0,
            "information_share": share, "log_information_share": math.log10(max(share, 1e-3)),
            "overlap": float(np.clip(overlap, 0.0, 1.0)),
            "candidate_lead": lead}


@dataclass(frozen=True)
class QualityModel:
    """A logistic model over some of :data:`SIGNAL_NAMES` (``names``): ``p = 1 / (1 + exp(-(intercept +
    coefficients . z)))`` with ``z`` each signal standardised by ``mean`` and ``scale``.

    Attributes:
        threshold: results below this probability are flagged.
        solver_model: the registration model the fit's data came from, as a request names it (``"none"`` for the
            learning-free solver, else the weights' SHA-256; :func:`dpcn_med.outputs.model_identity`): the test suite
            fails when the default registration model changes without a refit.
        fitted: how the model was made: the command, the data, the date, the counts.
    """

    names: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coefficients: tuple[float, ...]
    intercept: float
    threshold: float
    solver_model: str = "none"
    fitted: dict = field(default_factory=dict)

    def probability(self, values: dict[str, float]) -> float:
        """The modelled probability of success of one registration's :func:`signals`."""
        z = (np.array([values[name] for name in self.names]) - np.array(self.mean)) / np.array(self.scale)
        return float(1.0 / (1.0 + np.exp(-(self.intercept + float(np.dot(self.coefficients, z))))))

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (atomically)."""
        write_text(json.dumps(asdict(self), indent=2) + "\n", Path(path))

    @classmethod
    def load(cls, path: str | Path | None = None) -> QualityModel:
        """The model at ``path``, or the shipped one.

        Raises:
            InputError: a file that is missing, not JSON, or not a model of :data:`SIGNAL_NAMES`' inputs.
        """
        try:
            text = (Path(path).read_text() if path is not None
                    else resources.files("dpcn_med").joinpath(MODEL_FILE).read_text())
            data = json.loads(text)
            model = cls(**{**data, **{key: tuple(data[key]) for key in ("names", "mean", "scale", "coefficients")}})
        except (OSError, ValueError, TypeError, KeyError) as error:
            raise InputError(f"{path or MODEL_FILE}: not a quality model ({error})") from None
        if set(model.names) - set(SIGNAL_NAMES) or not (len(model.names) == len(model.mean) == len(model.scale)
                                                         == len(model.coefficients)):
            raise InputError(f"{path or MODEL_FILE}: a quality model's inputs must be among {SIGNAL_NAMES}, one "
                             "mean, scale and coefficient each")
        return model


def fit(rows: list[dict[str, float]], success: list[bool], names: tuple[str, ...], penalty: float = 0.1
        ) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], float]:
    """Logistic regression of ``success`` on the signals ``names`` of ``rows``, with a ridge ``penalty`` on the
    standardised coefficients (separable data would otherwise drive them to infinity and every probability to 0 or
    1): ``(mean, scale, coefficients, intercept)``. Written with scipy's L-BFGS rather than taking scikit-learn as a
    dependency for one model of a handful of inputs.

    Raises:
        InputError: fewer than two rows, or only successes or only failures.
    """
    from scipy.optimize import minimize

    if len(rows) < 2 or all(success) or not any(success):
        raise InputError("fitting a quality model needs both successes and failures")
    x = np.array([[row[name] for name in names] for row in rows], dtype=float)
    y = np.asarray(success, dtype=float)
    mean, scale = x.mean(0), x.std(0)
    scale[scale == 0] = 1.0
    z = (x - mean) / scale

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        logits = theta[0] + z @ theta[1:]
        # log(1 + e^l) - y l, and its gradient, without overflow
        value = np.sum(np.logaddexp(0.0, logits) - y * logits) + 0.5 * penalty * np.sum(theta[1:] ** 2)
        residual = 1.0 / (1.0 + np.exp(-logits)) - y
        gradient = np.concatenate([[residual.sum()], z.T @ residual + penalty * theta[1:]])
        return float(value), gradient

    theta = minimize(loss, np.zeros(len(names) + 1), jac=True, method="L-BFGS-B").x
    return tuple(mean.tolist()), tuple(scale.tolist()), tuple(theta[1:].tolist()), float(theta[0])


_SHIPPED: QualityModel | None = None


def shipped_model() -> QualityModel:
    """The model that ships with the package, read once."""
    global _SHIPPED
    if _SHIPPED is None:
        _SHIPPED = QualityModel.load()
    return _SHIPPED
