"""The training loop: synthetic pairs on the device, AdamW, warm-up and cosine decay, validation, checkpoints.

Single process, or one process per device under ``torchrun`` with DistributedDataParallel (each rank draws its own
pairs; rank 0 validates, logs and writes). Everything a run writes goes to ``config.output``:

* ``checkpoint.safetensors`` + ``checkpoint.json``: weights and optimiser state, the step (in both), the config
  (resumed from when ``config.resume``, if the config's :data:`MUST_MATCH_ON_RESUME` settings are the checkpoint's);
* ``log.csv``: a row per logged step (losses, rate, pairs per second) and per validation (success, median errors);
* ``training.png``: the losses and the validation success against steps;
* ``model.safetensors`` + ``model.json``: the final model with its training record (:func:`dpcn_med.models.save_model`).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from dpcn_med import __version__, io
from dpcn_med.errors import InputError
from dpcn_med.geometry import geodesic_distance
from dpcn_med.models import DPCN, DPCNOutput, pose_loss, save_model
from dpcn_med.models.weights import unique_state
from dpcn_med.solver import PoseTarget, SolveResult
from dpcn_med.train import distributed
from dpcn_med.train.config import TrainConfig
from dpcn_med.train.data import sample_pairs, validation_set, volume_bank
from dpcn_med.train.folders import FolderPairs, collate_pairs, derived_seed

SUCCESS_DEGREES, SUCCESS_VOXELS = 5.0, 2.0
"""A registration succeeds within 5 degrees and 2 voxels (the learning issue's criterion)."""

MUST_MATCH_ON_RESUME = ("model", "data", "optimiser.weight_decay")
"""Config entries a checkpoint must share with the run that resumes it: the networks (but their ``version``), the
pairs (the data's paths as seen from the output folder, or as they were: a project folder moves whole, or only its
run), and the weight decay (restored with the optimiser's state). An entry only one side has (a checkpoint from a
dpcn_med before that setting) differs. The rest may change: ``steps`` (to train on), the rest of the schedule, the
batch size, the seed, the device, the intervals."""

CHECKPOINT_ENTRIES = {"step": int, "param_groups": list, "optimiser_scalars": dict, "config": dict, "rows": list}
"""What ``checkpoint.json`` holds, and the JSON type of each."""

LOSS_TERMS = ("total", "rotation_kl", "rotation_l1", "scale_kl", "scale_l1", "translation_kl", "translation_l1")
MAX_SKIPPED_IN_A_ROW = 20
"""Steps in a row with non-finite gradients after which training stops: it has diverged, not met one bad pair."""
SCORES = ("success", "rotation_error_deg", "translation_error_vox")
COLUMNS = ("step", "kind", "learning_rate", *LOSS_TERMS, "skipped_steps", "pairs_per_second", *SCORES,
           *(f"real_{name}" for name in SCORES))


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
    resumed run draws new pairs, not the old ones, nor another rank's (``seed * 1_000_003 + rank * 7_919 + step``
    gave rank 0 resumed at step 7919 the pairs of rank 1 from step 0)."""
    return derived_seed(seed, rank, step)


def _real_pairs(roots: tuple[str, ...], config: TrainConfig, *, crop: tuple[float, float] | None, seed: int
                ) -> torch.utils.data.ConcatDataset | None:
    """The folders' real pairs as one dataset, every pair read and prepared now (kept for the run), or ``None``
    without folders.

    Raises:
        InputError: an unusable pair, before the output folder is made: read on first use, a broken pair surfaced
            mid-run, after checkpoints.
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


def _checkpoint_paths(output: Path) -> tuple[Path, Path]:
    return output / "checkpoint.safetensors", output / "checkpoint.json"


def save_checkpoint(model: DPCN, optimiser: torch.optim.Optimizer, step: int, config: TrainConfig,
                    rows: list[dict]) -> None:
    """Weights and optimiser moments as safetensors, everything else as JSON (no pickle anywhere)."""
    tensors = {f"model.{name}": tensor for name, tensor in unique_state(model).items()}
    state = optimiser.state_dict()
    scalars = {}
    for index, values in state["state"].items():
        for name, value in values.items():
            if isinstance(value, Tensor):
                tensors[f"optimiser.{index}.{name}"] = value
            else:
                scalars[f"{index}.{name}"] = value
    weights, description = _checkpoint_paths(Path(config.output))
    with io.interrupts_deferred():  # each file is atomic; the pair must be too (load_checkpoint checks the step)
        io.write_tensors(tensors, weights, metadata={"step": str(step)})
        io.write_json({"step": step, "param_groups": state["param_groups"], "optimiser_scalars": scalars,
                       "config": config.to_json(), "rows": rows, "version": __version__}, description)


_ABSENT = object()
"""A config entry a checkpoint does not have."""


