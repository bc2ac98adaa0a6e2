"""Wall time of the Slicer module's registration, measured through its Lib on slicer-core's MRML (no Slicer window).

The MRI-DIR CT (moving) onto its T2 (fixed), each read by Slicer's own volume storage node into a fresh scene per run;
the module's defaults (rigid, B = 32, refinement) on the CPU, no output volume. ``module`` is the Lib's wall time from
Apply to the transform node (writing the volumes, the child dpcn-med process, loading the result), ``dpcn-med`` the
registration inside the child (its report's total); the rest is the child's start, imports and files.

    python benchmarks/slicer_time.py [--resolutions 1p0mm 1p5mm] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "mridir"
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "slicer_module" / "DPCNRegistration"))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", nargs="+", default=["1p0mm", "1p5mm"], help="MRI-DIR file resolutions")
    parser.add_argument("--repeats", type=count_type(), default=3)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "slicer_time.md")
    args = parser.parse_args(argv)
    try:
        import slicer
    except ImportError:
        parser.error("needs slicer-core (pip install 'dpcn_med[test]')")
    from DPCNRegistrationLib.logic import register_volumes
    from DPCNRegistrationLib.process import Options
    from DPCNRegistrationLib.volumes import read_volume

    rows = []
    for resolution in args.resolutions:
        paths = [DATA / f"mridir_{kind}_{resolution}.nii.gz" for kind in ("t2", "ct")]
        for path in paths:
            if not path.is_file():
                parser.error(f"{path}: not found (the shared data lies in ../shared/data beside the repository)")
        module, inside = [], []
        for repeat in range(args.repeats):
            scene = slicer.vtkMRMLScene()
            fixed, moving = (read_volume(scene, path, path.name.split(".")[0]) for path in paths)
            result = register_volumes(fixed, moving, Options(device="cpu"))
            module.append(result.seconds)
            inside.append(result.report["timings_s"]["total"])
            print(f"{resolution} #{repeat + 1}: {result.seconds:.2f} s (dpcn-med {inside[-1]:.2f} s)", file=sys.stderr)
        rows.append(f"| MRI-DIR CT onto T2, {resolution.replace('p', '.')} | {len(module)} | "
                    f"{statistics.median(module):.2f} | {statistics.median(inside):.2f} | "
                    f"{statistics.median(m - i for m, i in zip(module, inside, strict=True)):.2f} |")
    text = (f"# Slicer module registration time\n\n{generated_by(__file__, argv)}, {os.cpu_count()} CPU cores; the "
            "module's Lib on slicer-core's MRML, defaults on the CPU, no output volume, a fresh scene per run. "
            "Medians in seconds.\n\n| pair | runs | module (Apply to transform node) | dpcn-med's registration | "
            "the rest (child start, imports, files) |\n|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
