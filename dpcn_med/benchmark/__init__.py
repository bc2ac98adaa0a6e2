"""``dpcn-med benchmark``: dpcn_med against SimpleITK, ANTs and elastix on the same pairs, binned by initial rotation.

Every pair is a real volume and a copy of it (or of another contrast of the same anatomy, aligned voxel for voxel)
moved by a known rigid transform: a rotation by an angle drawn uniformly inside the bin about a uniformly random axis,
and a translation of uniform direction and length up to ``max_shift_mm``. Every method registers the same pairs in
the same process; success is a target registration error under 2 mm over the corners of the fixed foreground's box.
Beside it, the solver's own criterion of a global estimate (:func:`global_success`): the rotation within 5 degrees,
the fixed canonical grid's centre within 2 canonical voxels.

Methods (``METHODS``): dpcn_med learning-free with and without its refinement; SimpleITK Mattes mutual information
(the same multi-resolution optimiser dpcn_med refines with) started from ``CenteredTransformInitializer`` GEOMETRY
or MOMENTS, or from an exhaustive search over Euler angles as in SimpleITK's registration-initialisation notebook;
ANTs ``Rigid``, alone and after its multi-start ``affine_initializer``; elastix's default rigid map. ANTs and elastix
come with the ``benchmark`` extra (``pip install 'dpcn_med[benchmark]'``); a run that asks for them without it is
refused, and the command line's default methods leave them out.

=============  ======================================================================================
module         contents
=============  ======================================================================================
``config``     :class:`BenchmarkConfig`, :data:`QUICK`, :data:`FULL`, :data:`SUCCESS_MM`
``cases``      :data:`CASES` (the aligned pairs), :func:`rotation_in_bin` (their poses)
``methods``    :data:`METHODS`, :func:`available_methods`, :data:`BASELINE_REFINEMENT`
``memory``     :func:`reset_peak_rss`, :func:`status_mib`: peak memory of one call
``runner``     :func:`run_benchmark`
``results``    ``results.csv`` read back (:func:`combine_results`), :func:`pose_settings`, :class:`Journal`,
               :data:`GLOBAL_FIELDS`
``outputs``    :func:`write_outputs`: the summary's tables, the success figure, the 3-D render;
               :func:`global_success`
=============  ======================================================================================
"""

from dpcn_med.benchmark.cases import CASES, SHARED_DATA, rotation_in_bin
from dpcn_med.benchmark.config import BIN_DEGREES, FULL, QUICK, SUCCESS_MM, BenchmarkConfig
from dpcn_med.benchmark.memory import reset_peak_rss, status_mib
from dpcn_med.benchmark.methods import BASELINE_REFINEMENT, DPCN_METHODS, METHODS, available_methods
from dpcn_med.benchmark.outputs import figure, global_success, markdown, summarise, write_outputs
from dpcn_med.benchmark.results import (
    GLOBAL_FIELDS,
    JOURNAL,
    RESULT_FIELDS,
    SETTINGS,
    Journal,
    combine_results,
    combined_settings,
    pose_settings,
)
from dpcn_med.benchmark.runner import run_benchmark

__all__ = ["BASELINE_REFINEMENT", "BIN_DEGREES", "CASES", "DPCN_METHODS", "FULL", "GLOBAL_FIELDS", "JOURNAL", "METHODS",
           "QUICK", "RESULT_FIELDS", "SETTINGS", "SHARED_DATA", "SUCCESS_MM", "BenchmarkConfig", "Journal",
           "available_methods", "combine_results", "combined_settings", "figure", "global_success", "markdown",
           "pose_settings",
           "reset_peak_rss", "rotation_in_bin", "run_benchmark", "status_mib", "summarise", "write_outputs"]
