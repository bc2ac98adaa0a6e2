"""Start-up of the `dpcn-med` commands that register nothing: `--help` and `info`, a fresh process each run.

Each command runs in a fresh Python process with the source tree first on the path, from interpreter start to exit.
``info`` reads a small NIfTI written once (the 2 mm MNI152 head). ``--compare TREE`` times another source tree (say,
a clone at an older commit) with the same Python, alternating run by run with this one, so both see the same machine.

    python benchmarks/startup_time.py [--repeats 10] [--compare /tmp/old_clone]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import (  # noqa: E402  (the scripts' shared helpers)
    count_type,
    generated_by,
    publish,
    source_label,
    tree_environment,
)

ROOT = Path(__file__).resolve().parents[1]


def _commands(image: Path) -> dict[str, list[str]]:
    return {"dpcn-med --help": ["--help"], "dpcn-med info IMAGE": ["info", str(image)]}


def _run(tree: Path, arguments: list[str], folder: Path) -> float:
    """Wall seconds of ``python -m dpcn_med ARGUMENTS`` with ``tree`` first on the path."""
    started = time.perf_counter()
    code = subprocess.run([sys.executable, "-m", "dpcn_med", *arguments], env=tree_environment(tree), cwd=folder,
                          stdout=subprocess.DEVNULL).returncode
    if code != 0:
        raise SystemExit(f"dpcn-med {' '.join(arguments)} with {tree} exited {code}")
    return time.perf_counter() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=count_type(), default=10, help="runs per source tree and command")
    parser.add_argument("--compare", type=Path, metavar="TREE", help="another source tree, timed alternately")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "startup_time.md")
    args = parser.parse_args(argv)
    trees = [ROOT, *([args.compare.resolve()] if args.compare else [])]

    folder = Path(tempfile.mkdtemp(prefix="startup-time-"))
    try:
        from dpcn_med.samples import mni152_t1

        image = folder / "mni_2mm.nii.gz"
        sitk.WriteImage(sitk.BinShrink(mni152_t1(), [2, 2, 2]), str(image))
        commands = _commands(image)
        seconds = {(tree, name): [] for tree in trees for name in commands}
        for _ in range(args.repeats):
            for name, arguments in commands.items():
                for tree in trees:
                    seconds[tree, name].append(_run(tree, arguments, folder))
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    lines = ["| source | command | runs | wall (s), median | min | max |", "|---|---|---|---|---|---|"]
    for name in commands:
        for tree in trees:
            values = seconds[tree, name]
            lines.append(f"| {source_label(tree)} | `{name}` | {len(values)} | {statistics.median(values):.2f} | "
                         f"{min(values):.2f} | {max(values):.2f} |")
    text = (f"# Start-up time of the commands\n\n{generated_by(__file__, argv)}, {os.cpu_count()} CPU cores; a fresh "
            "process per run, sources alternated run by run; `info` on the 2 mm MNI152 head (NIfTI).\n\n"
            + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
