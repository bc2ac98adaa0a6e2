"""The DPCN++ network: four feature extractors around the differentiable solver (DESIGN 3).

``{fixed, moving} x {rotation-scale stage, translation stage}``: the rotation-scale features go through the solver's
spectrum, sphere, SO(3) and log-radius stages; the translation features are computed on the fixed volume and on the
moving volume compensated by ``scale * rotation`` (the ground truth plus noise while training, so the translation
networks learn on well-compensated pairs from the first step; the estimate at inference), then phase-correlated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace

import torch
from torch import Tensor, nn

from dpcn_med import __version__
from dpcn_med.arguments import check_flag, check_integer, check_real, check_sequence, shown
from dpcn_med.errors import InputError
from dpcn_med.geometry import axis_angle_to_matrix, warp
from dpcn_med.models.features import FeatureExtractor
from dpcn_med.preprocess import MODALITIES as _INPUT_MODALITIES
from dpcn_med.preprocess import Preprocessing
from dpcn_med.solver import LossWeights, PoseTarget, SolverConfig, SolveResult, StageTemperatures, Temperatures, solve
from dpcn_med.solver import pose_loss as solver_pose_loss
from dpcn_med.solver.config import DEFAULT_BANDWIDTH
from dpcn_med.solver.solve3d import candidate_scores
from dpcn_med.solver.translation import TranslationEstimate, phase_translation
from dpcn_med.solver.validation import check_grid_bandwidth, check_mode

MODALITIES = tuple(modality for modality in _INPUT_MODALITIES if modality != "auto")
"""What a model is trained for: :data:`dpcn_med.preprocess.MODALITIES` but ``"auto"``."""
PER_CALL_SOLVER_FIELDS = ("bandwidth", "refine", "alternatives", "profile")
""":class:`SolverConfig` fields a model does not record: the bandwidth is the model's own, the rest each call sets."""
REQUIRED_KEYS = ("bandwidth", "channels", "residual_units", "modalities", "share_weights", "mode", "preprocessing")
"""Keys a saved model config must hold: they define the network and its grids, so a default would describe another
model than the weights (``solver`` may be absent: a config saved before it existed gets today's defaults)."""
SOLVER_FIELDS_ADDED = {"extra_degree_two_weights": (), "entropy_bins": 0, "extra_entropy_bins": (),
                       "cooccurrence_bins": 0}
""":class:`SolverConfig` fields added after models began recording their solver, each with the value a model saved
without it ran with: a saved model keeps registering as it was trained."""
MAX_CHANNELS = 1024
"""Most channels of a UNet level (why this bound: docs/design_notes/models.md)."""
MAX_RESIDUAL_UNITS = 8
"""Most residual units per level (why this bound: docs/design_notes/models.md)."""


