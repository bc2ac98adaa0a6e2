"""``dpcn-med``: register volumes from the command line (thin over :mod:`dpcn_med.outputs` and :mod:`dpcn_med.batch`).

Exit codes: 0 success; 2 bad input (one line on stderr naming the file and the problem, nothing written); 3 result
written but flagged as likely wrong (its success probability below ``--min-probability``, or with ``--no-refine`` the
solver's confidence below ``--min-confidence``; every refined ultrasound registration, which nothing verifies yet);
130 interrupted (Ctrl-C or SIGTERM), nothing written for the unfinished pair; 1 internal error.
"""

from __future__ import annotations

import argparse
import atexit
import json
import math
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

from dpcn_med import __version__
from dpcn_med.errors import InputError
from dpcn_med.modalities import MODALITIES
from dpcn_med.outputs import MIN_CONFIDENCE, OUTPUT_NAMES, RegistrationSettings, check_output_folder, unverified

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_LOW_CONFIDENCE = 0, 1, 2, 3


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dpcn-med", description="Initialisation-free rigid / similarity "
                                     "registration of CT, MRI and ultrasound volumes (DPCN++ phase correlation).")
    parser.add_argument("--version", action="version", version=f"dpcn-med {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    options = _registration_options()
    tracebacks = argparse.ArgumentParser(add_help=False)  # the commands without the loudness options
    tracebacks.add_argument("-v", "--verbose", action="store_true", help="print the traceback of an internal error")
    _add_register_commands(commands, options)
    _add_train_command(commands, tracebacks)
    _add_benchmark_command(commands, tracebacks)
    info = commands.add_parser("info", parents=[tracebacks], help="print an image's geometry and intensity range")
    info.add_argument("image", help="image file or DICOM folder")
    return parser


def _registration_options() -> argparse.ArgumentParser:
    """The options of ``register`` and ``register-batch`` (a parent parser)."""
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
    options.add_argument("--fixed-modality", default="auto", choices=MODALITIES)
    options.add_argument("--moving-modality", default="auto", choices=MODALITIES)
    options.add_argument("--min-probability", type=_probability, default=None,
                         help="exit with code 3 when the result's success probability (the quality model's, from "
                         "the refined result) is below this (default: the model's threshold)")
    options.add_argument("--min-confidence", type=_finite_float, default=MIN_CONFIDENCE,
                         help="with --no-refine (no success probability): exit with code 3 below this solver "
                         f"confidence (default {MIN_CONFIDENCE})")
    options.add_argument("--no-overview", dest="overview", action="store_false",
                         help="do not draw overview.png (saves about a third of a second on a 1 mm head)")
    options.add_argument("--no-resampled", dest="resampled", action="store_false",
                         help="do not write moving_resampled.nii.gz")
    options.add_argument("--progress", choices=("auto", "json"), default="auto",
                         help="auto (default): a bar on a terminal; json: one JSON object per line on stdout, "
                         '{"stage": ..., "fraction": ...}, for programs that drive dpcn-med (the Slicer module)')
    loudness = options.add_mutually_exclusive_group()
    loudness.add_argument("-q", "--quiet", action="store_true", help="print errors only")
    loudness.add_argument("-v", "--verbose", action="store_true", help="print timings; tracebacks on errors")
    return options


def _add_register_commands(commands, options: argparse.ArgumentParser) -> None:
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
    engines = batch.add_mutually_exclusive_group()
    engines.add_argument("--workers", type=count_type(), metavar="N",
                         help="register N pairs at a time on a local Dask cluster of N single-threaded processes "
                         "(needs dpcn_med[cluster])")
    engines.add_argument("--scheduler", metavar="ADDRESS",
                         help="register on the running Dask cluster at ADDRESS (tcp://HOST:8786); its workers read "
                         "the inputs and write the outputs by the same paths (shared storage; needs dpcn_med[cluster])")


def _add_train_command(commands, tracebacks: argparse.ArgumentParser) -> None:
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


def _add_benchmark_command(commands, tracebacks: argparse.ArgumentParser) -> None:
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


def _probability(text: str) -> float:
    value = _finite_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a probability in [0, 1]")
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


def _settings(args: argparse.Namespace) -> RegistrationSettings:
    return RegistrationSettings(mode=args.mode, model=args.model, bandwidth=args.bandwidth, refine=args.refine,
                                device=args.device, fixed_modality=args.fixed_modality,
                                moving_modality=args.moving_modality, min_confidence=args.min_confidence,
                                min_probability=args.min_probability,
                                resampled=args.resampled, overview=args.overview)


def _summary_line(report: dict) -> str:
    final = report["final"]
    shift = ", ".join(f"{v:.1f}" for v in final["translation_mm"])
    start = ", refined from the stored pose" if report["start"] == "stored pose" else ""
    probability = report.get("success_probability")
    quality = "" if probability is None else f"success probability {probability:.0%}, "
    return (f"rotation {final['rotation_degrees']:.1f} deg, scale {final['scale']:.4f}, translation ({shift}) mm, "
            f"{quality}confidence {report['confidence']:.3f}{start}, {report['timings_s']['total']:.1f} s")


def _flag_message(report: dict, settings: RegistrationSettings, look: str) -> str:
    """The warning for a flagged result: the number that flagged it, what it measures, and what to look at."""
    probability = report.get("success_probability")
    if probability is None and unverified(report):
        return ("dpcn-med: warning: the result is not verified: nothing yet tells a right ultrasound registration "
                "from a wrong one, and from any pose but a nearly right stored one (a tracked probe's) dpcn_med "
                f"registers none yet (docs/benchmarks/ultrasound.md). It is written: {look}")
    if probability is None:
        return (f"dpcn-med: warning: confidence {report['confidence']:.4f} is below {settings.min_confidence}; the "
                f"result is written but may be wrong: {look}")
    message = (f"dpcn-med: warning: the result is likely wrong: its success probability is {probability:.0%}, below "
               f"{settings.probability_threshold:.0%} (the images agree little at the result, "
               f"{report['overlap_fraction']:.0%} of the fixed foreground overlaps the moving volume). It is written: "
               f"{look}. ")
    mirrored = report.get("mirrored") or {}
    if mirrored.get("likely"):
        return message + (f"The moving volume looks mirrored: flipped left to right it registers with success "
                          f"probability {mirrored['success_probability']:.0%}. Check its header's orientation "
                          "(a left-right flip); the result written is of the volume as it is")
    return message + ("Check that both volumes show the same anatomy, that enough of it is in both, and that neither "
                      "header is flipped left to right")


def _register(args: argparse.Namespace) -> int:
    from dpcn_med.outputs import register_to_folder

    settings = _settings(args)
    report = register_to_folder(args.fixed, args.moving, args.output, settings=settings, fixed_mask=args.fixed_mask,
                                moving_mask=args.moving_mask,
                                progress=_Progress(args.quiet, args.verbose, "", args.progress == "json"))
    if not args.quiet:
        print(_summary_line(report))
        if args.verbose:
            for stage, seconds in report["timings_s"].items():
                print(f"  {stage:<28s}{seconds * 1000:10.1f} ms")
        print(f"outputs in {args.output}/: {', '.join(report['outputs'])}")
    if settings.flagged(report):
        look = (f"look at {args.output / 'overview.png'}" if args.overview
                else "check it (rerun without --no-overview for overview.png)")
        print(_flag_message(report, settings, look), file=sys.stderr)
        return EXIT_LOW_CONFIDENCE
    return EXIT_OK


_STATUS_CODES = {"bad input": EXIT_INPUT, "internal error": EXIT_INTERNAL, "low confidence": EXIT_LOW_CONFIDENCE,
                 "done earlier, low confidence": EXIT_LOW_CONFIDENCE}


def _register_batch(args: argparse.Namespace) -> int:
    from dpcn_med.batch import FAILED, plan_batch, run_batch

    if args.workers is not None or args.scheduler is not None:
        from dpcn_med.cluster import require_dask

        require_dask()
    batch = plan_batch(args.pairs, args.output, settings=_settings(args))
    if batch.missing:  # those pairs fail as 'bad input' in their turn: a typo should not surface hours into a cohort
        print(f"dpcn-med: warning: {len(batch.missing)} path(s) of the pairs file do not exist "
              f"({'; '.join(batch.missing[:5])}{'; ...' if len(batch.missing) > 5 else ''}); those pairs will be "
              "reported as bad input", file=sys.stderr)
    total = len(batch.jobs)

    def label(job) -> str:
        return f"[{job.index}/{total}] {job.id} "

    def show(job, row: dict, error: Exception | None) -> None:
        if row["status"].startswith("done earlier"):
            return
        if error is not None and args.verbose:
            traceback.print_exception(type(error), error, error.__traceback__)
        line = f"{label(job)}{row['status']} {row['message']}".rstrip()
        if row["status"] in FAILED:  # errors, on stderr, -q or not
            print(line, file=sys.stderr)
        elif not args.quiet:
            print(line)

    rows = run_batch(batch, on_row=show, workers=args.workers, scheduler=args.scheduler,
                     progress_for=lambda job: _Progress(args.quiet, args.verbose, label(job), args.progress == "json"),
                     status=None if args.quiet else lambda line: print(f"  {line}", file=sys.stderr))
    if not args.quiet:
        print(_table(rows))
        print(f"summary in {batch.summary}")
    codes = {_STATUS_CODES.get(row["status"], EXIT_OK) for row in rows}
    for code in (EXIT_INTERNAL, EXIT_INPUT, EXIT_LOW_CONFIDENCE):
        if code in codes:
            return code
    return EXIT_OK


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


EXIT_FLUSH_FAILED = 120
"""The exit code where the command succeeded but its output could not be flushed (Python's own, in that case)."""


def run() -> NoReturn:
    """The ``dpcn-med`` command (its console script and ``python -m dpcn_med``): :func:`main` on the command line,
    then :func:`exit_now`. :func:`main` itself returns, for callers in Python."""
    exit_now(main())


def exit_now(code: int) -> NoReturn:
    """End the process with ``code`` as the interpreter would, less its teardown of every module.

    The exit handlers run (:mod:`atexit`: logging's flush, weakref finalisers such as temporary folders') and the
    standard streams are flushed, then the process ends (``os._exit``) without the interpreter clearing its modules
    one by one: with torch imported that took 0.7-0.8 s of each command on 2 CPU cores, against 30 ms without
    (docs/benchmarks.md, "Time of a command-line registration"). Where another non-daemon thread still runs, the
    interpreter exits as usual, which waits for it. A stream that cannot be flushed gives
    :data:`EXIT_FLUSH_FAILED` in place of success, as Python does.
    """
    if any(thread is not threading.current_thread() and not thread.daemon and thread.is_alive()
           for thread in threading.enumerate()):
        sys.exit(code)
    atexit._run_exitfuncs()  # what the interpreter runs at exit, public in all but name since Python 2
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``), a closed stream
            code = code or EXIT_FLUSH_FAILED
    os._exit(code)
