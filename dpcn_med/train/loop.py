"""The training loop: synthetic pairs on the device, AdamW, warm-up and cosine decay, validation, checkpoints.

Single process, or one process per device under ``torchrun`` with DistributedDataParallel (each rank draws its own
pairs; rank 0 validates, logs and writes). Everything a run writes goes to ``config.output``:

* ``checkpoint.safetensors`` + ``checkpoint.json``: weights and optimiser state, the step (in both), the config
  (resumed from when ``config.resume``, if the config's
  :data:`~dpcn_med.train.checkpoint.MUST_MATCH_ON_RESUME` settings are the checkpoint's);
* ``log.csv``: a row per logged step (losses, rate, pairs per second) and per validation (success, median errors);
* ``training.png``: the losses and the validation success against steps;
* ``model.safetensors`` + ``model.json``: the final model with its training record (:func:`dpcn_med.models.save_model`).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from dpcn_med import io
from dpcn_med.errors import InputError
from dpcn_med.evaluation import SUCCESS_DEGREES, SUCCESS_VOXELS
from dpcn_med.geometry import geodesic_distance
from dpcn_med.models import DPCN, DPCNOutput, pose_loss, save_model
from dpcn_med.solver import PoseTarget, SolveResult
from dpcn_med.train import distributed
from dpcn_med.train.checkpoint import load_checkpoint, save_checkpoint
from dpcn_med.train.config import TrainConfig
from dpcn_med.train.data import sample_pairs, validation_set, volume_bank
from dpcn_med.train.folders import FolderPairs, collate_pairs, derived_seed
from dpcn_med.train.pretrain import dense_loss, pretrained_extractors, set_pretrained_gains

LOSS_TERMS = ("total", "rotation_kl", "rotation_l1", "scale_kl", "scale_l1", "translation_kl", "translation_l1",
              "candidate_ranking", "dense_ncc", "pose_contrast")
CANDIDATE_ERRORS = ("chosen_error_deg", "best_candidate_error_deg")
"""Logged with the training terms (batch medians): the rotation error of the candidate the model chose, and of the
candidate nearest the truth among all it ranked: the choice's error against the best it could have made."""
MAX_SKIPPED_IN_A_ROW = 20
"""Steps in a row with non-finite gradients after which training stops: it has diverged, not met one bad pair."""
SCORES = ("success", "rotation_error_deg", "translation_error_vox")
COLUMNS = ("step", "kind", "learning_rate", *LOSS_TERMS, *CANDIDATE_ERRORS, "skipped_steps", "pairs_per_second",
           *SCORES, *(f"real_{name}" for name in SCORES))


def learning_rate(step: int, config: TrainConfig) -> float:
    """Linear warm-up over ``warmup_steps``, then a cosine decay to ``final_fraction`` at ``steps``."""
    settings = config.optimiser
    if step < settings.warmup_steps:
        return settings.learning_rate * (step + 1) / settings.warmup_steps
    progress = (step - settings.warmup_steps) / max(1, settings.steps - settings.warmup_steps)
    cosine = 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))
    return settings.learning_rate * (settings.final_fraction + (1 - settings.final_fraction) * cosine)


def pose_errors(output: DPCNOutput | SolveResult, target: PoseTarget) -> tuple[Tensor, Tensor]:
    """``(B,)`` rotation errors in degrees and ``(B,)`` translation errors in voxels of a model's or the solver's
    result."""
    rotation = torch.rad2deg(geodesic_distance(output.rotation.double(), target.rotation.double()))
    translation = (output.translation.double() - target.translation.double()).norm(dim=-1)
    return rotation, translation


@torch.no_grad()
def evaluate(model: DPCN, pairs: list[tuple[Tensor, Tensor, PoseTarget]]) -> dict[str, float]:
    """Success rate and median errors of ``model`` (eval mode: arg-max with refinement) over ``pairs``."""
    was_training = model.training
    model.eval()
    rotations, translations = [], []
    for fixed, moving, target in pairs:
        rotation, translation = pose_errors(model(fixed, moving), target)
        rotations.append(rotation)
        translations.append(translation)
    model.train(was_training)
    rotation, translation = torch.cat(rotations), torch.cat(translations)
    success = ((rotation < SUCCESS_DEGREES) & (translation < SUCCESS_VOXELS)).double().mean()
    return {"success": success.item(), "rotation_error_deg": rotation.median().item(),
            "translation_error_vox": translation.median().item()}


