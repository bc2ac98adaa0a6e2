"""A benchmark's outputs: the summary per case, method and bin, its Markdown tables, the success figure and the 3-D
render of one registration."""

from __future__ import annotations

import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dpcn_med import io
from dpcn_med.benchmark.cases import CASES
from dpcn_med.benchmark.config import SUCCESS_MM, BenchmarkConfig
from dpcn_med.benchmark.methods import METHODS
from dpcn_med.benchmark.results import SETTINGS
from dpcn_med.errors import InputError
from dpcn_med.evaluation import SUCCESS_DEGREES, SUCCESS_VOXELS


def global_success(row: dict) -> bool | None:
    """Whether a registration meets the solver's own criterion of a right global estimate: its rotation within
    :data:`~dpcn_med.evaluation.SUCCESS_DEGREES` of the truth, and the fixed canonical grid's centre within
    :data:`~dpcn_med.evaluation.SUCCESS_VOXELS` canonical voxels of where the truth sends it; ``None`` for a row
    written before it was measured."""
    if math.isnan(row["rotation_error_deg"]) or math.isnan(row["centre_error_mm"]):
        return None
    return (row["rotation_error_deg"] < SUCCESS_DEGREES
            and row["centre_error_mm"] < SUCCESS_VOXELS * row["canonical_voxel_mm"])


def _share(group: list[dict], success: Callable[[dict], bool | None]) -> float:
    """The share of ``group`` that ``success`` passes, among those it measures (NaN where it measures none)."""
    measured = [outcome for outcome in map(success, group) if outcome is not None]
    return sum(measured) / len(measured) if measured else math.nan


def summarise(rows: list[dict]) -> list[dict]:
    """Per (case, method, bin): trials, success rate (TRE), the global criterion's success rate
    (:func:`global_success`; NaN for rows written before it), median TRE, median seconds, median peak MiB."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["case"], row["method"], row["bin"]), []).append(row)
    return [{"case": case, "method": method, "bin": bin_, "trials": len(group),
             "success": sum(r["tre_mm"] < SUCCESS_MM for r in group) / len(group),
             "global_success": _share(group, global_success),
             "median_tre_mm": statistics.median(r["tre_mm"] for r in group),
             "median_seconds": statistics.median(r["seconds"] for r in group),
             "median_peak_mib": statistics.median(r["peak_mib"] for r in group)}
            for (case, method, bin_), group in groups.items()]


def markdown(rows: list[dict], config: BenchmarkConfig) -> str:
    """Tables per case: success by rotation bin for every method, then the medians over all its registrations of
    the case (not of the bins' medians, which weigh a bin of one pose like one of ten) of TRE, seconds and peak MiB,
    then, where the rows measured it, the share within the global criterion by bin (:func:`global_success`)."""
    bins = [f"{low}-{high}" for low, high in config.bins]
    summary = {(r["case"], r["method"], r["bin"]): r for r in summarise(rows)}
    success = {key: cell["success"] for key, cell in summary.items()}
    shares = {key: cell["global_success"] for key, cell in summary.items()}
    lines = []
    for case in dict.fromkeys(r["case"] for r in rows):
        lines += [f"### {CASES[case][0]}", "",
                  "| method | " + " | ".join(f"{b} deg" for b in bins)
                  + " | median TRE (mm) | median s | median peak MiB |",
                  "|---|" + "---|" * (len(bins) + 3)]
        for method in dict.fromkeys(r["method"] for r in rows):
            mine = [r for r in rows if (r["case"], r["method"]) == (case, method)]
            if not mine:
                continue
            lines.append(f"| {METHODS[method][0]} | "
                         + " | ".join(f"{100 * success[(case, method, b)]:.0f}%" if (case, method, b) in success
                                      else "-" for b in bins)
                         + f" | {statistics.median(r['tre_mm'] for r in mine):.2f}"
                         + f" | {statistics.median(r['seconds'] for r in mine):.1f}"
                         + f" | {statistics.median(r['peak_mib'] for r in mine):.0f} |")
        lines += ["", *_global_table(rows, case, bins, shares)]
    return "\n".join(lines)


def _global_table(rows: list[dict], case: str, bins: list[str], shares: dict[tuple[str, str, str], float]
                  ) -> list[str]:
    """The case's ``shares`` of :func:`global_success` (:func:`summarise`'s, by case, method and bin) by method and
    bin; none where no row of the case measured it."""
    measured = [r for r in rows if r["case"] == case and global_success(r) is not None]
    if not measured:
        return []
    title = (f"Global estimate within {SUCCESS_DEGREES:g} degrees and {SUCCESS_VOXELS:g} canonical voxels "
             f"({SUCCESS_VOXELS * measured[0]['canonical_voxel_mm']:.1f} mm at the fixed grid's centre; the solver's "
             "own criterion, which a global estimate on its coarse grid can meet where it cannot meet 2 mm):")
    lines = [title, "", "| method | " + " | ".join(f"{b} deg" for b in bins) + " |", "|---|" + "---|" * len(bins)]
    for method in dict.fromkeys(r["method"] for r in measured):
        cells = [shares.get((case, method, b), math.nan) for b in bins]
        lines.append(f"| {METHODS[method][0]} | "
                     + " | ".join("-" if math.isnan(c) else f"{100 * c:.0f}%" for c in cells) + " |")
    return [*lines, ""]


def figure(summary: list[dict], config: BenchmarkConfig, path: Path) -> None:
    """Success rate against initial rotation, one panel per case, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r["case"] for r in summary))
    centres = [(low + high) / 2 for low, high in config.bins]
    bins = [f"{low}-{high}" for low, high in config.bins]
    figure_, axes = plt.subplots(1, len(cases), figsize=(4.5 * len(cases), 4.2), squeeze=False,
                                 constrained_layout=True)
    for ax, case in zip(axes[0], cases):
        for method in dict.fromkeys(r["method"] for r in summary):
            cells = {r["bin"]: r for r in summary if r["case"] == case and r["method"] == method}
            ax.plot(centres, [100 * cells[b]["success"] if b in cells else np.nan for b in bins], "o-",
                    label=METHODS[method][0], lw=2.5 if method == "dpcn" else 1.2)
        ax.set(title=CASES[case][0], xlabel="initial rotation (deg)", ylabel=f"success (TRE < {SUCCESS_MM:g} mm), %",
               ylim=(-5, 105), xticks=[b[0] for b in config.bins] + [config.bins[-1][1]])
    # Below the panels: inside one, eight methods' labels hide its curves.
    figure_.legend(*axes[0][0].get_legend_handles_labels(), loc="outside lower center", ncols=4, fontsize=7)
    with io.atomic_output(path) as staged:
        figure_.savefig(staged, dpi=110)
    plt.close(figure_)