def _tuples(value):
    """JSON's lists back into the dataclasses' (nested) tuples."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _mapping(cls: type, values: object, name: str) -> Mapping:
    """``values`` if it is a mapping (of ``cls``'s fields, the message says; a JSON list arrives as a tuple)."""
    if not isinstance(values, Mapping):
        raise InputError(f"{name} is {shown(values)}; expected a mapping of {cls.__name__} settings (a JSON object)")
    return values


def _settings(cls: type, values: dict, name: str):
    """``cls(**values)``; a value that is not a mapping, or unknown keys, are refused, the message naming the config
    key ``name``."""
    unknown = set(_mapping(cls, values, name)) - {f.name for f in fields(cls)}
    if unknown:
        raise InputError(f"{name} has unknown keys {sorted(unknown)}")
    return cls(**{k: _tuples(v) for k, v in values.items()})


def _recorded(settings, exclude: tuple[str, ...] = ()) -> dict:
    """A settings dataclass as the dict a :class:`ModelConfig` saves, without the ``exclude`` fields."""
    return {k: v for k, v in asdict(settings).items() if k not in exclude}


@dataclass(frozen=True)
class ModelConfig:
    """What a model is; saved beside its weights (:mod:`dpcn_med.models.weights`).

    Attributes:
        bandwidth: solver bandwidth ``B``; inputs are ``(2B)^3`` grids.
        channels: UNet channels per level (``len - 1`` downsamplings, so ``2B`` must be divisible by
            ``2 ** (len - 1)``).
        residual_units: MONAI's ``num_res_units`` per level.
        modalities: ``(fixed, moving)`` modalities the networks were trained for, each ``ct``, ``mr`` or ``us``.
        share_weights: one extractor per stage for both inputs (for same-modality pairs).
        mode: ``similarity`` (7 DoF) or ``rigid`` (6 DoF).
        compensation_noise_degrees: training only: the rotation compensating the moving volume before the
            translation stage is the truth turned by an angle of this standard deviation about a random axis...
        compensation_noise_scale: ...and its scale the truth times ``exp(N(0, this))``.
        temperatures: initial softmax temperatures ``(rotation, scale, translation)`` (learned afterwards).
        preprocessing: the :class:`dpcn_med.preprocess.Preprocessing` fields the training grids are made with, and
            so the ones :func:`dpcn_med.register` uses with this model (the defaults when it was created).
        solver: the :class:`dpcn_med.solver.SolverConfig` fields the model trains and registers with (the defaults
            when it was created), so that a later change of the learning-free defaults leaves a trained model as it
            was; all but :data:`PER_CALL_SOLVER_FIELDS`. A config saved before this key existed gets today's defaults.
        version: dpcn_med version that made the model.
    """

    bandwidth: int = DEFAULT_BANDWIDTH
    channels: tuple[int, ...] = (8, 16, 32, 64)
    residual_units: int = 1
    modalities: tuple[str, str] = ("ct", "mr")
    share_weights: bool = False
    mode: str = "similarity"
    compensation_noise_degrees: float = 2.0
    compensation_noise_scale: float = 0.02
    temperatures: tuple[float, float, float] = (StageTemperatures.rotation, StageTemperatures.scale,
                                                StageTemperatures.translation)
    preprocessing: dict = field(default_factory=lambda: _recorded(Preprocessing()))
    solver: dict = field(default_factory=lambda: _recorded(SolverConfig(), PER_CALL_SOLVER_FIELDS))
    version: str = __version__

    def __post_init__(self) -> None:
        check_grid_bandwidth(self.bandwidth)
        check_mode(self.mode)
        if not all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= MAX_CHANNELS for c in self.channels):
            raise InputError(f"channels {self.channels!r}: expected positive integers <= {MAX_CHANNELS}")
        check_integer("residual_units", self.residual_units, minimum=0, maximum=MAX_RESIDUAL_UNITS)
        check_flag("share_weights", self.share_weights)
        if not isinstance(self.version, str):
            raise InputError(f"version is {shown(self.version)}; expected a string (the dpcn_med version)")
        if any(m not in MODALITIES for m in self.modalities) or len(self.modalities) != 2:
            raise InputError(f"modalities {self.modalities!r}: expected two of {', '.join(MODALITIES)}")
        downsampling = 2 ** (len(self.channels) - 1)
        if len(self.channels) < 2 or (2 * self.bandwidth) % downsampling or 2 * self.bandwidth < 2 * downsampling:
            # one voxel at the deepest level: MONAI's instance norm fails ("more than 1 spatial element")
            raise InputError(f"channels {self.channels!r}: need at least two levels, and the grid size "
                             f"{2 * self.bandwidth} must be divisible by 2^{len(self.channels) - 1} and leave at "
                             "least 2 voxels at the deepest level")
        check_real("compensation_noise_degrees", self.compensation_noise_degrees, minimum=0.0)
        check_real("compensation_noise_scale", self.compensation_noise_scale, minimum=0.0)
        for index, temperature in enumerate(check_sequence("temperatures", self.temperatures, length=3)):
            check_real(f"temperatures[{index}]", temperature, minimum=0.0, above=True)
        # Complete, so that the saved config says every setting; JSON lists become the dataclasses' tuples again.
        object.__setattr__(self, "preprocessing", _recorded(self.grid_preprocessing()))
        object.__setattr__(self, "solver", _recorded(self.solver_config(), PER_CALL_SOLVER_FIELDS))

    def grid_preprocessing(self) -> Preprocessing:
        """:attr:`preprocessing` as a :class:`dpcn_med.preprocess.Preprocessing` (missing fields at their
        defaults)."""
        return _settings(Preprocessing, self.preprocessing, "preprocessing")

    def solver_config(self) -> SolverConfig:
        """:attr:`solver` as a :class:`dpcn_med.solver.SolverConfig` at the model's bandwidth (missing fields at
        their defaults)."""
        per_call = sorted(set(_mapping(SolverConfig, self.solver, "solver")) & set(PER_CALL_SOLVER_FIELDS))
        if per_call:
            raise InputError(f"solver sets {per_call}: a model does not record {', '.join(PER_CALL_SOLVER_FIELDS)} "
                             "(the bandwidth is the model's own, the rest each call sets)")
        return replace(_settings(SolverConfig, self.solver, "solver"), bandwidth=self.bandwidth)

    def to_json(self) -> dict:
        """Plain JSON types (tuples become lists)."""
        return asdict(self)

    @classmethod
    def from_json(cls, values: dict) -> ModelConfig:
        """Inverse of :meth:`to_json`; unknown keys are refused (a file from another program or version), and so
        are missing :data:`REQUIRED_KEYS`; a recorded solver without a field of :data:`SOLVER_FIELDS_ADDED` gets
        the value it ran with."""
        missing = [key for key in REQUIRED_KEYS if key not in values]
        if missing:
            raise InputError(f"model config lacks {missing}; a saved model must state {', '.join(REQUIRED_KEYS)}")
        if isinstance(values.get("solver"), dict):  # saved before a field existed: the value it ran with
            values = {**values, "solver": {**SOLVER_FIELDS_ADDED, **values["solver"]}}
        return _settings(cls, values, "model config")


