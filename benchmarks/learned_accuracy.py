"""Held-out heterogeneous accuracy: learned models against the learning-free solver on the same synthetic pairs.

Pairs are made from volumes a model never saw (a config's ``validation_volumes``) with contrasts, poses and crops from
a seed of their own: rotation uniform over SO(3), translation up to 20% of the grid, scale 0.8-1.2 (similarity mode),
each side a random non-monotonic intensity map with bias field, blur, thick slices and noise. Success: rotation
within 5 degrees and translation within 2 voxels (the learning issue's criterion). Prints a table and writes it under
docs/. ``--volumes training`` makes the pairs from the config's training volumes instead, with the same unseen
contrasts and poses: a model that wins there and loses on held-out volumes has learned its training anatomy.
``--per-volume`` draws the pairs from each volume alone, a row per model and volume. ``--variants`` adds rows of the
learning-free solver with settings changed (``SolverConfig`` fields, several joined by ``;``), on the same pairs;
``--models`` with no value leaves only those rows.

    python benchmarks/learned_accuracy.py --config training/configs/ct_mr.yaml --models none runs/ct_mr/model
"""

from __future__ import annotations

import argparse
import ast
import statistics
import sys
from pathlib import Path

import torch

from dpcn_med.models import load_model
from dpcn_med.options import LEARNING_FREE
from dpcn_med.solver import solve
from dpcn_med.train import load_config
from dpcn_med.train.data import validation_set, volume_bank
from dpcn_med.train.loop import SUCCESS_DEGREES, SUCCESS_VOXELS, pose_errors

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]


def errors(predict, pairs) -> tuple[list[float], list[float], list[float]]:
    """Rotation (degrees) and translation (voxels) errors of ``predict(fixed, moving)``, which returns a solver or
    model result (anything with ``rotation`` and ``translation``), and the rotation error of the candidate nearest
    the truth among all the solver ranked (how good the choice could have been)."""
    rotations, translations, best = [], [], []
    with torch.no_grad():
        for fixed, moving, target in pairs:
            result = predict(fixed, moving)
            rotation, translation = pose_errors(result, target)
            rotations += rotation.tolist()
            translations += translation.tolist()
            best += getattr(result, "stage", result).ranking.errors(target.rotation).amin(-1).tolist()
    return rotations, translations, best


def _variant(text: str) -> dict:
    """``FIELD=VALUE[;FIELD=VALUE...]`` as solver options, each value a Python literal (``0``, ``(0.3,)``)."""
    options = {}
    for part in text.split(";"):
        field, equals, value = part.partition("=")
        if not equals or not field.strip():
            raise argparse.ArgumentTypeError(f"{text!r}: expected FIELD=VALUE, several joined by ';'")
        try:
            options[field.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise argparse.ArgumentTypeError(f"{text!r}: {value!r} is not a Python literal") from None
    return options


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, required=True, help="training config: its held-out volumes and pairs")
    parser.add_argument("--models", nargs="*", default=["none"], help="'none' (learning-free) and/or model paths; "
                        "none at all (the flag alone) leaves only the --variants rows")
    parser.add_argument("--pairs", type=count_type(2), default=200, help="held-out pairs (at least 2: the table gives "
                        "a 90th percentile)")
    parser.add_argument("--seed", type=int, default=2025, help="not the config's validation seed: unseen contrasts")
    parser.add_argument("--volumes", choices=("validation", "training"), default="validation",
                        help="the config's held-out volumes (the acceptance), or its training volumes with unseen "
                        "contrasts and poses (does a model generalise to new anatomy, or only to new contrasts?)")
    parser.add_argument("--per-volume", action="store_true",
                        help="--pairs pairs from each volume alone, one row per model and volume (which anatomy a "
                        "model fails on)")
    parser.add_argument("--variants", nargs="+", default=[], type=_variant, metavar="FIELD=VALUE[;FIELD=VALUE]",
                        help="more learning-free rows, each with SolverConfig fields changed (Python literals, several "
                        "joined by ';'), e.g. entropy_ranking_weight=0 'finalists=8;candidate_size=64'")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "learned_accuracy.md")
    args = parser.parse_args(argv)
    if not args.models and not args.variants:
        parser.error("nothing to score: give --models, --variants or both")
    config = load_config(args.config)
    device = torch.device(args.device)
    bandwidth, mode = config.model.bandwidth, config.data.pair.mode
    # Prepared as in training (the config's grid preprocessing), as register prepares a model's inputs.
    volumes = config.data.validation_volumes if args.volumes == "validation" else config.data.volumes
    preprocessing = config.model.grid_preprocessing()
    if args.per_volume:  # the same number of pairs from each volume alone (other pairs than the pooled set's)
        groups = [(Path(name).name, validation_set(volume_bank((name,), 2 * bandwidth, preprocessing, device=device),
                                                   args.pairs, args.seed, config.data.pair)) for name in volumes]
    else:
        groups = [(None, validation_set(volume_bank(volumes, 2 * bandwidth, preprocessing, device=device),
                                        args.pairs, args.seed, config.data.pair))]
    volume_column = " volume |" if args.per_volume else ""
    lines = [f"| model |{volume_column} pairs | success (< 5 deg and < 2 voxels) | median rotation error (deg) | "
             "median translation error (voxels) | 90th percentile rotation error (deg) | "
             "a candidate within 5 deg |",
             "|---|" + ("---|" if args.per_volume else "") + "---|---|---|---|---|---|"]
    # The learning-free solver is a variant that changes nothing.
    for name in [{} if name.lower() in LEARNING_FREE else name for name in args.models] + args.variants:
        if isinstance(name, dict):
            label = ", ".join(["learning-free solver", *(f"`{field}={value!r}`" for field, value in name.items())])

            def predict(fixed, moving, options=name):
                return solve(fixed, moving, mode, bandwidth=bandwidth, **options)
        else:
            model = load_model(name, device=device)
            label = f"`{name}`"

            def predict(fixed, moving, model=model):
                return model(fixed, moving, mode=mode)
        for volume, pairs in groups:
            rotation, translation, best = errors(predict, pairs)
            success = sum(r < SUCCESS_DEGREES and t < SUCCESS_VOXELS for r, t in zip(rotation, translation))
            lines.append(f"| {label} |{f' {volume} |' if volume else ''} {len(rotation)} | "
                         f"{100 * success / len(rotation):.1f}% | "
                         f"{statistics.median(rotation):.2f} | {statistics.median(translation):.2f} | "
                         f"{statistics.quantiles(rotation, n=10)[-1]:.1f} | "
                         f"{100 * sum(b < SUCCESS_DEGREES for b in best) / len(best):.1f}% |")
            print(lines[-1], file=sys.stderr)
    names = ", ".join(Path(v).name for v in volumes)
    lines.append("")
    lines.append("The last column: the share of pairs where some candidate the solver ranked lies within 5 degrees of "
                 "the truth, whether or not it was chosen (before the rotation refinement, which may bring a near "
                 "miss within 5 degrees).")
    title = "Held-out heterogeneous accuracy" if args.volumes == "validation" else \
        "Heterogeneous accuracy on the training volumes"
    text = (f"# {title}\n\n{generated_by(__file__, argv)}: bandwidth {bandwidth} "
            f"({2 * bandwidth}^3 grids), {mode} mode, {'held-out' if args.volumes == 'validation' else 'training'} "
            f"volumes {names}, pair seed {args.seed}, device "
            f"{device}.\n\n" + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