def _resume_settings(config: dict) -> dict:
    """The :data:`MUST_MATCH_ON_RESUME` entries of a config's JSON, nested as in the config."""
    settings: dict = {}
    for key in MUST_MATCH_ON_RESUME:
        section, _, name = key.partition(".")
        value = config.get(section, _ABSENT)
        if name:
            value = {name: value.get(name, _ABSENT) if isinstance(value, dict) else _ABSENT}
        elif section == "model" and isinstance(value, dict):
            value = {k: v for k, v in value.items() if k != "version"}  # which dpcn_med saved it; not a setting
        settings[section] = value
    return settings


def _seen_from(settings: dict, output: Any) -> dict:
    """``settings`` with the data's absolute paths made relative to the ``output`` folder."""
    data = settings.get("data")
    if not (isinstance(data, dict) and isinstance(output, str)):
        return settings
    relative = {key: [os.path.relpath(p, output) if isinstance(p, str) and os.path.isabs(p) else p for p in paths]
                for key in ("volumes", "validation_volumes", "folders", "validation_folders")
                if isinstance(paths := data.get(key), list)}
    return {**settings, "data": {**data, **relative}}


def _first_difference(saved: Any, current: Any, key: str = "") -> tuple[str, Any, Any] | None:
    """``(dotted key, saved value, current value)`` of the first entry where two JSON values differ, else ``None``."""
    if isinstance(saved, dict) and isinstance(current, dict):
        for name in [*current, *(k for k in saved if k not in current)]:
            found = _first_difference(saved.get(name, _ABSENT), current.get(name, _ABSENT),
                                      f"{key}.{name}" if key else name)
            if found is not None:
                return found
        return None
    return None if saved == current else (key, saved, current)


def _shown(value: Any) -> str:
    return "no such entry" if value is _ABSENT else json.dumps(value)


