"""Run ``dpcn-med`` in Slicer's Python (``PythonSlicer run_registration.py register ...``), for the module's Logic.

A script rather than ``python -m dpcn_med`` so that a missing installation ends with a message the module can show
(exit 2) instead of Python's ``No module named`` traceback.
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> int:
    try:
        from dpcn_med.cli import main as dpcn_med
    except ImportError as error:
        print(f"dpcn_med is not installed in this Python ({sys.executable}): {error}. Press Apply in the DPCN "
              "Registration module to install it, or pip install it into Slicer's Python.", flush=True)
        return 2
    return dpcn_med(argv)


if __name__ == "__main__":
    code = main(sys.argv[1:])
    try:
        from dpcn_med.cli import exit_now  # skips the interpreter's teardown, most of a second with torch imported
    except ImportError:  # no dpcn_med, or one older than this module: the interpreter's own exit
        sys.exit(code)
    exit_now(code)
