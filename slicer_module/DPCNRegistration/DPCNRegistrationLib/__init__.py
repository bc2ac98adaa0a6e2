"""The Slicer-side helpers of the DPCN registration module, importable without Slicer's application or Qt.

They need MRML (``slicer`` inside 3D Slicer, or the ``slicer-core`` package on PyPI), SimpleITK and numpy, all of
which Slicer bundles, but not ``dpcn_med``: the registration itself runs in a separate Python process
(:mod:`.process`), so the module loads, and can offer to install its dependencies, before ``dpcn_med`` is there.
"""
