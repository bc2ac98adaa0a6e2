"""dpcn_med: initialisation-free CT / MRI / ultrasound registration by differentiable phase correlation (DPCN++).

``dpcn_med.register(fixed, moving, ...)`` is the public entry point (:mod:`dpcn_med.registration`).
"""

__version__ = "0.1.0"

from dpcn_med.registration import RegistrationResult, register  # noqa: E402  (after __version__, which it imports)

__all__ = ["RegistrationResult", "__version__", "register"]
