"""``python -m dpcn_med``: the ``dpcn-med`` command (the Slicer module runs it this way)."""

from dpcn_med.cli import run

run()
