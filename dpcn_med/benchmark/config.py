"""What a benchmark run registers: the configuration, its two presets, and the success threshold."""

from __future__ import annotations

from dataclasses import dataclass

SUCCESS_MM = 2.0
"""A registration succeeds with a target registration error under this, mm."""
BIN_DEGREES = 30
"""Width of the default initial-rotation bins, degrees."""


@dataclass(frozen=True)
class BenchmarkConfig:
    """What to run.

    Attributes:
        cases: keys of :data:`dpcn_med.benchmark.CASES`.
        methods: keys of :data:`dpcn_med.benchmark.METHODS`; every installed one when empty.
        bins: initial-rotation bins in degrees, ``(low, high)``.
        trials: pairs per case and bin.
        max_shift_mm: translation length up to this.
        seed: of the poses.
        run_bins: names (``"90-120"``) of the bins to register, all when empty; a pose follows from the case, the
            seed, the trials and the bins (one random stream per case, drawn bin after bin, ``trials`` poses each),
            so a run split over processes by bin registers the same poses as one run with the same trials.
    """

    cases: tuple[str, ...] = ("mni", "mni-pseudo-ct")
    methods: tuple[str, ...] = ()
    bins: tuple[tuple[int, int], ...] = tuple((low, low + BIN_DEGREES) for low in range(0, 180, BIN_DEGREES))
    trials: int = 1
    max_shift_mm: float = 60.0
    seed: int = 0
    run_bins: tuple[str, ...] = ()


QUICK = BenchmarkConfig(methods=("dpcn", "dpcn-global", "sitk-geometry", "sitk-moments", "sitk-exhaustive",
                                 "ants-rigid", "elastix-rigid"))
"""A few minutes on a CPU: the built-in volumes, one pose per bin, every method but ANTs' multi-start (its cost:
docs/design_notes/benchmark.md)."""
FULL = BenchmarkConfig(cases=("mni", "mni-pseudo-ct", "seg3d", "seg3d-pseudo-ct", "t1-flair"), trials=10)
"""The documented run (docs/benchmarks.md): the shared real volumes too, ten poses per bin."""
