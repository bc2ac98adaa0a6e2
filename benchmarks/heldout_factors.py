"""What makes the held-out heterogeneous pairs hard: the learning-free solver on the same pairs with one factor of
their simulation changed at a time, at one or more weights of the rotation correlation's degree-2 harmonics (each
alone: ``SolverConfig(degree_two_weight=w, extra_degree_two_weights=())``).

The pairs are those of ``benchmarks/learned_accuracy.py`` (a config's held-out volumes, pair seed 2025), drawn again
with the factor changed: the same contrast on both sides (no contrast at all), no slab crop, rigid poses, no shift,
and the random modality taken apart (the non-monotonic intensity map alone, a monotonic map alone, and a monotonic
map with each degradation alone: bias field, blur, thick slices, noise). Success: rotation within 5 degrees and
translation within 2 voxels. Prints a table and writes it under docs/.

    python benchmarks/heldout_factors.py --config training/configs/ct_mr.yaml --degree-two-weights 1 0.3 0
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

import torch

from dpcn_med.solver import SolverConfig, solve
from dpcn_med.synth.contrast import ContrastConfig
from dpcn_med.train import load_config
from dpcn_med.train.data import validation_set, volume_bank
from dpcn_med.train.loop import SUCCESS_DEGREES, SUCCESS_VOXELS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from learned_accuracy import errors  # noqa: E402  (the scripts' shared helpers)
from markdown import count_type, generated_by, publish  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
_CLEAN = {"bias_strength": 0.0, "sigma_range": (0.0, 0.0), "factor_range": (1.0, 1.0), "noise_std_range": (0.0, 0.0)}
_DEGRADATIONS = {"bias_strength": "bias field", "sigma_range": "blur", "factor_range": "thick slices",
                 "noise_std_range": "noise"}


def variants(pair) -> dict[str, object]:
    """Row label -> the :class:`dpcn_med.synth.PairConfig` of that row, from the config's own ``pair``."""
    def contrast(config: ContrastConfig):
        return dataclasses.replace(pair, fixed_contrast=config, moving_contrast=config)

    rows = {"as benchmarked (learned_accuracy.py)": pair,
            "same contrast on both sides (identity)": dataclasses.replace(pair, fixed_modality="identity",
                                                                          moving_modality="identity"),
            "no slab crop": dataclasses.replace(pair, crop_probability=0.0),
            "rigid (scale 1)": dataclasses.replace(pair, mode="rigid"),
            "no shift": dataclasses.replace(pair, max_shift_fraction=0.0),
            "non-monotonic intensity map alone": contrast(ContrastConfig(**_CLEAN)),
            "monotonic intensity map alone": contrast(ContrastConfig(monotonic=True, **_CLEAN)),
            "monotonic map and every degradation": contrast(ContrastConfig(monotonic=True))}
    default = ContrastConfig()
    for field, label in _DEGRADATIONS.items():
        rows[f"monotonic map and {label} alone"] = contrast(
            ContrastConfig(monotonic=True, **{**_CLEAN, field: getattr(default, field)}))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, required=True, help="training config: its held-out volumes and pairs")
    parser.add_argument("--pairs", type=count_type(2), default=200, help="pairs per row")
    parser.add_argument("--seed", type=int, default=2025, help="pair seed (learned_accuracy.py's by default)")
    parser.add_argument("--degree-two-weights", type=float, nargs="+", default=[1.0, 0.3],
                        help="SolverConfig.degree_two_weight values, a column pair each")
    parser.add_argument("--rows", nargs="+", help="only the rows whose label starts with one of these")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "heldout_factors.md")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    bandwidth = config.model.bandwidth
    bank = volume_bank(config.data.validation_volumes, 2 * bandwidth, config.model.grid_preprocessing())
    # One weighting each, without the default's extra weighted correlation: each column measures its weight alone.
    weights = [SolverConfig(degree_two_weight=weight, extra_degree_two_weights=())
               for weight in args.degree_two_weights]
    header = "| pairs |" + "".join(f" success, degree-2 weight {w.degree_two_weight:g} | median rotation error (deg) |"
                                   for w in weights)
    lines = [header, "|---|" + "---|---|" * len(weights)]
    for label, pair in variants(config.data.pair).items():
        if args.rows and not any(label.startswith(prefix) for prefix in args.rows):
            continue
        pairs = validation_set(bank, args.pairs, args.seed, pair)
        cells = []
        for solver in weights:
            with torch.no_grad():
                rotation, translation, _ = errors(
                    lambda fixed, moving, solver=solver, mode=pair.mode: solve(fixed, moving, mode, config=solver,
                                                                               bandwidth=bandwidth), pairs)
            success = sum(r < SUCCESS_DEGREES and t < SUCCESS_VOXELS for r, t in zip(rotation, translation))
            cells.append(f" {100 * success / len(rotation):.1f}% | {statistics.median(rotation):.1f} |")
        lines.append(f"| {label} |" + "".join(cells))
        print(lines[-1], file=sys.stderr)
    names = ", ".join(Path(v).name for v in config.data.validation_volumes)
    text = (f"# What makes the held-out pairs hard\n\n{generated_by(__file__, argv)}: the learning-free solver, "
            f"bandwidth {bandwidth}, one degree-2 weighting per column, on {args.pairs} pairs per row of the held-out "
            f"volumes {names} (pair seed "
            f"{args.seed}), each row with one factor of the simulation changed. Success: rotation within "
            f"{SUCCESS_DEGREES:g} degrees and translation within {SUCCESS_VOXELS:g} voxels.\n\n" + "\n".join(lines)
            + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