def pair_stream_seed(seed: int, rank: int, step: int) -> int:
    """The seed of the synthetic pairs a rank draws from ``step`` on: one stream per (seed, rank, start step), so a
    resumed run draws new pairs, not the old ones, nor another rank's (history: docs/design_notes/training.md)."""
    return derived_seed(seed, rank, step)


def _real_pairs(roots: tuple[str, ...], config: TrainConfig, *, crop: tuple[float, float] | None, seed: int
                ) -> torch.utils.data.ConcatDataset | None:
    """The folders' real pairs as one dataset, every pair read and prepared now (kept for the run), or ``None``
    without folders (why now: docs/design_notes/training.md).

    Raises:
        InputError: an unusable pair, before the output folder is made.
    """
    if not roots:
        return None
    # A seed per folder: ConcatDataset hands each its own indices, so with one seed pair i of every folder was cropped
    # alike at every step.
    datasets = [FolderPairs(root, config.model.bandwidth, crop=crop,
                            seed=derived_seed(seed, position),
                            preprocessing=config.model.grid_preprocessing()) for position, root in enumerate(roots)]
    for dataset in datasets:
        for index in range(len(dataset)):
            dataset.grids(index)
    return torch.utils.data.ConcatDataset(datasets)


def _check_output_outside_data(output: Path, config: TrainConfig) -> None:
    """Refuse an output folder inside a folder of pairs: the run's folder would read as a broken pair next time."""
    resolved = os.path.realpath(output)
    for key in ("folders", "validation_folders"):
        for root in getattr(config.data, key):
            folder = os.path.realpath(root)
            if os.path.commonpath([resolved, folder]) == folder:
                raise InputError(f"{output}: is inside data.{key} {root}, where the run's folder would read as a pair "
                                 "folder; choose an output folder outside the data")


def _to(batch: tuple[Tensor, Tensor, PoseTarget], device: torch.device) -> tuple[Tensor, Tensor, PoseTarget]:
    fixed, moving, target = batch
    return fixed.to(device), moving.to(device), PoseTarget(*(t.to(device) for t in (
        target.rotation, target.scale, target.translation)))


def _validation_row(step: int, model: DPCN, synthetic: list, real: list | None) -> dict:
    row = {"step": step, "kind": "validation", **evaluate(model, synthetic)}
    if real is not None:
        row.update({f"real_{name}": value for name, value in evaluate(model, real).items()})
    return row