def load_checkpoint(model: DPCN, optimiser: torch.optim.Optimizer, config: TrainConfig) -> tuple[int, list[dict]]:
    """Restore a checkpoint into ``model`` and ``optimiser``: ``(step, log rows)``; ``(0, [])`` without one.

    Raises:
        InputError: the checkpoint is malformed, was made with other :data:`MUST_MATCH_ON_RESUME` settings, or is past
            ``config.optimiser.steps``; the message names the file and the way out.
    """
    weights, description = _checkpoint_paths(Path(config.output))
    afresh = "train into another output folder, or start afresh over this one with --restart (resume: false)"
    if not config.resume or not (weights.exists() or description.exists()):
        return 0, []
    for missing, present in ((weights, description), (description, weights)):
        if not missing.exists():  # starting afresh would overwrite the other half at the first checkpoint
            raise InputError(f"{missing}: missing beside {present.name} (a checkpoint is the two files); {afresh}")
    saved = io.read_json(description)
    wrong = [key for key, kind in CHECKPOINT_ENTRIES.items()
             if not (isinstance(saved, dict) and isinstance(saved.get(key), kind))
             or (key == "step" and (isinstance(saved[key], bool) or saved[key] < 0))]
    if wrong:
        raise InputError(f"{description}: not a dpcn_med checkpoint (no valid {', '.join(wrong)}); {afresh}")
    settings = _resume_settings(saved["config"]), _resume_settings(json.loads(json.dumps(config.to_json())))
    difference = _first_difference(*settings)
    if difference is not None and _first_difference(_seen_from(settings[0], saved["config"].get("output")),
                                                    _seen_from(settings[1], config.output)) is not None:
        key, before, now = difference
        raise InputError(f"{description}: was made with {key} {_shown(before)}, this config has {_shown(now)}; "
                         f"{afresh}")
    if saved["step"] > config.optimiser.steps:
        raise InputError(f"{description}: is at step {saved['step']}, past this config's optimiser.steps "
                         f"{config.optimiser.steps}; ask for more steps, or {afresh}")
    try:
        tensors, step = io.read_tensors(weights), io.read_tensor_header(weights)[0].get("step")
    except InputError as error:
        raise InputError(f"{error}; {afresh}") from None
    if step != str(saved["step"]):
        raise InputError(f"{weights}: holds step {step}, {description.name} step {saved['step']}: the two files are "
                         f"from different saves (one cut short?); {afresh}")
    model_state = {name[len("model."):]: t for name, t in tensors.items() if name.startswith("model.")}
    shapes = {name: tensor.shape for name, tensor in unique_state(model).items()}
    misfits = sorted(set(shapes) ^ set(model_state)) + sorted(
        name for name in set(shapes) & set(model_state) if model_state[name].shape != shapes[name])
    if misfits:
        raise InputError(f"{weights}: does not fit this model ({len(misfits)} tensors missing, unexpected or of "
                         f"another shape, such as {misfits[0]}); {afresh}")
    model.load_state_dict({**model.state_dict(), **model_state})
    state: dict = {"state": {}, "param_groups": saved["param_groups"]}
    try:
        for name, tensor in tensors.items():
            if name.startswith("optimiser."):
                _, index, key = name.split(".", 2)
                state["state"].setdefault(int(index), {})[key] = tensor
        for name, value in saved["optimiser_scalars"].items():
            index, key = name.split(".", 1)
            state["state"].setdefault(int(index), {})[key] = value
        optimiser.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise InputError(f"{description}: its optimiser state does not fit this model ({' '.join(str(error).split())})"
                         f"; {afresh}") from None
    return saved["step"], saved["rows"]


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
        saved with it.
    """
    output = Path(config.output)
    _check_output_outside_data(output, config)
    process = distributed.start(config.device)
    torch.manual_seed(config.seed)  # the same initial weights on every rank
    model = DPCN(config.model).to(process.device).train()
    optimiser = torch.optim.AdamW(model.parameters(), lr=config.optimiser.learning_rate,
                                  weight_decay=config.optimiser.weight_decay)
    step, rows = load_checkpoint(model, optimiser, config)  # first: a checkpoint of another config is refused at once
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
    distributed.barrier(process)
    amp = config.optimiser.amp and process.device.type == "cuda"
    from tqdm import tqdm

    bar = tqdm(total=config.optimiser.steps, initial=step, disable=not process.main, desc="training",
               dynamic_ncols=True)
    started, pairs_since, clock = time.perf_counter(), 0, time.perf_counter()
    skipped, skipped_in_a_row = 0, 0
    while step < config.optimiser.steps:
        rate = learning_rate(step, config)
        for group in optimiser.param_groups:
            group["lr"] = rate
        if real is not None and torch.rand((), generator=generator, device=generator.device) < \
                config.data.folder_fraction:
            for dataset in real.datasets:
                dataset.set_epoch(step)  # new crops every step
            index = torch.randint(len(real), (config.optimiser.batch_size,), generator=generator,
                                  device=generator.device)
            fixed, moving, target = _to(collate_pairs([real[int(i)] for i in index]), process.device)
        else:
            fixed, moving, target = sample_pairs(bank, config.optimiser.batch_size, generator, config.data.pair)
        result = network(fixed, moving, target, generator=generator, amp=amp)
        terms = pose_loss(result, target)
        optimiser.zero_grad(set_to_none=True)
        terms["total"].backward()
        # One non-finite gradient (a degenerate pair: an empty crop, a constant volume) would make every weight NaN
        # at the step; such a step is skipped, and counted (its gradients are all-reduced: every process agrees).
        norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.optimiser.gradient_clip
                                              if config.optimiser.gradient_clip > 0 else math.inf)
        if torch.isfinite(norm):
            optimiser.step()
            skipped_in_a_row = 0
        else:
            skipped += 1
            skipped_in_a_row += 1
            if skipped_in_a_row == MAX_SKIPPED_IN_A_ROW:
                raise InputError(f"training: {MAX_SKIPPED_IN_A_ROW} steps in a row gave non-finite gradients (at "
                                 f"step {step + 1}); the training has diverged: lower optimiser.learning_rate, or "
                                 "check the training volumes for empty or constant ones")
        step += 1
        pairs_since += config.optimiser.batch_size * process.world_size
        bar.update(1)
        if step % config.log_every == 0 or step == config.optimiser.steps:
            values = torch.stack([terms[t].detach().float() for t in LOSS_TERMS])
            if process.distributed:
                dist.all_reduce(values)
                values /= process.world_size
            now = time.perf_counter()
            row = {"step": step, "kind": "train", "learning_rate": rate,
                   **{t: v.item() for t, v in zip(LOSS_TERMS, values)}, "skipped_steps": skipped,
                   "pairs_per_second": pairs_since / (now - clock)}
            pairs_since, clock, skipped = 0, now, 0
            if process.main:
                rows.append(row)
                bar.set_postfix(loss=f"{row['total']:.3g}")
        if process.main and (step % config.validate_every == 0 or step == config.optimiser.steps):
            rows.append(_validation_row(step, model, validation, real_validation))
            bar.write(f"step {step}: validation success {100 * rows[-1]['success']:.1f}%")
        if step % config.checkpoint_every == 0 or step == config.optimiser.steps:
            if process.main:
                save_checkpoint(model, optimiser, step, config, rows)
                io.write_csv(rows, output / "log.csv", COLUMNS)
                plot(rows, output / "training.png")
            distributed.barrier(process)
    bar.close()
    record = {}
    if process.main:
        validations = [r for r in rows if r["kind"] == "validation"]
        record = {"steps": step, "pairs_seen": step * config.optimiser.batch_size * process.world_size,
                  "wall_seconds_this_run": time.perf_counter() - started, "processes": process.world_size,
                  "device": torch.cuda.get_device_name(process.device) if process.device.type == "cuda" else "cpu",
                  "training_volumes": list(config.data.volumes),
                  "validation_volumes": list(config.data.validation_volumes),
                  "validation_before": validations[0] if validations else None,
                  "validation_after": validations[-1] if validations else None,
                  "config": replace(config, output=str(output)).to_json()}
        save_model(model, output / "model", record=record)
        io.write_csv(rows, output / "log.csv", COLUMNS)
        plot(rows, output / "training.png")
    distributed.stop(process)
    return model.eval(), record
