"""dpcn_med: initialisation-free CT / MRI / ultrasound registration by differentiable phase correlation (DPCN++).

``dpcn_med.register(fixed, moving, ...)`` is the public entry point (:mod:`dpcn_med.registration`).
"""

__version__ = "0.1.0"

__all__ = ["RegistrationResult", "__version__", "register"]


def __getattr__(name: str):
    # The public API is imported on first use, so that `dpcn-med --help` and `import dpcn_med.io` do not pay for
    # torch and MONAI.
    if name in ("RegistrationResult", "register"):
        from dpcn_med import registration

        return getattr(registration, name)
    raise AttributeError(f"module 'dpcn_med' has no attribute {name!r}")