def plot(rows: list[dict], path: Path) -> None:
    """Training losses (log scale) and validation success against steps, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (losses, success) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    train_rows = [r for r in rows if r["kind"] == "train"]
    for term in LOSS_TERMS:
        values = [(r["step"], r[term]) for r in train_rows if r.get(term, 0) > 0]
        if values:
            losses.plot(*zip(*values), label=term, lw=2 if term == "total" else 1)
    losses.set(xlabel="step", ylabel="loss", yscale="log", title="training loss")
    losses.legend(fontsize=7)
    validation = [r for r in rows if r["kind"] == "validation"]
    if validation:
        success.plot([r["step"] for r in validation], [100 * r["success"] for r in validation], "o-")
    success.set(xlabel="step", ylabel="%", ylim=(0, 100),
                title=f"validation success (< {SUCCESS_DEGREES:g} deg and < {SUCCESS_VOXELS:g} voxels)")
    with io.atomic_output(path) as staged:
        figure.savefig(staged, dpi=110)
    plt.close(figure)


def train(config: TrainConfig) -> tuple[DPCN, dict]:
    """Train a model as ``config`` says (resuming from its checkpoint if there is one).

    Returns:
        ``(model, record)``: the trained (unwrapped) model on its device, in eval mode, and the training record
        saved with it (empty on every rank but 0).
    """
    output = Path(config.output)
    _check_output_outside_data(output, config)
    process = distributed.start(config.device)
    torch.manual_seed(config.seed)  # the same initial weights on every rank
    model = DPCN(config.model).to(process.device).train()
    optimiser = torch.optim.AdamW(model.parameters(), lr=config.optimiser.learning_rate,
                                  weight_decay=config.optimiser.weight_decay)
    step, rows = load_checkpoint(model, optimiser, config)  # first: a checkpoint of another config is refused at once
    run = _prepare(config, process, model, optimiser, step, rows)
    distributed.barrier(process)
    step, started = _steps(run, step)
    record = _finish(run, step, started) if process.main else {}
    distributed.stop(process)
    return model.eval(), record


@dataclass
class _Run:
    """What every step of one :func:`train` call shares.

    Attributes:
        config, process, model, optimiser: the run's.
        network: ``model``, wrapped in DistributedDataParallel when there are several processes.
        generator: the rank's stream of pairs (on the device).
        bank: ``(V, 1, N, N, N)`` base volumes of the synthetic pairs.
        real: the folders' real pairs, or ``None``.
        validation, real_validation: batches of the synthetic and real validation pairs (rank 0; ``None`` elsewhere,
            and ``real_validation`` without validation folders).
        output: the run's folder.
        rows: the log so far (rank 0's).
    """

    config: TrainConfig
    process: distributed.Process
    model: DPCN
    optimiser: torch.optim.Optimizer
    network: torch.nn.Module
    generator: torch.Generator
    bank: Tensor
    real: torch.utils.data.ConcatDataset | None
    validation: list | None
    real_validation: list | None
    output: Path
    rows: list[dict]


def _prepare(config: TrainConfig, process: distributed.Process, model: DPCN, optimiser: torch.optim.Optimizer,
             step: int, rows: list[dict]) -> _Run:
    """The run's data, its wrapped network and its pair stream from ``step``; rank 0 also reads the validation pairs,
    makes the output folder and, on a fresh start, scores the untrained model."""
    output = Path(config.output)
    size = 2 * config.model.bandwidth
    preprocessing = config.model.grid_preprocessing()  # the model records it; register uses the same
    bank = volume_bank(config.data.volumes, size, preprocessing, device=process.device)
    network = model
    if process.distributed:
        network = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[process.device] if process.device.type == "cuda" else None,
            find_unused_parameters=True)  # rigid mode leaves the scale temperature unused
    generator = torch.Generator(device=process.device).manual_seed(pair_stream_seed(config.seed, process.rank, step))
    real = _real_pairs(config.data.folders, config, crop=config.data.folder_crop, seed=config.seed + process.rank)
    validation, real_validation = None, None
    if process.main:
        validation_bank = volume_bank(config.data.validation_volumes, size, preprocessing, device=process.device,
                                      key="data.validation_volumes")
        validation = validation_set(validation_bank, config.data.validation_pairs, config.data.validation_seed,
                                    config.data.pair)
        held_out = _real_pairs(config.data.validation_folders, config, crop=None, seed=0)
        if held_out is not None:
            items = [held_out[i] for i in range(len(held_out))]
            real_validation = [_to(collate_pairs(items[i:i + 16]), process.device) for i in range(0, len(items), 16)]
        output.mkdir(parents=True, exist_ok=True)  # only now: a bad input leaves no empty folder behind
        if step == 0:
            rows.append(_validation_row(0, model, validation, real_validation))
    return _Run(config, process, model, optimiser, network, generator, bank, real, validation, real_validation,
                output, rows)


def _steps(run: _Run, step: int) -> tuple[int, float]:
    """Train from ``step`` to ``config.optimiser.steps``, logging, validating and checkpointing on the way:
    ``(the last step, the perf_counter at the start)``.

    Raises:
        InputError: :data:`MAX_SKIPPED_IN_A_ROW` steps in a row with non-finite gradients.
    """
    config, process = run.config, run.process
    amp = config.optimiser.amp and process.device.type == "cuda"
    from tqdm import tqdm

    # Closed on an error too: an open bar wrote its last line after the error's message, at the interpreter's exit.
    with tqdm(total=config.optimiser.steps, initial=step, disable=not process.main, desc="training",
              dynamic_ncols=True) as bar:
        started, pairs_since, clock = time.perf_counter(), 0, time.perf_counter()
        skipped, skipped_in_a_row = 0, 0
        while step < config.optimiser.steps:
            rate = learning_rate(step, config)
            for group in run.optimiser.param_groups:
                group["lr"] = rate
            batch = _batch(run, step)
            terms, finite = _descend(run, *batch, amp, pretraining=step < config.pretrain.steps)
            if finite:
                skipped_in_a_row = 0
            else:
                skipped += 1
                skipped_in_a_row += 1
                if skipped_in_a_row == MAX_SKIPPED_IN_A_ROW:
                    raise InputError(f"training: {MAX_SKIPPED_IN_A_ROW} steps in a row gave non-finite gradients (at "
                                     f"step {step + 1}); the training has diverged: lower optimiser.learning_rate, or "
                                     "check the training volumes for empty or constant ones")
            step += 1
            if step == config.pretrain.steps:
                _end_pretraining(run, batch, bar)
            pairs_since += config.optimiser.batch_size * process.world_size
            bar.update(1)
            if step % config.log_every == 0 or step == config.optimiser.steps:
                now = time.perf_counter()
                row = _train_row(run, step, rate, terms, skipped, pairs_since / (now - clock))
                pairs_since, clock, skipped = 0, now, 0
                if process.main:
                    run.rows.append(row)
                    bar.set_postfix(loss=f"{row['total']:.3g}")
            _validate_and_save(run, step, bar)
    return step, started


def _batch(run: _Run, step: int) -> tuple[Tensor, Tensor, PoseTarget]:
    """The step's batch on the device: real pairs (new crops every step) with probability
    ``data.folder_fraction`` when there are folders, else synthetic pairs."""
    config, generator = run.config, run.generator
    if run.real is not None and torch.rand((), generator=generator, device=generator.device) < \
            config.data.folder_fraction:
        for dataset in run.real.datasets:
            dataset.set_epoch(step)  # new crops every step
        index = torch.randint(len(run.real), (config.optimiser.batch_size,), generator=generator,
                              device=generator.device)
        return _to(collate_pairs([run.real[int(i)] for i in index]), run.process.device)
    return sample_pairs(run.bank, config.optimiser.batch_size, generator, config.data.pair)


def _descend(run: _Run, fixed: Tensor, moving: Tensor, target: PoseTarget, amp: bool, pretraining: bool = False
             ) -> tuple[dict[str, Tensor], bool]:
    """One optimiser step on a batch: ``(loss terms, whether the gradients were finite and the step was taken)``;
    the pose loss, or while ``pretraining`` the dense loss of :mod:`dpcn_med.train.pretrain` (no solver)."""
    if pretraining:
        terms = dense_loss(run.model, fixed, moving, target, run.config.pretrain, amp=amp, generator=run.generator)
        nan = torch.tensor(float("nan"), device=fixed.device)
        terms = {**{name: torch.zeros((), device=fixed.device) for name in LOSS_TERMS},
                 **{name: nan for name in CANDIDATE_ERRORS}, **terms}
    else:
        result = run.network(fixed, moving, target, generator=run.generator, amp=amp)
        terms = pose_loss(result, target, run.config.loss)
        terms["dense_ncc"] = terms["pose_contrast"] = torch.zeros((), device=fixed.device)
        terms["chosen_error_deg"] = torch.rad2deg(geodesic_distance(result.rotation.detach().double(),
                                                                    target.rotation.double())).median()
        terms["best_candidate_error_deg"] = result.candidate_errors.min(-1).values.median()
    run.optimiser.zero_grad(set_to_none=True)
    terms["total"].backward()
    if pretraining and run.process.distributed:
        # The dense loss calls the extractors, not the DistributedDataParallel wrapper, which would sync the
        # gradients: average them here, as it would.
        for parameter in run.model.parameters():
            if parameter.grad is not None:
                dist.all_reduce(parameter.grad)
                parameter.grad /= run.process.world_size
    # One non-finite gradient (a degenerate pair: an empty crop, a constant volume) would make every weight NaN
    # at the step; such a step is skipped, and counted (its gradients are all-reduced: every process agrees).
    gradient_clip = run.config.optimiser.gradient_clip
    norm = torch.nn.utils.clip_grad_norm_(run.model.parameters(), gradient_clip if gradient_clip > 0 else math.inf)
    if torch.isfinite(norm):
        run.optimiser.step()
        return terms, True
    return terms, False


def _end_pretraining(run: _Run, batch: tuple[Tensor, Tensor, PoseTarget], bar: Any) -> None:
    """Give the pretrained extractors their gains (:func:`dpcn_med.train.pretrain.set_pretrained_gains`) on the last
    pretraining batch, averaged over the processes so that every rank keeps the same weights."""
    fixed, moving, _ = batch
    set_pretrained_gains(run.model, fixed, moving, run.config.pretrain)
    extractors = pretrained_extractors(run.model)
    if run.process.distributed:
        for extractor in extractors.values():
            dist.all_reduce(extractor.gain.data)
            extractor.gain.data /= run.process.world_size
    bar.write("pretraining done: gains " + ", ".join(
        f"{name} {extractor.gain.item():.3g}" for name, extractor in extractors.items()))


def _train_row(run: _Run, step: int, rate: float, terms: dict[str, Tensor], skipped: int, pairs_per_second: float
               ) -> dict:
    """The log row of a step: its loss terms averaged over the processes (every rank takes part)."""
    names = (*LOSS_TERMS, *CANDIDATE_ERRORS)
    values = torch.stack([terms[t].detach().float() for t in names])
    if run.process.distributed:
        dist.all_reduce(values)
        values /= run.process.world_size
    return {"step": step, "kind": "train", "learning_rate": rate,
            **{t: v.item() for t, v in zip(names, values)}, "skipped_steps": skipped,
            "pairs_per_second": pairs_per_second}


def _validate_and_save(run: _Run, step: int, bar: Any) -> None:
    """Validate (rank 0) and checkpoint at their intervals and at the last step."""
    config, process = run.config, run.process
    if process.main and (step % config.validate_every == 0 or step == config.optimiser.steps):
        run.rows.append(_validation_row(step, run.model, run.validation, run.real_validation))
        bar.write(f"step {step}: validation success {100 * run.rows[-1]['success']:.1f}%")
    if step % config.checkpoint_every == 0 or step == config.optimiser.steps:
        if process.main:
            save_checkpoint(run.model, run.optimiser, step, config, run.rows)
            io.write_csv(run.rows, run.output / "log.csv", COLUMNS)
            plot(run.rows, run.output / "training.png")
        distributed.barrier(process)


def _finish(run: _Run, step: int, started: float) -> dict:
    """Rank 0's end of a run: the final model with its training record, the log and the plot; the record."""
    config, process, rows = run.config, run.process, run.rows
    validations = [r for r in rows if r["kind"] == "validation"]
    record = {"steps": step, "pairs_seen": step * config.optimiser.batch_size * process.world_size,
              "wall_seconds_this_run": time.perf_counter() - started, "processes": process.world_size,
              "device": torch.cuda.get_device_name(process.device) if process.device.type == "cuda" else "cpu",
              "training_volumes": list(config.data.volumes),
              "validation_volumes": list(config.data.validation_volumes),
              "validation_before": validations[0] if validations else None,
              "validation_after": validations[-1] if validations else None,
              "config": replace(config, output=str(run.output)).to_json()}
    save_model(run.model, run.output / "model", record=record)
    io.write_csv(rows, run.output / "log.csv", COLUMNS)
    plot(rows, run.output / "training.png")
    return record
