"""The DPC solver (DPCN++), pure PyTorch: one module per step of the paper.

=====================  =================================================================
module                 step
=====================  =================================================================
``spectrum``           1. apodised magnitude spectrum (translation invariance)
``entropy``            1. entropy images: more rotation candidates across contrasts
``cooccurrence``       1. co-occurrence spectra: more rotation candidates across contrasts
``sphere``             2. radial aggregation onto the SOFT sphere (scale invariance)
``harmonics``          3a. spherical harmonic transform
``wigner``, ``so3``    3b. SO(3) correlation, peaks, soft arg-max and refinement (rotation)
``scale``              4. log-radius correlation (scale)
``translation``        5. phase correlation (translation)
``phase_correlation``  the N-D phase correlation, soft arg-max and sub-grid peak they share
``log_polar``          2-D: rotation and scale in one log-polar correlation
``losses``             7. the training losses
=====================  =================================================================
"""

from dpcn_med.solver.config import SolverConfig, StageTemperatures, Temperatures
from dpcn_med.solver.losses import LossWeights, PoseTarget, pose_loss
from dpcn_med.solver.solve2d import Solve2dResult, solve2d
from dpcn_med.solver.solve3d import Alternatives, Ranking, SolveResult, solve

__all__ = ["Alternatives", "LossWeights", "PoseTarget", "Ranking", "Solve2dResult", "SolveResult", "SolverConfig",
           "StageTemperatures", "Temperatures", "pose_loss", "solve", "solve2d"]