def write_outputs(rows: list[dict], config: BenchmarkConfig, output: str | os.PathLike, *, command: str,
                  showcase: dict | None = None, settings: dict | None = None) -> str:
    """``results.csv`` (every registration), ``summary.md`` and ``success.png`` in ``output``, ``render.png``
    (:func:`dpcn_med.render.before_after`) of the ``showcase`` from :func:`~dpcn_med.benchmark.run_benchmark` where
    pyvista is installed, and :data:`~dpcn_med.benchmark.SETTINGS` holding ``settings``
    (:func:`~dpcn_med.benchmark.pose_settings`) when given; returns the summary's text."""
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    io.write_csv(rows, output / "results.csv")
    if settings is None:
        (output / SETTINGS).unlink(missing_ok=True)  # a run's before, in a folder --combine writes over
    else:
        io.write_json(settings, output / SETTINGS)
    summary = summarise(rows)
    counts = sorted({r["trials"] for r in summary})
    poses = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
    text = (f"# dpcn_med against SimpleITK, ANTs and elastix\n\nGenerated by `{command}` on "
            f"{time.strftime('%Y-%m-%d')}; {poses} pose(s) per case, method and bin, rotation angle uniform in the "
            f"bin about a uniform axis, translation up to {config.max_shift_mm:g} mm; success is a TRE under "
            f"{SUCCESS_MM:g} mm over the fixed foreground's box; medians over every registration of a case and "
            f"method; times on one CPU process; peak memory the resident-set growth during the call, the C heap's "
            f"free pages handed back before it, so it counts the memory the call itself touches.\n\n"
            f"![success against initial rotation](success.png)\n\n" + markdown(rows, config))
    if showcase:
        text += _render(showcase, output / "render.png")
    io.write_text(text, output / "summary.md")
    figure(summary, config, output / "success.png")
    return text


def _render(showcase: dict, path: Path) -> str:
    """The showcase rendered to ``path``; the summary's paragraph about it."""
    from dpcn_med import render

    what = (f"{CASES[showcase['case']][0]}, a start in the {showcase['bin']} degree bin, registered by dpcn_med with "
            "the command line's defaults")
    try:
        render.before_after(showcase["fixed"], showcase["moving"], showcase["estimate"], path, title=what)
    except InputError as error:  # pyvista is the optional mesh extra
        return f"\n3-D render skipped: {error}\n"
    return (f"\n## Before and after in 3-D\n\n{what}: the fixed volume's foreground in grey, the moving volume's "
            "brightest tissue (bone on a CT) in orange.\n\n![before and after](render.png)\n")