@dataclass
class DPCNOutput:
    """The pose ``fixed(p) ~ moving(scale * rotation @ p + translation)`` and what the losses need.

    Attributes:
        rotation: ``(B, 3, 3)``.
        scale: ``(B,)``.
        translation: ``(B, 3)`` voxels ``(x, y, z)``.
        confidence: ``(B,)`` softmax mass of the translation peak.
        stage: the solver's rotation-scale result on the rotation-scale features.
        translation_estimate: the translation stage on the translation features.
        compensation: ``(B, 3, 3)`` the ``scale * rotation`` the moving volume was compensated by before it.
        candidate_scores: ``(B, K)`` training with a target only: the translation peak of each of the solver's
            ranked candidates on the translation features, differentiable (``-inf``: a candidate the solver dropped).
        candidate_errors: ``(B, K)`` their angles to the true rotation, degrees (``inf`` where dropped).
        ranking_temperature: the softmax temperature of the ranking loss over ``candidate_scores``.
    """

    rotation: Tensor
    scale: Tensor
    translation: Tensor
    confidence: Tensor
    stage: SolveResult
    translation_estimate: TranslationEstimate
    compensation: Tensor
    candidate_scores: Tensor | None = None
    candidate_errors: Tensor | None = None
    ranking_temperature: Tensor | None = None


RANKING_TEMPERATURE = 0.01
"""Initial softmax temperature of the candidate ranking loss, in units of phase-correlation peak height (why this
value: docs/design_notes/models.md)."""


