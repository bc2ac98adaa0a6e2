"""The methods a benchmark compares: dpcn_med's own and the local baselines (SimpleITK, ANTs, elastix).

Each is a function ``(fixed, moving, folder) -> fixed_to_moving`` (LPS mm, ITK's direction); ``folder`` is a scratch
folder for the tools that read files. ANTs and elastix come with the ``benchmark`` extra.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import SimpleITK as sitk

from dpcn_med.preprocess import dilate, foreground_mask
from dpcn_med.refine import Refinement, refine_transform
from dpcn_med.registration import register

BASELINE_REFINEMENT = Refinement(max_step_mm=2.0)
"""The SimpleITK baselines' local optimiser: dpcn_med's refinement as one SimpleITK run, every level's first step
2 mm, fixed (why: docs/design_notes/benchmark.md)."""


def _mask(fixed: sitk.Image) -> sitk.Image:
    return dilate(foreground_mask(fixed), Refinement().mask_margin_voxels)


def _sitk_initialised(kind: int) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        fixed, moving = sitk.Cast(fixed, sitk.sitkFloat32), sitk.Cast(moving, sitk.sitkFloat32)
        start = sitk.CenteredTransformInitializer(fixed, moving, sitk.VersorRigid3DTransform(), kind)
        return refine_transform(fixed, moving, start, (_mask(fixed), None), BASELINE_REFINEMENT)
    return run


def _sitk_exhaustive(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
    """Mattes MI over a grid of Euler angles (45-degree steps, 4x shrunk), then the local optimiser from the best."""
    return exhaustive_search(fixed, moving)


def exhaustive_search(fixed: sitk.Image, moving: sitk.Image, step_degrees: float = 45.0) -> sitk.Transform:
    """SimpleITK's exhaustive search: Mattes MI at every Euler angle of a grid of ``step_degrees`` (a divisor of 90:
    about x and z over the whole turn, about y over half of it), 4x shrunk, then the local optimiser from the best;
    fixed to moving."""
    steps = round(90 / step_degrees)
    fixed, moving = sitk.Cast(fixed, sitk.sitkFloat32), sitk.Cast(moving, sitk.sitkFloat32)
    start = sitk.CenteredTransformInitializer(fixed, moving, sitk.Euler3DTransform(),
                                              sitk.CenteredTransformInitializerFilter.GEOMETRY)
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsMattesMutualInformation(32)
    method.SetMetricSamplingStrategy(method.RANDOM)
    # The baselines' seed, not 0: SimpleITK takes 0 for the wall clock, a new sample (and result) on every run.
    method.SetMetricSamplingPercentage(0.05, BASELINE_REFINEMENT.seed)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetShrinkFactorsPerLevel([4])
    method.SetSmoothingSigmasPerLevel([2.0])
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    method.SetOptimizerAsExhaustive(numberOfSteps=[2 * steps, steps, 2 * steps, 0, 0, 0],
                                    stepLength=math.radians(step_degrees))
    method.SetOptimizerScales([1, 1, 1, 1, 1, 1])
    method.SetInitialTransform(start, inPlace=True)
    method.Execute(fixed, moving)
    rigid = sitk.VersorRigid3DTransform()
    rigid.SetCenter(start.GetCenter())
    rigid.SetMatrix(start.GetMatrix())
    rigid.SetTranslation(start.GetTranslation())
    return refine_transform(fixed, moving, rigid, (_mask(fixed), None), BASELINE_REFINEMENT)


def _dpcn(refine: bool) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        return register(fixed, moving, refine=refine).fixed_to_moving
    return run


def _ants(multistart: bool) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        import ants

        sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
        sitk.WriteImage(moving, str(folder / "moving.nii.gz"))
        fixed_ants = ants.image_read(str(folder / "fixed.nii.gz"))
        moving_ants = ants.image_read(str(folder / "moving.nii.gz"))
        options = {"outprefix": str(folder / "ants_")}
        if multistart:
            options["initial_transform"] = ants.affine_initializer(fixed_ants, moving_ants,
                                                                   txfn=str(folder / "initial.mat"))
        result = ants.registration(fixed_ants, moving_ants, type_of_transform="Rigid", **options)
        # ANTs' forward transforms map fixed points to moving ones (ITK's direction); the last is the rigid one.
        return sitk.ReadTransform(result["fwdtransforms"][-1])
    return run


def _elastix(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
    import itk

    sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
    sitk.WriteImage(moving, str(folder / "moving.nii.gz"))
    parameters = itk.ParameterObject.New()
    parameters.AddParameterMap(parameters.GetDefaultParameterMap("rigid"))
    _, result = itk.elastix_registration_method(itk.imread(str(folder / "fixed.nii.gz"), itk.F),
                                                itk.imread(str(folder / "moving.nii.gz"), itk.F),
                                                parameter_object=parameters, log_to_console=False,
                                                output_directory=str(folder))
    found = result.GetParameterMap(0)
    values = [float(v) for v in found["TransformParameters"]]
    # elastix's EulerTransform maps fixed points to moving ones: angles (x, y, z) in radians, then the translation.
    transform = sitk.Euler3DTransform()
    transform.SetCenter([float(v) for v in found["CenterOfRotationPoint"]])
    transform.SetComputeZYX(found["ComputeZYX"][0] == "true" if "ComputeZYX" in found else False)
    transform.SetRotation(*values[:3])
    transform.SetTranslation(values[3:])
    return transform


DPCN_METHODS = ("dpcn", "dpcn-global")
"""dpcn_med's own methods: an error of theirs stops the run (a bug to see), where a baseline's scores a failure."""

METHODS: dict[str, tuple[str, str | None, Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]]] = {
    "dpcn": ("dpcn_med learning-free + refinement (defaults)", None, _dpcn(True)),
    "dpcn-global": ("dpcn_med learning-free, global estimate only", None, _dpcn(False)),
    "sitk-geometry": ("SimpleITK MI from GEOMETRY initialiser", None,
                      _sitk_initialised(sitk.CenteredTransformInitializerFilter.GEOMETRY)),
    "sitk-moments": ("SimpleITK MI from MOMENTS initialiser", None,
                     _sitk_initialised(sitk.CenteredTransformInitializerFilter.MOMENTS)),
    "sitk-exhaustive": ("SimpleITK MI after an exhaustive Euler-angle search", None, _sitk_exhaustive),
    "ants-rigid": ("ANTs Rigid", "antspyx", _ants(False)),
    "ants-multistart": ("ANTs Rigid after affine_initializer", "antspyx", _ants(True)),
    "elastix-rigid": ("elastix rigid (default map)", "itk-elastix", _elastix),
}
"""name: (description, distribution it needs beyond dpcn_med's, ``(fixed, moving, folder) -> fixed_to_moving``)."""


def available_methods() -> tuple[str, ...]:
    """The methods whose packages are installed."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(distribution: str | None) -> bool:
        if distribution is None:
            return True
        try:
            version(distribution)
        except PackageNotFoundError:
            return False
        return True

    return tuple(name for name, (_, distribution, _) in METHODS.items() if installed(distribution))
