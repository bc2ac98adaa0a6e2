"""Two `dpcn-med benchmark` runs of one method on the same poses, side by side: seconds, success, TRE and memory.

Run the benchmark twice, one tree after the other on an idle machine (the same ``--full``, ``--trials`` and ``--seed``,
so the poses are the same), then join the two ``results.csv`` pose by pose. The ratio is the median of the per-pose
ratios of seconds (before / after), which the machine's drift between the runs moves less than a ratio of medians.

    dpcn-med benchmark --full --trials 2 --methods dpcn -o BEFORE   # in the older tree
    dpcn-med benchmark --full --trials 2 --methods dpcn -o AFTER
    python benchmarks/compare_runs.py BEFORE/results.csv AFTER/results.csv --labels e7efb34 b4f114f \\
        --output docs/benchmarks/refine_speed.md
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import generated_by, publish, read_unique_rows  # noqa: E402  (the scripts' shared helpers)

from dpcn_med.benchmark import SUCCESS_MM
from dpcn_med.errors import InputError

FIELDS = {"case": str, "bin": str, "trial": int, "method": str, "tre_mm": float, "seconds": float, "peak_mib": float}


def _rows(path: Path) -> dict[tuple, dict]:
    rows = read_unique_rows([path], FIELDS, key=lambda row: (row["case"], row["bin"], row["trial"], row["method"]),
                            shown=lambda row: f"{row['case']} {row['bin']} #{row['trial']} {row['method']}")
    return {(row["case"], row["bin"], row["trial"], row["method"]): row for row in rows}


def compare(before: dict[tuple, dict], after: dict[tuple, dict], labels: tuple[str, str]) -> str:
    """The markdown table, one line per case and method, over the poses both runs registered (by key)."""
    common = sorted(before.keys() & after.keys())
    if not common:
        raise InputError("the two runs share no pose (case, bin, trial, method): were they run with the same --full, "
                         "--trials and --seed?")
    first, second = labels
    lines = [f"| case | method | poses | {first} median s | {second} median s | per-pose ratio (median) | "
             f"success {first} / {second} | median TRE mm {first} / {second} | median peak MiB {first} / {second} |",
             "|---|---|---|---|---|---|---|---|---|"]
    groups = sorted({key[0::3] for key in common})
    for case, method in groups:
        keys = [key for key in common if key[0] == case and key[3] == method]
        old, new = [before[key] for key in keys], [after[key] for key in keys]

        def median(rows: list[dict], field: str) -> float:
            return statistics.median(row[field] for row in rows)

        ratio = statistics.median(a["seconds"] / b["seconds"] for a, b in zip(old, new))
        success = [sum(row["tre_mm"] < SUCCESS_MM for row in rows) for rows in (old, new)]
        lines.append(f"| {case} | {method} | {len(keys)} | {median(old, 'seconds'):.2f} | {median(new, 'seconds'):.2f} "
                     f"| {ratio:.2f}x | {success[0]} / {success[1]} | {median(old, 'tre_mm'):.2f} / "
                     f"{median(new, 'tre_mm'):.2f} | {median(old, 'peak_mib'):.0f} / {median(new, 'peak_mib'):.0f} |")
    only = len(before.keys() ^ after.keys())
    if only:
        lines.append(f"\n{only} registration(s) in one run only are left out.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path, help="the older run's results.csv")
    parser.add_argument("after", type=Path, help="the newer run's results.csv")
    parser.add_argument("--labels", nargs=2, default=["before", "after"], metavar=("BEFORE", "AFTER"))
    parser.add_argument("--note", default="", help="a sentence on how the runs were made")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        table = compare(_rows(args.before), _rows(args.after), tuple(args.labels))
    except InputError as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    head = (f"# Side by side: {args.labels[0]} and {args.labels[1]}\n\n{generated_by(__file__, argv)}: the same poses "
            f"registered by each, one run after the other; success is a TRE under {SUCCESS_MM:g} mm over the fixed "
            f"foreground's box; the ratio is the median of the per-pose ratios of seconds. {args.note}".rstrip())
    return publish(f"{head}\n\n{table}\n", args.output)


if __name__ == "__main__":
    sys.exit(main())
