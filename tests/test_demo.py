"""`make demo` end to end, on the built-in sample (no ../shared needed)."""

from __future__ import annotations

import re

from dpcn_med.demo import main


def test_demo_recovers_the_pose_and_reports_it(capsys):
    assert main([]) == 0
    output = capsys.readouterr().out
    errors = re.search(r"rotation error ([\d.]+)°, scale error ([\d.]+)%, translation error ([\d.]+) voxels", output)
    assert errors, output
    rotation, scale, translation = (float(value) for value in errors.groups())
    assert rotation < 5.0 and scale < 3.0 and translation < 2.0
