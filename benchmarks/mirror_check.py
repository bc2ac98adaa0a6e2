"""How often the mirror check names a left-right flip, on mirrored heads and on other flagged results.

A result the quality model flags is registered again with its moving volume mirrored left to right
(``dpcn_med.outputs.check_mirrored``, report.json's ``mirrored``). This script counts, on new poses of
``quality_fit.py``'s cases (its mirrored heads, deliberate failures and 40% slabs), how often the flag fires on
successes and on failures, and how often the check then says "mirrored": where the moving volume is mirrored, and
where it is not.

    python benchmarks/mirror_check.py [--trials 6] [--output docs/benchmarks/mirror_check.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)
from quality_fit import cases, poses  # noqa: E402  (the same cases and poses)

from dpcn_med.benchmark import SUCCESS_MM
from dpcn_med.evaluation import foreground_corners, target_registration_error
from dpcn_med.outputs import RegistrationSettings, check_mirrored

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=count_type(), default=6, help="poses per case")
    parser.add_argument("--seed", type=count_type(0), default=1, help="of the poses (quality_fit's data used 0)")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "mirror_check.md")
    args = parser.parse_args(argv)
    from dpcn_med.registration import register

    settings = RegistrationSettings()
    chosen = [case for case in cases() if case[1] in ("mirrored", "deliberate", "slab 40%")]
    lines = ["| group | pair | successes flagged | failures flagged | named mirrored | median seconds of the check |",
             "|---|---|---|---|---|---|"]
    for case in chosen:
        _, group, pair = case[:3]
        good = bad = good_flagged = bad_flagged = named = 0
        seconds = []
        for _, fixed, moving, truth in poses(case, args.trials, args.seed):
            result = register(fixed, moving)
            flagged = settings.flagged({"confidence": result.confidence,
                                        "success_probability": result.success_probability})
            wrong = group in ("mirrored", "deliberate") or target_registration_error(
                result.fixed_to_moving, truth, foreground_corners(fixed)) >= SUCCESS_MM
            good, bad = good + (not wrong), bad + wrong
            good_flagged, bad_flagged = good_flagged + (flagged and not wrong), bad_flagged + (flagged and wrong)
            if flagged:
                started = time.perf_counter()
                named += check_mirrored(result, settings, None, None)["likely"]
                seconds.append(time.perf_counter() - started)
            print(f"{group} {pair}: {bad_flagged} of {bad} failures flagged, {named} named mirrored", file=sys.stderr)
        median = sorted(seconds)[len(seconds) // 2] if seconds else float("nan")
        lines.append(f"| {group} | {pair} | {good_flagged} of {good} | {bad_flagged} of {bad} | "
                     f"{named} of {good_flagged + bad_flagged} | {median:.1f} |")
    text = (f"# The mirror check\n\n{generated_by(__file__, argv)}: each case's poses (other poses than the quality "
            "model's fit and check, by the seed) registered with the defaults; a success is a TRE under "
            f"{SUCCESS_MM:g} mm, and every mirrored and deliberate case is a failure. Each flagged result (below the "
            "quality model's threshold) registered again with its moving volume mirrored left to right; 'named "
            "mirrored' counts those whose mirrored copy then registered above the threshold. Only the mirrored "
            "heads should be named.\n\n" + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    sys.exit(main())
