"""The imaging modalities dpcn_med knows, by the names users give them (``--fixed-modality``, a model's config)."""

MODALITIES = ("auto", "ct", "mr", "us")
"""``"auto"`` (the intensities decide: :func:`dpcn_med.preprocess.detect_modality`), CT, MR or ultrasound."""
