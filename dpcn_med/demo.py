"""`make demo`: `dpcn-med register` on a built-in CT / MR pair, 150 degrees apart, with no initial guess.

The pair is generated in code from the MNI152 template that ships inside the nilearn wheel: a T1-weighted head
(:func:`dpcn_med.samples.mni152_head_t1`) is the fixed image; a pseudo-CT of the same head
(:func:`dpcn_med.samples.mni152_pseudo_ct`, bone bright where the MR is dark), moved by a known rigid transform, is the
moving one. The demo writes both, runs the command-line registration on them and compares the result with the truth.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med import cli, io
from dpcn_med.benchmark import SUCCESS_MM
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.preprocess import foreground_box
from dpcn_med.samples import mni152_head_t1, mni152_pseudo_ct

ROTATION_DEGREES = 150.0
ROTATION_AXIS = (0.3, -0.8, 0.5)
SHIFT_MM = (25.0, -15.0, 10.0)


def demo_pair() -> tuple[sitk.Image, sitk.Image, sitk.Transform]:
    """``(fixed MR, moving CT, fixed_to_moving truth)``: the built-in pair and the transform that relates them."""
    mr = mni152_head_t1()
    truth = sitk.VersorRigid3DTransform()
    truth.SetCenter(foreground_box(mr)[0].tolist())
    truth.SetRotation(ROTATION_AXIS, math.radians(ROTATION_DEGREES))
    truth.SetTranslation(SHIFT_MM)
    return mr, moved_copy(mni152_pseudo_ct(), truth), truth


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=cli.output_path, default=Path("demo_output"),
                        help="folder for inputs and results")
    args = parser.parse_args(argv)
    try:  # before the half minute of generating the pair
        cli.check_output_folder(args.output / "inputs")
    except InputError as error:
        print(f"dpcn-med demo: error: {error}", file=sys.stderr)
        return cli.EXIT_INPUT

    print("generating the built-in pair: MNI152 T1 head (fixed) and its pseudo-CT moved by "
          f"{ROTATION_DEGREES:.0f} degrees and {np.linalg.norm(SHIFT_MM):.0f} mm (moving)")
    mr, ct, truth = demo_pair()
    inputs = args.output / "inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    io.write_image(mr, inputs / "mr_t1.nii.gz")
    io.write_image(ct, inputs / "ct_moved.nii.gz")
    io.write_transform(truth, inputs / "truth.tfm")

    results = args.output / "registration"
    command = ["register", str(inputs / "mr_t1.nii.gz"), str(inputs / "ct_moved.nii.gz"), "-o", str(results)]
    print("dpcn-med " + " ".join(command))
    code = cli.main(command)
    if code not in (cli.EXIT_OK, cli.EXIT_LOW_CONFIDENCE):
        return code

    corners = foreground_corners(mr)
    found = io.read_transform(results / "transform.tfm")
    dpc_matrix = np.asarray(json.loads((results / "report.json").read_text())["dpc"]["fixed_to_moving_lps"])
    dpc = sitk.AffineTransform(dpc_matrix[:3, :3].flatten().tolist(), dpc_matrix[:3, 3].tolist())
    error = target_registration_error(found, truth, corners)
    print(f"target registration error against the truth: {error:.2f} mm after refinement, "
          f"{target_registration_error(dpc, truth, corners):.1f} mm for the global estimate alone")
    print(f"inputs in {inputs}/, results in {results}/ (open overview.png)")
    if error >= SUCCESS_MM:
        print(f"dpcn-med demo: the result is {error:.1f} mm from the truth (success is under {SUCCESS_MM} mm)",
              file=sys.stderr)
        return cli.EXIT_INTERNAL
    if code == cli.EXIT_LOW_CONFIDENCE:  # the demo knows the truth, which a user's registration does not
        print(f"dpcn-med register flagged the result as likely wrong (exit code {code}), yet it is {error:.2f} mm from "
              "the truth: a false alarm of the quality model (docs/benchmarks/quality.md)")
    return cli.EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