class DPCN(nn.Module):
    """DPCN++ for one pair of modalities; ``model(fixed, moving)`` registers ``(B, 1, 2B, 2B, 2B)`` grids."""

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ModelConfig()

        def extractor() -> FeatureExtractor:
            return FeatureExtractor(config.channels, config.residual_units)

        self.rotation_fixed, self.translation_fixed = extractor(), extractor()
        if config.share_weights:
            self.rotation_moving, self.translation_moving = self.rotation_fixed, self.translation_fixed
        else:
            self.rotation_moving, self.translation_moving = extractor(), extractor()
        self.temperatures = Temperatures(StageTemperatures(*config.temperatures))
        # Only the ranking loss reads it (an arg-max does not depend on it), so it is a model parameter, not a stage
        # temperature the solver takes.
        self.ranking_temperature = nn.Parameter(torch.tensor(math.log(math.expm1(RANKING_TEMPERATURE))))
        self.solver = config.solver_config()

    def forward(self, fixed: Tensor, moving: Tensor, target: PoseTarget | None = None,
                generator: torch.Generator | None = None, mode: str | None = None,
                alternatives: int = 0, amp: bool = False) -> DPCNOutput:
        """Register ``moving`` onto ``fixed``.

        Args:
            fixed, moving: ``(B, 1, 2B, 2B, 2B)`` canonical grids, normalised intensities, floating point (cast to
                the parameters' dtype: numpy's float64 becomes float32).
            target: the true pose; in training mode it (plus noise) compensates the translation stage's input.
            generator: for the compensation noise (reproducible training); drawn on its device.
            mode: ``rigid`` or ``similarity``; defaults to the mode the model was trained in.
            alternatives: runner-up candidates for ``stage.alternatives`` (the solver's option; their translations
                come from the rotation-stage features).
            amp: run the feature extractors under bfloat16 autocast (training's mixed precision).

        Returns:
            A :class:`DPCNOutput`. In training mode every estimate is a soft arg-max (differentiable); in eval mode
            the solver's arg-max with sub-grid refinement.

        Convention:
            Only the extractors may run in reduced precision: their features are cast back to the parameters' dtype
            and the solver runs with autocast off, the caller's included (why: docs/design_notes/models.md).

        Raises:
            InputError: grids that are not tensors, not floating point, or not ``(B, 1, 2B, 2B, 2B)`` pairs.
        """
        fixed, moving = self._grids(fixed, moving)
        mode = check_mode(mode or self.config.mode)
        with torch.autocast(fixed.device.type, enabled=False):
            temperatures = self.temperatures()
            # The candidates are ranked by their translation peak on the translation features, in training as at
            # inference, so that the ranking loss trains the choice that registration makes.
            fixed_translation = self._features("translation_fixed", fixed, amp)
            moving_translation = self._features("translation_moving", moving, amp)
            truth = self.training and target is not None
            stage = solve(self._features("rotation_fixed", fixed, amp), self._features("rotation_moving", moving, amp),
                          mode, config=self.solver, temperatures=temperatures, refine=not self.training,
                          alternatives=alternatives, score_volumes=(fixed_translation, moving_translation),
                          scale_rotation=target.rotation if truth else None)
            if truth:
                compensation = self._noisy(target, generator, rigid=mode == "rigid").to(fixed.dtype)
            else:
                compensation = (stage.scale[:, None, None] * stage.rotation).detach()
            estimate = self._translation_stage(fixed_translation, self._features(
                "translation_moving", warp(moving, compensation), amp), temperatures.translation)
            translation = (compensation @ estimate.shift[..., None])[..., 0]
            scores = errors = None
            if truth:
                scores, errors = self._candidate_scores(stage, fixed_translation, moving_translation, target)
        return DPCNOutput(rotation=stage.rotation, scale=stage.scale, translation=translation,
                          confidence=estimate.peak.mass, stage=stage, translation_estimate=estimate,
                          compensation=compensation, candidate_scores=scores, candidate_errors=errors,
                          ranking_temperature=torch.nn.functional.softplus(self.ranking_temperature))

    def _candidate_scores(self, stage: SolveResult, fixed: Tensor, moving: Tensor, target: PoseTarget
                          ) -> tuple[Tensor, Tensor]:
        """The solver's ranked candidates scored again with gradients, on the translation features ``fixed`` and
        ``moving`` ``(B, 1, N, N, N)`` at the solver's ``candidate_size`` (as it scores them all), and their errors
        in degrees: ``(B, K)`` each, ``-inf`` and ``inf`` where the solver dropped a candidate."""
        ranking = stage.ranking
        dropped = ranking.score == float("-inf")
        linear = (ranking.scale[..., None, None] * ranking.rotation).detach()
        scores = candidate_scores(fixed[:, 0], moving[:, 0], linear, self.solver.candidate_size, self.solver.taper,
                                  keep=~dropped)
        return scores, ranking.errors(target.rotation).to(scores.dtype)

    def translation_peak(self, fixed: Tensor, moving: Tensor, temperature: Tensor | None = None, amp: bool = False
                         ) -> TranslationEstimate:
        """The translation stage: phase correlation of the translation features of ``fixed`` and ``moving``
        ``(B, 1, 2B, 2B, 2B)``, ``moving`` already compensated for rotation and scale (or as stored). The
        arg-max is refined in eval mode, a soft arg-max in training mode; ``temperature`` defaults to the learned
        one; ``amp`` and the grids' dtypes as in :meth:`forward`."""
        fixed, moving = self._grids(fixed, moving)
        with torch.autocast(fixed.device.type, enabled=False):
            temperature = self.temperatures().translation if temperature is None else temperature
            return self._translation_stage(self._features("translation_fixed", fixed, amp),
                                           self._features("translation_moving", moving, amp), temperature)

    def _translation_stage(self, fixed: Tensor, moving: Tensor, temperature: Tensor) -> TranslationEstimate:
        """Phase correlation of translation features ``(B, 1, 2B, 2B, 2B)``: refined arg-max in eval mode, soft
        arg-max in training mode."""
        return phase_translation(fixed[:, 0], moving[:, 0], temperature, dim=3, taper=self.solver.taper,
                                 refine=not self.training, upsample=self.solver.upsample)

    def _grids(self, fixed: Tensor, moving: Tensor) -> tuple[Tensor, Tensor]:
        """``fixed`` and ``moving`` checked as ``(B, 1, 2B, 2B, 2B)`` pairs, in the parameters' dtype."""
        size = 2 * self.config.bandwidth
        expected = f"this model takes (B, 1, {size}, {size}, {size}) pairs (bandwidth {self.config.bandwidth})"
        for name, volume in (("fixed", fixed), ("moving", moving)):
            if not isinstance(volume, Tensor):
                raise InputError(f"{name} is {shown(volume)}; {expected} of floating-point tensors")
            if not volume.is_floating_point():
                raise InputError(f"{name} is {str(volume.dtype).removeprefix('torch.')}; {expected} of "
                                 "floating-point grids (e.g. volume.float())")
        if fixed.ndim != 5 or fixed.shape[1:] != (1, size, size, size) or moving.shape != fixed.shape:
            raise InputError(f"grids {tuple(fixed.shape)} and {tuple(moving.shape)}: {expected}")
        dtype = next(self.parameters()).dtype
        return fixed.to(dtype), moving.to(dtype)

    def _features(self, extractor: str, volume: Tensor, amp: bool = False) -> Tensor:
        """``(B, 1, N, N, N)`` features of ``volume`` by the extractor named ``extractor``, in ``volume``'s dtype
        (computed under bfloat16 autocast when ``amp``).

        Raises:
            InputError: in eval mode, features holding NaN or Inf (training skips the check; why:
                docs/design_notes/models.md).
        """
        with torch.autocast(volume.device.type, dtype=torch.bfloat16, enabled=amp):
            features = getattr(self, extractor)(volume)
        features = features.to(volume.dtype)
        if not self.training and not torch.isfinite(features).all():
            raise InputError(f"the {extractor} features hold NaN or Inf values (the weights overflow float32 on "
                             "this input); the model is unusable")
        return features

    def _noisy(self, target: PoseTarget, generator: torch.Generator | None, rigid: bool) -> Tensor:
        """``(B, 3, 3)``: the true ``scale * rotation``, turned and scaled a little at random."""
        batch = target.rotation.shape[0]
        # Drawn on the generator's device (the training loop's is on the data's, and a CUDA generator cannot draw on
        # the CPU), then moved.
        options = {"generator": generator, "device": "cpu" if generator is None else generator.device,
                   "dtype": torch.float64}
        axis = torch.randn(batch, 3, **options)
        angle = torch.randn(batch, 1, **options) * math.radians(self.config.compensation_noise_degrees)
        turn = axis_angle_to_matrix(axis / axis.norm(dim=-1, keepdim=True) * angle).to(target.rotation.device)
        scale = target.scale.double() * torch.exp(torch.randn(batch, **options).to(target.scale.device)
                                                  * self.config.compensation_noise_scale)
        if rigid:
            scale = torch.ones_like(scale)
        return scale[:, None, None] * (turn @ target.rotation.double())


