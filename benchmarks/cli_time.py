"""Wall time of `dpcn-med register` as a user runs it: a fresh process per registration, from start to written outputs.

The pair is the built-in demo's (:func:`dpcn_med.demo.demo_pair`: the MNI152 head T1 and its pseudo-CT moved by 150
degrees, 1 mm, 197 x 233 x 189), written once as NIfTI, or ``--pair FIXED MOVING``. Each run is timed from outside
(process start, imports, the registration, the outputs and the overview figure) and its report's stage timings are
read back; the table gives medians and the time outside the registration (``wall - total``: interpreter start,
imports, writing).

``--compare TREE`` times another source tree (say, a clone at an older commit) with the same Python, alternating run
by run with this one, so that both see the same machine.

    python benchmarks/cli_time.py [--repeats 5] [--compare /tmp/old_clone] [--output docs/benchmarks/cli_time.md]
    python benchmarks/cli_time.py --pair ../shared/data/mridir/mridir_t2_1p0mm.nii.gz \
        ../shared/data/mridir/mridir_ct_1p0mm.nii.gz --output /tmp/cli_time_mridir.md
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import (  # noqa: E402  (the scripts' shared helpers)
    count_type,
    generated_by,
    publish,
    source_label,
    source_trees,
    tree_environment,
)

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("read", "preprocess", "solve", "refine", "resample", "total")
VARIANTS = {  # name: extra options of `dpcn-med register`
    "defaults": [],
    "no-refine": ["--no-refine"],
    "slicer": ["--no-overview", "--no-resampled"],  # what the Slicer module runs when no output volume is asked for
}


def _run(tree: Path, fixed: Path, moving: Path, extra: list[str], folder: Path) -> dict[str, float]:
    """One registration in a fresh process with ``tree`` (absolute: the process runs in ``folder``) first on the path:
    its wall time and report timings."""
    from dpcn_med.cli import EXIT_LOW_CONFIDENCE, EXIT_OK

    output = folder / "out"
    command = [sys.executable, "-m", "dpcn_med", "register", str(fixed), str(moving), "-o", str(output), "-q", *extra]
    started = time.perf_counter()
    code = subprocess.run(command, env=tree_environment(tree), cwd=folder).returncode
    wall = time.perf_counter() - started
    if code not in (EXIT_OK, EXIT_LOW_CONFIDENCE):  # low confidence is a result written like any other
        raise subprocess.CalledProcessError(code, command)
    timings = json.loads((output / "report.json").read_text())["timings_s"]
    shutil.rmtree(output)
    return {"wall": wall, **{stage: timings.get(stage, 0.0) for stage in STAGES}}


def table(results: dict[tuple[str, str], list[dict[str, float]]]) -> str:
    """Markdown: one row per (tree, variant), medians in seconds."""
    lines = ["| source | options | runs | wall (s) | " + " | ".join(STAGES) + " | outside the registration |",
             "|---|---|---|---|" + "---|" * len(STAGES) + "---|"]
    for (tree, variant), runs in results.items():
        median = {key: statistics.median(run[key] for run in runs) for key in ("wall", *STAGES)}
        outside = statistics.median(run["wall"] - run["total"] for run in runs)
        lines.append(f"| {tree} | {variant} | {len(runs)} | {median['wall']:.2f} | "
                     + " | ".join(f"{median[stage]:.2f}" for stage in STAGES) + f" | {outside:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=count_type(), default=5, help="runs per source tree and options")
    parser.add_argument("--compare", type=Path, nargs="*", default=[], help="other source trees, alternated with this")
    parser.add_argument("--pair", type=Path, nargs=2, metavar=("FIXED", "MOVING"), help="default: the demo's pair")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                        help="option sets to time (a --compare tree must know their options)")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "cli_time.md")
    args = parser.parse_args(argv)
    trees = source_trees(parser, ROOT, args.compare)  # resolved: the runs' working folder is a temporary one

    from dpcn_med import io
    from dpcn_med.demo import demo_pair

    labels = [source_label(tree) for tree in trees]
    results: dict[tuple[str, str], list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="dpcn-med-cli-time-") as name:
        folder = Path(name)
        if args.pair:
            fixed, moving = (path.resolve() for path in args.pair)
            what = f"`{args.pair[0]}` (fixed) and `{args.pair[1]}` (moving)"
        else:
            fixed, moving = folder / "mr_t1.nii.gz", folder / "ct_moved.nii.gz"
            what = "the built-in demo pair (MNI152 head T1, 1 mm, and its pseudo-CT moved by 150 degrees)"
            mr, ct, _ = demo_pair()
            io.write_image(mr, fixed)
            io.write_image(ct, moving)
        for repeat in range(args.repeats):  # sources and option sets alternate: each sees the same machine
            for variant in args.variants:
                for tree, label in zip(trees, labels, strict=True):
                    run = _run(tree, fixed, moving, VARIANTS[variant], folder)
                    results.setdefault((label, variant), []).append(run)
                    print(f"{label} {variant} #{repeat + 1}: {run['wall']:.2f} s", file=sys.stderr)
    options = "; ".join(f"{variant}: `{' '.join(VARIANTS[variant]) or 'none'}`" for variant in args.variants)
    text = (f"# Command-line registration time\n\n{generated_by(__file__, argv)}, {os.cpu_count()} CPU cores; "
            f"`dpcn-med register` on {what}, a fresh process per run, sources and options alternated run by run. "
            "Medians in seconds; stages from report.json; `outside` is the wall time less the registration "
            f"(interpreter start, imports, writing the outputs and the overview figure). Options: {options}.\n\n"
            + table(results) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
