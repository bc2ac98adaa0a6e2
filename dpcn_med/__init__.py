"""dpcn_med: initialisation-free CT / MRI / ultrasound registration by differentiable phase correlation (DPCN++)."""

__version__ = "0.1.0"