def ranking_loss(output: DPCNOutput, max_degrees: float) -> Tensor:
    """Cross-entropy of the softmax over :attr:`DPCNOutput.candidate_scores` (at its ``ranking_temperature``) with
    the candidate nearest the truth as the target: ``(B,)``, zero for a pair whose nearest candidate lies
    ``max_degrees`` or more from the truth (no right answer among them to rank first)."""
    nearest = output.candidate_errors.min(-1)
    dropped = output.candidate_scores == float("-inf")
    # Masked after the division: -inf / temperature has a NaN gradient with respect to the temperature.
    logits = (output.candidate_scores.masked_fill(dropped, 0.0) / output.ranking_temperature).masked_fill(
        dropped, float("-inf"))
    loss = -torch.log_softmax(logits, -1).gather(1, nearest.indices[:, None])[:, 0]
    return torch.where(nearest.values < max_degrees, loss, torch.zeros_like(loss))


def pose_loss(output: DPCNOutput, target: PoseTarget, weights: LossWeights | None = None) -> dict[str, Tensor]:
    """The six DPCN++ terms (:func:`dpcn_med.solver.pose_loss`) with the translation terms on the model's own
    translation stage, and ``"candidate_ranking"`` (:func:`ranking_loss`, batch mean; zero outside training with a
    target); ``"total"`` is their weighted sum."""
    weights = weights or LossWeights()
    terms = solver_pose_loss(output.stage, target, weights, translation=output.translation_estimate,
                             compensation=output.compensation)
    if output.candidate_scores is None:
        terms["candidate_ranking"] = terms["total"].new_zeros(())
    else:
        terms["candidate_ranking"] = ranking_loss(output, weights.candidate_degrees).mean()
        terms["total"] = terms["total"] + weights.candidate_ranking * terms["candidate_ranking"]
    return terms
