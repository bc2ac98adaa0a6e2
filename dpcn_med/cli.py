"""``dpcn-med``: register volumes from the command line (thin over :mod:`dpcn_med.register`).

Exit codes: 0 success; 2 bad input (one line on stderr naming the file and the problem, nothing written); 3 result
written but the solver's confidence is below ``--min-confidence``; 130 interrupted (Ctrl-C or SIGTERM), nothing written
for the unfinished pair; 1 internal error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from dpcn_med import __version__
from dpcn_med.errors import InputError

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_LOW_CONFIDENCE = 0, 1, 2, 3
MIN_CONFIDENCE = 0.003
"""Default threshold on the solver's confidence (translation-peak mass), learning-free, B = 32. Measured: 0.0007-0.0011
for five pairs of unrelated volumes; 1.0 for correct same-modality round trips; 0.11-0.88 for the real MRI-DIR CT to
T2 from 21 starts; 0.0024 for the built-in pseudo-CT to MR demo pose, correct (docs/registration.md, Confidence)."""

OUTPUT_NAMES = ("transform.tfm", "transform.h5", "inverse.tfm", "inverse.h5", "moving_resampled.nii.gz",
                "overview.png", "report.json")
"""What ``register`` writes into its output folder; ``report.json`` comes last and marks a finished pair."""

PAIR_COLUMNS = ("id", "fixed", "moving", "fixed_mask", "moving_mask")
"""The columns of a register-batch pairs file; fixed and moving are required."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dpcn-med", description="Initialisation-free rigid / similarity "
                                     "registration of CT, MRI and ultrasound volumes (DPCN++ phase correlation).")
    parser.add_argument("--version", action="version", version=f"dpcn-med {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    options = argparse.ArgumentParser(add_help=False)
    options.add_argument("--mode", choices=("rigid", "similarity"), default="rigid",
                         help="rigid (6 DoF, default) or similarity (7 DoF, isotropic scale)")
    options.add_argument("--bandwidth", type=int, help="solver bandwidth B, grids are (2B)^3 (default: the model's; "
                         "32 without one)")
    options.add_argument("--model", default="none", help="'none' (default): the learning-free solver; or a model "
                         "trained with dpcn-med train (NAME.safetensors with its NAME.json)")
    options.add_argument("--no-refine", dest="refine", action="store_false",
                         help="skip the local mutual-information refinement")
    options.add_argument("--device", default="auto", help="auto (default), cpu, cuda or cuda:N")
    options.add_argument("--fixed-modality", default="auto", choices=("auto", "ct", "mr", "us"))
    options.add_argument("--moving-modality", default="auto", choices=("auto", "ct", "mr", "us"))
    options.add_argument("--min-confidence", type=_finite_float, default=MIN_CONFIDENCE,
                         help=f"exit with code 3 below this solver confidence (default {MIN_CONFIDENCE})")
    options.add_argument("--no-overview", dest="overview", action="store_false",
                         help="do not draw overview.png (saves about a second: matplotlib's import and the drawing)")
    options.add_argument("--no-resampled", dest="resampled", action="store_false",
                         help="do not write moving_resampled.nii.gz")
    options.add_argument("--progress", choices=("auto", "json"), default="auto",
                         help="auto (default): a bar on a terminal; json: one JSON object per line on stdout, "
                         '{"stage": ..., "fraction": ...}, for programs that drive dpcn-med (the Slicer module)')
    tracebacks = argparse.ArgumentParser(add_help=False)  # the commands without the loudness options
    tracebacks.add_argument("-v", "--verbose", action="store_true", help="print the traceback of an internal error")

    loudness = options.add_mutually_exclusive_group()
    loudness.add_argument("-q", "--quiet", action="store_true", help="print errors only")
    loudness.add_argument("-v", "--verbose", action="store_true", help="print timings; tracebacks on errors")

    register = commands.add_parser("register", parents=[options], help="register MOVING onto FIXED",
                                   description="Register MOVING onto FIXED from any starting pose and write the "
                                   f"transform, its inverse, the resampled moving volume and a report into OUTDIR "
                                   f"({', '.join(OUTPUT_NAMES)}).")
    register.add_argument("fixed", help="fixed volume: NIfTI, NRRD, MHA/MHD, DICOM folder (FOLDER@SERIES_UID to pick "
                          "a series) or a surface mesh / point cloud (.stl .vtk .vtp .ply .obj)")
    register.add_argument("moving", help="moving volume, same kinds")
    register.add_argument("-o", "--output", required=True, type=output_path, help="output folder (created)")
    register.add_argument("--fixed-mask", help="binary mask on the fixed image's grid")
    register.add_argument("--moving-mask", help="binary mask on the moving image's grid")

    batch = commands.add_parser("register-batch", parents=[options], help="register every pair of a CSV file",
                                description="Register every row of PAIRS.csv (columns fixed, moving and optionally "
                                "id, fixed_mask, moving_mask; paths relative to the CSV) into OUTDIR/ID/. Pairs whose "
                                "report.json records the same inputs and settings are skipped, so an interrupted run "
                                "resumes.")
    batch.add_argument("pairs", type=Path, help="CSV file with a header row")
    batch.add_argument("-o", "--output", required=True, type=output_path, help="output folder (created)")

    training = commands.add_parser("train", parents=[tracebacks],
                                   help="train the feature networks (DPCN++) from a YAML config",
                                   description="Train a model on synthetic pairs as CONFIG says (see training/configs/"
                                   "); resumes from OUTPUT/checkpoint. Under torchrun (torchrun --nproc_per_node N -m "
                                   "dpcn_med train ...) every process trains on its own device "
                                   "(DistributedDataParallel). Writes OUTPUT/model.safetensors and .json, log.csv and "
                                   "training.png.")
    training.add_argument("--config", required=True, type=Path, help="YAML training config")
    training.add_argument("--output", help="output folder (overrides the config's)")
    training.add_argument("--steps", type=count_type(), help="optimiser steps (overrides the config's)")
    training.add_argument("--device", help="auto, cpu or cuda (overrides the config's)")
    training.add_argument("--restart", action="store_true", help="ignore an existing checkpoint and start afresh")

    bench = commands.add_parser("benchmark", parents=[tracebacks],
                                help="compare with SimpleITK, ANTs and elastix by initial rotation",
                                description="Register the same pairs with dpcn_med and the classical tools, in "
                                "30-degree bins of initial rotation, and write results.csv, summary.md and "
                                "success.png into OUTDIR. Quick mode (default): the built-in volumes, one pose per "
                                "bin, a few minutes; --full: the shared real volumes too, ten poses per bin.")
    bench.add_argument("-o", "--output", type=output_path, default=Path("benchmark_output"),
                       help="output folder; an interrupted run's registrations are kept there (results.partial.jsonl) "
                       "and the same command goes on from them; registrations of it that a rerun with fewer --cases, "
                       "--methods or --bins does not cover stay there for the command that made them")
    bench.add_argument("--full", action="store_true", help="the documented run (docs/benchmarks.md)")
    bench.add_argument("--cases", nargs="+", help="override the mode's cases")
    bench.add_argument("--methods", nargs="+", help="override the methods (default: the installed ones; quick mode "
                       "leaves out ants-multistart)")
    bench.add_argument("--trials", type=count_type(), help="poses per case and bin (quick 1, full 10); a case's poses "
                       "follow from it, the case and --seed")
    bench.add_argument("--seed", type=count_type(0), help="of the poses, 0 or more (default 0)")
    bench.add_argument("--bins", nargs="+", metavar="BIN",
                       help="register only these rotation bins, named as in results.csv (90-120); the poses are "
                       "those of a run of every bin with the same --trials, so runs split by bin over several cores "
                       "can be combined")
    bench.add_argument("--combine", nargs="+", type=Path, metavar="FOLDER",
                       help="run nothing: one summary and figure of earlier runs' results.csv (say, split by --cases "
                       "or --bins over several cores; the same poses, which follow from the case, --seed and "
                       "--trials: folders whose settings.json differ are refused)")

    info = commands.add_parser("info", parents=[tracebacks], help="print an image's geometry and intensity range")
    info.add_argument("image", help="image file or DICOM folder")
    return parser


class _Progress:
    """A one-line progress bar on an interactive terminal; stage names with --verbose elsewhere; silent with -q;
    JSON lines on stdout with ``--progress json`` (whatever the loudness)."""

    def __init__(self, quiet: bool, verbose: bool, label: str = "", json_lines: bool = False) -> None:
        self.json = json_lines
        self.live = not quiet and not json_lines and sys.stderr.isatty()
        self.verbose = verbose and not self.live
        self.label = label
        self.stage = ""

    def __call__(self, stage: str, fraction: float) -> None:
        if self.json:
            print(json.dumps({"stage": stage, "fraction": round(float(fraction), 4), "pair": self.label.strip()}),
                  flush=True)
        elif self.live:
            filled = int(round(30 * fraction))
            sys.stderr.write(f"\r{self.label}[{'#' * filled}{'.' * (30 - filled)}] {fraction:4.0%} {stage:<14s}")
            sys.stderr.flush()
            if stage == "done":
                sys.stderr.write("\n")
        elif self.verbose and stage != self.stage:
            print(f"{self.label}{stage}", file=sys.stderr)
        self.stage = stage


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:  # argparse would say "invalid _finite_float value"
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def count_type(minimum: int = 1) -> Callable[[str], int]:
    """An argparse type for a count (steps, poses, trials) or a seed: a whole number of at least ``minimum``, so that a
    mistyped 0 or -1 stops at the command line instead of failing after the data are loaded."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} is too few; give at least {minimum}")
        return value

    return parse


def output_path(text: str) -> Path:
    if not text.strip():  # Path("") is the working folder: an empty variable in a script would write there
        raise argparse.ArgumentTypeError("an empty output folder; give a folder name ('.' for the working folder)")
    return Path(text)


def check_output_folder(output: Path) -> None:
    """Refuse, before any work, an output folder that exists as a file or cannot be created or written."""
    try:
        if output.exists() and not output.is_dir():
            raise InputError(f"{output}: exists and is not a folder; choose another output folder")
        for existing in (output, *output.absolute().parents):
            if existing.exists():
                break
            if existing.is_symlink():  # mkdir would fail on it after the work
                raise InputError(f"{output}: cannot be created: {existing} is a link to {os.readlink(existing)}, which "
                                 "does not exist; choose another output folder")
        if not existing.is_dir():
            raise InputError(f"{output}: cannot be created: {existing} is a file; choose another output folder")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise InputError(f"{output}: cannot be written: no write permission in {existing}; choose another output "
                             "folder")
    except OSError as error:  # a name too long for the file system, a loop of links
        raise InputError(f"{output}: cannot be used ({error.strerror}); choose another output folder") from None


def _make_folder(output: Path, *, staging: bool = False) -> Path:
    """Create ``output`` and its missing parents; with ``staging``, return a new hidden folder inside it.

    Raises:
        InputError: naming ``output``, where the checks before the work could not tell (``/proc/x``, a full disk).
    """
    try:
        output.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=".dpcn-med-", dir=output)) if staging else output
    except OSError as error:
        raise InputError(f"{output}: cannot be written ({error.strerror}); choose another output folder") from None


def _refuse_overwriting_inputs(inputs: dict[str, str], targets: Iterable[Path]) -> None:
    """Refuse, before any work, a run that would write one of ``targets`` over one of its ``inputs`` (each path with
    what messages call it), however spelt: a link, or ``out/x/../in.nii.gz`` with no ``x`` yet, which names
    ``out/in.nii.gz`` once the output folders are made (``realpath`` drops ``x/..`` when ``x`` is missing)."""
    existing = {}
    for path, description in inputs.items():
        with contextlib.suppress(OSError):
            found = os.stat(os.path.realpath(path))
            existing.setdefault((found.st_dev, found.st_ino), description)
    for target in targets:
        try:
            found = os.stat(os.path.realpath(target))
        except OSError:  # not there: nothing to overwrite
            continue
        if (found.st_dev, found.st_ino) in existing:
            raise InputError(f"{target}: is {existing[found.st_dev, found.st_ino]}, which this run would replace; "
                             "choose another output folder (inputs are never overwritten)")


def register_pair(fixed: str, moving: str, output: Path, args: argparse.Namespace, *, fixed_mask: str | None = None,
                  moving_mask: str | None = None, label: str = "") -> tuple[int, dict]:
    """Register one pair and write every output into ``output`` at once (staged, then renamed into place).

    Returns:
        ``(exit code, report)``; input errors raise :class:`InputError` before anything is written.
    """
    from dpcn_med import io
    from dpcn_med.registration import register
    from dpcn_med.report import overview_figure, registration_report

    _refuse_overwriting_inputs({p: "an input of this run" for p in (fixed, moving, fixed_mask, moving_mask)
                                if p is not None}, [output / name for name in OUTPUT_NAMES])
    check_output_folder(output)
    for name in OUTPUT_NAMES:
        if (output / name).is_dir() and not (output / name).is_symlink():
            raise InputError(f"{output / name}: exists and is a folder, where {name} is to be written; move it or "
                             "choose another output folder")

    outputs = written_outputs(args)
    started, begun = time.perf_counter(), time.time()
    result = register(fixed, moving, mode=args.mode, model=args.model, bandwidth=args.bandwidth, refine=args.refine,
                      device=args.device, fixed_mask=fixed_mask, moving_mask=moving_mask,
                      fixed_modality=args.fixed_modality, moving_modality=args.moving_modality,
                      resample=args.resampled, progress=_Progress(args.quiet, args.verbose, label,
                                                                  args.progress == "json"))
    low = not result.confidence >= args.min_confidence  # NaN is never confident
    report = registration_report(result, fixed=fixed, moving=moving, fixed_mask=fixed_mask, moving_mask=moving_mask,
                                 min_confidence=args.min_confidence, outputs=list(outputs))
    report["timings_s"] = {**report["timings_s"], "total": time.perf_counter() - started}  # not result.timings
    report["request"] = _request(fixed, moving, fixed_mask, moving_mask, args, result.bandwidth)

    # Stage everything in a hidden folder inside the output folder (one file system, so the moves are renames), then
    # move it in: a failed or interrupted run leaves no partial result, nor the folders it created.
    created = [folder for folder in (output, *output.absolute().parents) if not folder.exists()]
    for stale in output.glob(".dpcn-med-*"):  # staging left by a run killed outright (SIGKILL, a power cut)
        with contextlib.suppress(OSError):
            if stale.is_dir() and not stale.is_symlink() and stale.stat().st_mtime < begun:
                shutil.rmtree(stale)
    staging, finished = None, False
    try:
        staging = _make_folder(output, staging=True)
        io.write_transform(result.fixed_to_moving, staging / "transform.tfm")
        io.write_transform(result.fixed_to_moving, staging / "transform.h5")
        io.write_transform(result.moving_to_fixed, staging / "inverse.tfm")
        io.write_transform(result.moving_to_fixed, staging / "inverse.h5")
        if args.resampled:
            io.write_image(result.resampled, staging / "moving_resampled.nii.gz")
        if args.overview:
            overview_figure(result.fixed_image, result.moving_image, result.fixed_to_moving, staging / "overview.png",
                            title=f"{Path(moving).name} onto {Path(fixed).name}: confidence {result.confidence:.3f}, "
                            f"overlap {result.overlap:.0%}",
                            centre=result.fixed_grid.centre)  # the fixed foreground centre, already found
        io.write_json(report, staging / "report.json")
        earlier = _earlier_outputs(output)
        with io.interrupts_deferred():  # Ctrl-C between two renames would leave two runs' files side by side
            (output / "report.json").unlink(missing_ok=True)  # first: killed outright, the pair reads as unfinished
            # An earlier run's files this one does not write would read as this one's; a file its report does not
            # list is not known to be a run's (the user's own overview.png), and stays.
            for name in earlier - set(outputs):
                (output / name).unlink(missing_ok=True)
            for name in outputs:  # report.json last: it marks the pair as finished
                os.replace(staging / name, output / name)
            finished = True
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        if not finished:
            for folder in created:  # deepest first; one holding anything else stays
                try:
                    folder.rmdir()
                except OSError:
                    break
    return (EXIT_LOW_CONFIDENCE if low else EXIT_OK), report


def _earlier_outputs(output: Path) -> set[str]:
    """The files of :data:`OUTPUT_NAMES` that the report.json of an earlier run in ``output`` lists (none if there is
    no readable one)."""
    from dpcn_med import io

    try:
        return set(OUTPUT_NAMES) & set(io.read_json(output / "report.json")["outputs"])
    except (InputError, KeyError, TypeError):  # none, unreadable, or not a report
        return set()


def written_outputs(args: argparse.Namespace) -> tuple[str, ...]:
    """The files of :data:`OUTPUT_NAMES` that ``register`` writes with these options, in writing order."""
    skipped = {"moving_resampled.nii.gz": not args.resampled, "overview.png": not args.overview}
    return tuple(name for name in OUTPUT_NAMES if not skipped.get(name, False))


def _summary_line(report: dict) -> str:
    final = report["final"]
    shift = ", ".join(f"{v:.1f}" for v in final["translation_mm"])
    start = ", refined from the stored pose" if report["start"] == "stored pose" else ""
    return (f"rotation {final['rotation_degrees']:.1f} deg, scale {final['scale']:.4f}, translation ({shift}) mm, "
            f"confidence {report['confidence']:.3f}{start}, {report['timings_s']['total']:.1f} s")


def _register(args: argparse.Namespace) -> int:
    code, report = register_pair(args.fixed, args.moving, args.output, args, fixed_mask=args.fixed_mask,
                                 moving_mask=args.moving_mask)
    if not args.quiet:
        print(_summary_line(report))
        if args.verbose:
            for stage, seconds in report["timings_s"].items():
                print(f"  {stage:<28s}{seconds * 1000:10.1f} ms")
        print(f"outputs in {args.output}/: {', '.join(report['outputs'])}")
    if code == EXIT_LOW_CONFIDENCE:
        look = (f"look at {args.output / 'overview.png'}" if args.overview
                else "check it (rerun without --no-overview for overview.png)")
        print(f"dpcn-med: warning: confidence {report['confidence']:.4f} is below {args.min_confidence}; the result "
              f"is written but may be wrong: {look}", file=sys.stderr)
    return code


def _path_cell(value: str | None) -> str:
    """A pairs-file cell that must hold a path (a short row leaves ``None``)."""
    if not value or not value.strip():
        raise ValueError("a fixed or moving path is missing")
    return value.strip()


def _read_pairs(path: Path) -> list[dict[str, str | None]]:
    """The pairs of a pairs file, paths resolved against its folder (``~`` is the home folder, as in a shell); a row
    without an id gets ``NNN-STEM`` (its place among the rows and the moving file's name up to its first dot).

    Raises:
        InputError: naming the file and line: a missing path, an unknown column or an extra cell, a NUL character in
            a path, or an id that is repeated (case aside) or is not a folder name (empty, '.', '..', 'summary.csv',
            a slash, a control character, over 255 bytes).
    """
    from dpcn_med import io

    rows = io.read_csv(path, {"fixed": _path_cell, "moving": _path_cell}, allowed=PAIR_COLUMNS)
    if not rows:
        raise InputError(f"{path}: no pairs (a header row with at least the columns fixed,moving, then a row a pair)")
    pairs, seen = [], {}
    for index, (line, row) in enumerate(rows, start=1):
        pair_id = (row.get("id") or f"{index:03d}-{Path(row['moving']).name.split('.')[0]}").strip()
        if pair_id.casefold() in seen:  # Sub01 and sub01 would share one folder on macOS and Windows
            first_line, first = seen[pair_id.casefold()]
            alike = ("" if first == pair_id
                     else f" ({first!r}: ids that differ only in case share a folder on macOS and Windows)")
            raise InputError(f"{path}: line {line}: id {pair_id!r} is repeated (case aside): line {first_line} has "
                             f"it{alike}; give every pair its own id")
        if (pair_id in ("", ".", "..", "summary.csv") or any(c in pair_id for c in "/\\")
                or any(ord(c) < 32 for c in pair_id) or len(pair_id.encode()) > 255):
            raise InputError(f"{path}: line {line}: id {pair_id!r} is not a folder name inside the output folder "
                             "(empty, '.', '..', 'summary.csv', a slash, a control character, or over 255 bytes)")
        seen[pair_id.casefold()] = (line, pair_id)
        cells = {key: (row.get(key) or "").strip() for key in ("fixed", "moving", "fixed_mask", "moving_mask")}
        if any("\0" in value for value in cells.values()):
            raise InputError(f"{path}: line {line}: a path holds a NUL character")
        pairs.append({"id": pair_id, **{key: str(path.parent / os.path.expanduser(value)) if value else None
                                        for key, value in cells.items()}})
    return pairs


def _request(fixed: str, moving: str, fixed_mask: str | None, moving_mask: str | None,
             args: argparse.Namespace, bandwidth: int) -> dict:
    """What a registration was asked for (report.json's ``request``): the inputs, resolved, and the options that
    change its result (``bandwidth`` resolved: ``--bandwidth`` or the model's). A batch rerun reuses an earlier
    result only if this matches."""
    resolved = {key: None if value is None else os.path.realpath(value) for key, value in
                (("fixed", fixed), ("moving", moving), ("fixed_mask", fixed_mask), ("moving_mask", moving_mask))}
    return {**resolved, "mode": args.mode, "bandwidth": bandwidth, "model": _model_identity(args.model),
            "refine": args.refine, "fixed_modality": args.fixed_modality, "moving_modality": args.moving_modality}


def _model_identity(model: str) -> str | dict[str, str]:
    """A model as a request names it: ``none`` for the learning-free solver, else its files' real paths and SHA-256
    (a model trained again into the same folder, or a relative path from another folder, was taken for the earlier
    one). Files that cannot be read leave their path alone: the registration then says what is wrong."""
    import hashlib

    from dpcn_med.models.weights import model_paths
    from dpcn_med.registration import LEARNING_FREE

    if model.lower() in LEARNING_FREE:
        return "none"
    identity = {}
    for kind, path in zip(("weights", "config"), model_paths(model)):
        identity[kind] = os.path.realpath(path)
        digest = hashlib.sha256()
        try:
            with open(path, "rb") as file:  # in blocks: hashlib.file_digest is Python 3.11's, and 3.10 is supported
                for block in iter(lambda: file.read(1 << 20), b""):
                    digest.update(block)
        except OSError:
            continue
        identity[f"{kind}_sha256"] = digest.hexdigest()
    return identity


def _earlier_report(folder: Path, request: dict, outputs: Sequence[str]) -> tuple[dict | None, str]:
    """The report.json a finished earlier run left in ``folder`` for this ``request`` and at least these
    ``outputs``, and else why a report there is not reused ("" when there is none, or none readable; the pair is
    then registered again)."""
    from dpcn_med import io

    if not (folder / "report.json").exists():
        return None, ""
    try:
        report = io.read_json(folder / "report.json")
        float(report["confidence"]), float(report["final"]["rotation_degrees"]), float(report["timings_s"]["total"])
    except (InputError, KeyError, TypeError, ValueError):
        return None, ""
    if report.get("request") != request:
        return None, "replaced an earlier result of other inputs or settings"
    missing = [name for name in outputs if name not in report.get("outputs", ())]
    if missing:
        return None, f"registered again: the earlier result lacks {', '.join(missing)}"
    return report, ""


def _register_batch(args: argparse.Namespace) -> int:
    from dpcn_med import io
    from dpcn_med.registration import check_options

    pairs = _read_pairs(args.pairs)
    summary = args.output / "summary.csv"
    if os.path.lexists(summary) and not summary.is_file():
        raise InputError(f"{summary}: exists and is not a file; choose another output folder")
    check_output_folder(args.output)
    _, bandwidth, _, _ = check_options(mode=args.mode, model=args.model, bandwidth=args.bandwidth,
                                       device=args.device, fixed_modality=args.fixed_modality,
                                       moving_modality=args.moving_modality)
    outputs = written_outputs(args)
    earlier = [_earlier_report(args.output / pair["id"], _request(pair["fixed"], pair["moving"], pair["fixed_mask"],
                                                                  pair["moving_mask"], args, bandwidth), outputs)
               for pair in pairs]
    # One pair's output must not replace another's input either: the second would read the first's result.
    inputs = {str(args.pairs): "this run's pairs file"}
    for pair in pairs:
        for key in ("fixed", "moving", "fixed_mask", "moving_mask"):
            if pair[key] is not None:
                inputs.setdefault(pair[key], f"the {key.replace('_', ' ')} of pair {pair['id']!r}")
    _refuse_overwriting_inputs(inputs, [summary, *(args.output / pair["id"] / name
                                                   for pair, (report, _) in zip(pairs, earlier) if report is None
                                                   for name in OUTPUT_NAMES)])
    absent = [f"{pair['id']}: {pair[key]}" for pair, (report, _) in zip(pairs, earlier) if report is None
              for key in ("fixed", "moving", "fixed_mask", "moving_mask")
              if pair[key] is not None and not os.path.exists(_split_series_folder(pair[key]))]
    if absent:  # those pairs fail as 'bad input' in their turn: a typo should not surface hours into a cohort
        print(f"dpcn-med: warning: {len(absent)} path(s) of the pairs file do not exist ({'; '.join(absent[:5])}"
              f"{'; ...' if len(absent) > 5 else ''}); those pairs will be reported as bad input", file=sys.stderr)
    rows, codes = [], []
    for index, (pair, (report, note)) in enumerate(zip(pairs, earlier), start=1):
        label = f"[{index}/{len(pairs)}] {pair['id']} "
        if report is not None:
            low = not report["confidence"] >= args.min_confidence  # NaN is never confident
            rows.append({"id": pair["id"], "status": "done earlier" + (", low confidence" if low else ""),
                         "confidence": f"{report['confidence']:.4f}",
                         "rotation_deg": f"{report['final']['rotation_degrees']:.1f}",
                         "seconds": f"{report['timings_s']['total']:.1f}", "message": ""})
            codes.append(EXIT_LOW_CONFIDENCE if low else EXIT_OK)
        else:
            codes.append(_register_row(pair, args, label, rows, note))
        _make_folder(args.output)  # after every pair: an interrupted run's summary lists what it finished
        io.write_csv(rows, summary)
    if not args.quiet:
        print(_table(rows))
        print(f"summary in {summary}")
    for code in (EXIT_INTERNAL, EXIT_INPUT, EXIT_LOW_CONFIDENCE):
        if code in codes:
            return code
    return EXIT_OK


def _split_series_folder(path: str) -> str:
    """The folder of a ``FOLDER@SERIES_UID`` path (as :func:`dpcn_med.io.read_image` splits it), else ``path``."""
    folder, _, uid = path.rpartition("@")
    return folder if uid and not os.path.exists(path) and os.path.isdir(folder) else path


def _register_row(pair: dict, args: argparse.Namespace, label: str, rows: list[dict], note: str) -> int:
    """Register one pair of a batch, append its summary row to ``rows`` (``note`` its message), print its line;
    returns its exit code."""
    try:
        code, report = register_pair(pair["fixed"], pair["moving"], args.output / pair["id"], args,
                                     fixed_mask=pair["fixed_mask"], moving_mask=pair["moving_mask"], label=label)
        rows.append({"id": pair["id"], "status": "ok" if code == EXIT_OK else "low confidence",
                     "confidence": f"{report['confidence']:.4f}",
                     "rotation_deg": f"{report['final']['rotation_degrees']:.1f}",
                     "seconds": f"{report['timings_s']['total']:.1f}", "message": note})
    except InputError as error:
        code = EXIT_INPUT
        rows.append({"id": pair["id"], "status": "bad input", "confidence": "", "rotation_deg": "", "seconds": "",
                     "message": str(error)})
    except Exception as error:  # one broken pair must not stop a cohort; it is reported and counted
        code = EXIT_INTERNAL
        rows.append({"id": pair["id"], "status": "internal error", "confidence": "", "rotation_deg": "",
                     "seconds": "", "message": f"{type(error).__name__}: {error}"})
        if args.verbose:
            traceback.print_exc()
    line = f"{label}{rows[-1]['status']} {rows[-1]['message']}".rstrip()
    if code in (EXIT_INPUT, EXIT_INTERNAL):  # errors, on stderr, -q or not
        print(line, file=sys.stderr)
    elif not args.quiet:
        print(line)
    return code


def _table(rows: list[dict[str, str]]) -> str:
    columns = ["id", "status", "confidence", "rotation_deg", "seconds"]
    widths = {c: max(len(c), *(len(r[c]) for r in rows)) for c in columns}
    lines = ["  ".join(c.ljust(widths[c]) for c in columns)]
    lines += ["  ".join(r[c].ljust(widths[c]) for c in columns) for r in rows]
    return "\n".join(lines)


def _train(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from dpcn_med.train import load_config, train

    config = load_config(args.config)
    changes = {"output": args.output, "device": args.device, "resume": False if args.restart else None}
    config = replace(config, **{k: v for k, v in changes.items() if v is not None})
    if args.steps is not None:
        config = replace(config, optimiser=replace(config.optimiser, steps=args.steps))
    check_output_folder(Path(config.output))
    _, record = train(config)
    if record:  # rank 0 only
        after = record["validation_after"] or {}
        print(f"trained {record['steps']} steps in {record['wall_seconds_this_run']:.0f} s; validation success "
              f"{100 * after.get('success', float('nan')):.1f}%; model in {Path(config.output) / 'model.safetensors'}")
    return EXIT_OK


def _benchmark(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from dpcn_med import benchmark

    config = benchmark.FULL if args.full else benchmark.QUICK
    changes = {"cases": tuple(args.cases) if args.cases else None, "trials": args.trials,
               "methods": tuple(args.methods) if args.methods else None, "seed": args.seed,
               "run_bins": tuple(args.bins) if args.bins else None}
    config = replace(config, **{k: v for k, v in changes.items() if v is not None})
    showcase: dict = {}
    check_output_folder(args.output)
    if args.combine:
        ignored = [flag for flag, value in (("--cases", args.cases), ("--methods", args.methods),
                                            ("--trials", args.trials), ("--seed", args.seed), ("--bins", args.bins))
                   if value is not None]
        if ignored:
            raise InputError(f"--combine registers nothing, so {', '.join(ignored)} cannot apply; give the folders "
                             "and -o only")
        inputs = {folder.resolve() for folder in args.combine}
        if args.output.resolve() in inputs:
            raise InputError(f"{args.output}: is an input of --combine; choose another output folder")
        rows = benchmark.combine_results(args.combine)
        settings = benchmark.combined_settings(args.combine)
    else:
        journal = benchmark.Journal(args.output / benchmark.JOURNAL, config)
        rows = benchmark.run_benchmark(config, progress=lambda line: print(line, file=sys.stderr),
                                       showcase=showcase, skip_missing=not args.methods, journal=journal)
        settings = benchmark.pose_settings(config)
    print(benchmark.write_outputs(rows, config, args.output, command=args.command_line, showcase=showcase,
                                  settings=settings))
    if not args.combine:
        done = {(row["case"], row["bin"], row["trial"], row["method"]) for row in rows}
        left = [key for key in journal.rows() if key not in done]
        if left:  # registrations of an interrupted run with more cases, methods or bins: its command goes on from them
            print(f"dpcn-med: {len(left)} registration(s) in {journal.path} are not in this run's cases, methods or "
                  "bins; kept there for the command that made them", file=sys.stderr)
        else:
            journal.path.unlink(missing_ok=True)  # its rows are in results.csv now
    return EXIT_OK


def _info(args: argparse.Namespace) -> int:
    from dpcn_med import io

    summary = io.image_summary(io.read_image(args.image))
    for key, value in summary.items():
        print(f"{key:<22s}{value}")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``dpcn-med`` with ``argv`` (default: the command line) and return its exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    args.command_line = " ".join(["dpcn-med", *(sys.argv[1:] if argv is None else argv)])
    verbose = getattr(args, "verbose", False)
    # SIGTERM (a cancel button, a job scheduler) unwinds like Ctrl-C, so staged outputs are removed.
    terminate = signal.signal(signal.SIGTERM, _interrupt) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        if args.command == "register":
            return _register(args)
        if args.command == "register-batch":
            return _register_batch(args)
        if args.command == "train":
            return _train(args)
        if args.command == "benchmark":
            return _benchmark(args)
        return _info(args)
    except InputError as error:
        print(f"dpcn-med: error: {error}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        unfinished = {"register": "nothing was written for the unfinished pair",
                      "register-batch": "nothing was written for the unfinished pair; finished pairs are kept and "
                                        "skipped when the same command runs again",
                      "train": "any checkpoint written so far is kept, and the same command resumes from it",
                      "benchmark": "the finished registrations are kept (results.partial.jsonl in the output "
                                   "folder), and the same command goes on from them"}
        print(f"dpcn-med: interrupted; {unfinished.get(args.command, 'nothing was written')}", file=sys.stderr)
        return 130
    except Exception as error:
        if verbose:
            traceback.print_exc()
        message = " ".join(str(error).split())  # one line, whatever the library raised (ITK's messages span several)
        print(f"dpcn-med: internal error: {type(error).__name__}: {message} (rerun with --verbose for the traceback)",
              file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        if terminate is not None:
            signal.signal(signal.SIGTERM, terminate)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt
