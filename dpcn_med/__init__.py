"""dpcn_med: initialisation-free CT / MRI / ultrasound registration by differentiable phase correlation (DPCN++).

``dpcn_med.register(fixed, moving, ...)`` is the public entry point (the function; its module is reached with
``from dpcn_med.register import ...``).
"""

__version__ = "0.1.0"

from dpcn_med.register import RegistrationResult, register  # noqa: E402  (after __version__, which it imports)

__all__ = ["RegistrationResult", "__version__", "register"]
