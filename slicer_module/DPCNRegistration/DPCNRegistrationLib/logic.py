"""One registration of two volume nodes, from writing the inputs to the transform node in the scene.

:class:`Registration` is asynchronous (start, :meth:`~Registration.poll`, :meth:`~Registration.finish` or
:meth:`~Registration.cancel`) for the widget's timer; :func:`register_volumes` runs one to the end, for Slicer's
Python console and batch scripts. Neither needs Qt or the Slicer application.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from DPCNRegistrationLib import process
from DPCNRegistrationLib.process import Event, Job, Options
from DPCNRegistrationLib.transforms import base_transform_node, place_result, read_transform_file, reusable_output
from DPCNRegistrationLib.volumes import (
    image_to_volume,
    mask_on_volume,
    parent_to_world,
    transform_to_world,
    volume_to_image,
)

CONFIDENCE_ATTRIBUTE = "DPCNRegistration.Confidence"
UNVERIFIED_KEY = "negative_lc2"
"""report.json's key of a result nothing verifies yet (an ultrasound pair refined by LC2): dpcn_med's
``SIMILARITY_KEYS["lc2"]``, named here because this module reads the report without importing dpcn_med."""
WORLD_TOLERANCE = 1e-9
"""Largest change of a to-world matrix entry (mm, or unitless for rotation) taken as no change during a run."""


class RegistrationError(RuntimeError):
    """The registration process failed; the message is dpcn-med's own one-line explanation."""


@dataclass
class Result:
    """What a finished registration put into the scene."""

    transform: object
    """``vtkMRMLLinearTransformNode`` the moving volume now hangs under."""
    volume: object | None
    """``vtkMRMLScalarVolumeNode`` with the moving volume resampled onto the fixed grid, when one was asked for."""
    confidence: float
    low_confidence: bool
    """dpcn-med wrote the result but flagged it as likely wrong (exit code 3): look before trusting it."""
    overlap: float
    """Share of the fixed foreground that the result maps inside the moving volume's field of view."""
    report: dict = field(repr=False)
    """dpcn-med's report.json."""
    seconds: float = 0.0
    success_probability: float | None = None
    """How likely the result is right, by dpcn-med's quality model (``None`` without refinement)."""

    @property
    def unverified(self) -> bool:
        """An ultrasound result refined by LC2: dpcn-med flags every one (``low_confidence``), since nothing yet tells
        a right one from a wrong one."""
        return UNVERIFIED_KEY in self.report


class Registration:
    """Register ``moving`` onto ``fixed`` in a separate process, started on construction.

    Args:
        fixed, moving: scalar volume nodes, taken as shown (linear parent transforms applied).
        options: the registration's choices.
        fixed_mask, moving_mask: optional label map nodes; only the voxels of each volume under its mask's non-zero
            voxels (as shown in the views) are registered (:func:`~DPCNRegistrationLib.volumes.mask_on_volume`).
        output_transform: linear transform node to write; a new one, named for the pair, when ``None`` or when
            writing it would move other nodes (:func:`~DPCNRegistrationLib.transforms.reusable_output`).
        output_volume: scalar volume node to fill with the resampled moving volume (none when ``None``).
        python: the Python to run dpcn-med with (default :func:`process.python_executable`).
        workspace: folder for the temporary files (default the system's); they are deleted when the run ends.

    Raises:
        ValueError: a missing, empty or repeated volume, a mask that covers none of its volume, or an output that is
            one of the inputs.
    """

    def __init__(self, fixed, moving, options: Options | None = None, *, fixed_mask=None, moving_mask=None,
                 output_transform=None, output_volume=None, python: str | None = None,
                 workspace: str | None = None) -> None:
        _check_inputs(fixed, moving, output_volume, (fixed_mask, moving_mask))
        output_transform = reusable_output(output_transform, moving, moving_mask)
        _check_output_transform(fixed, moving, output_transform)
        options = options or Options()
        self.fixed, self.moving, self.options = fixed, moving, options
        self.scene = moving.GetScene()
        self.output_transform, self.output_volume = output_transform, output_volume
        self.base = base_transform_node(moving, output_transform)
        # Where the result lands depends on these; _load refuses it if either changed during the run.
        self.worlds = {"moving": transform_to_world(self.base), "fixed": parent_to_world(fixed)}
        self.started = time.perf_counter()
        self.folder = Path(tempfile.mkdtemp(prefix="DPCNRegistration-", dir=workspace))
        self.names: dict[str, str] = {}  # the temporary files' paths and the nodes they hold, for dpcn-med's messages
        try:
            paths = {}
            for role, volume, mask in (("fixed", fixed, fixed_mask), ("moving", moving, moving_mask)):
                world = self.worlds[role]
                image = volume_to_image(volume, world=world)
                paths[role] = self.folder / f"{role}.nrrd"
                sitk.WriteImage(image, str(paths[role]))
                self.names[str(paths[role])] = f"{volume.GetName()} (the {role} volume)"
                if mask is not None:
                    paths[f"{role}_mask"] = self.folder / f"{role}_mask.nrrd"
                    # Both in the frame registered in: without the output transform of an earlier run.
                    mask_world = transform_to_world(base_transform_node(mask, output_transform))
                    sitk.WriteImage(mask_on_volume(mask, volume, image, volume_world=world, mask_world=mask_world),
                                    str(paths[f"{role}_mask"]))
                    self.names[str(paths[f"{role}_mask"])] = f"{mask.GetName()} (the {role} mask)"
            self.job = Job(process.command(paths["fixed"], paths["moving"], self.folder / "result", options,
                                           fixed_mask=paths.get("fixed_mask"), moving_mask=paths.get("moving_mask"),
                                           resampled=output_volume is not None, python=python))
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise

    def poll(self) -> list[Event]:
        """What the process reported since the last call (see :class:`process.Event`)."""
        return self.job.poll()

    @property
    def finished(self) -> bool:
        return self.job.finished

    def cancel(self) -> None:
        """Stop the process without waiting for it (:meth:`process.Job.cancel`); its files are deleted once it has
        ended, by :meth:`finish` or else in the background. The scene is left as it was."""
        self.job.cancel()
        threading.Thread(target=self._delete_files_when_ended, daemon=True).start()

    def _delete_files_when_ended(self) -> None:
        self.job.wait()
        shutil.rmtree(self.folder, ignore_errors=True)

    def finish(self) -> Result:
        """Wait for the process and load its result into the scene (temporary files deleted either way).

        Raises:
            RegistrationError: the process failed or was cancelled, or its result is incomplete or unreadable;
                nothing in the scene changed.
        """
        try:
            self.job.wait()
            if self.job.cancelled:
                raise RegistrationError("the registration was cancelled")
            if self.job.returncode not in (process.EXIT_OK, process.EXIT_LOW_CONFIDENCE):
                message = self.job.error_message()
                for path, name in self.names.items():  # the files are gone; the nodes are what the user knows
                    message = message.replace(path, name)
                raise RegistrationError(message)
            return self._load(self.folder / "result")
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)

    def _load(self, folder: Path) -> Result:
        """Load dpcn-med's result ``folder`` into the scene, all or nothing: every file is read and checked before
        the first node changes.

        Raises:
            RegistrationError: a file is missing or unreadable, report.json lacks a value this module shows, or a node
                the result depends on was removed or moved while the process ran.
        """
        for node in (self.fixed, self.moving, self.base, self.output_transform, self.output_volume):
            if node is not None and not self.scene.IsNodePresent(node):
                raise RegistrationError(f"{node.GetName()}: was removed from the scene while it was being registered; "
                                        "the scene is left as it is")
        self._check_unmoved()
        report = _read_report(folder / "report.json")
        path = folder / "transform.tfm"
        _require(path)
        try:
            registration = read_transform_file(path, self.scene)
        except ValueError as error:
            raise RegistrationError(str(error)) from None
        if self.output_volume is not None:
            path = folder / "moving_resampled.nii.gz"
            _require(path)
            try:
                resampled = sitk.ReadImage(str(path))
                # First of the scene's changes: it checks the image before it touches the node.
                image_to_volume(resampled, self.output_volume)
            except (RuntimeError, ValueError) as error:
                raise RegistrationError(f"{path.name}: not a readable volume ({error})") from None
            self.output_volume.SetAndObserveTransformNodeID(None)  # on the fixed grid as shown, in world coordinates
            if self.output_volume.GetDisplayNode() is None:
                self.output_volume.CreateDefaultDisplayNodes()
        transform = self.output_transform
        if transform is None:
            transform = self.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
            transform.SetName(self.scene.GenerateUniqueName(f"{self.moving.GetName()} to {self.fixed.GetName()}"))
        place_result(registration, self.moving, self.fixed, transform, self.base)
        transform.SetAttribute(CONFIDENCE_ATTRIBUTE, f"{report['confidence']:.6g}")
        return Result(transform=transform, volume=self.output_volume, confidence=float(report["confidence"]),
                      low_confidence=self.job.returncode == process.EXIT_LOW_CONFIDENCE,
                      overlap=float(report["overlap_fraction"]), report=report,
                      seconds=time.perf_counter() - self.started,
                      success_probability=_optional_number(report.get("success_probability")))

    def _check_unmoved(self) -> None:
        """Raise :class:`RegistrationError` unless the moving volume still hangs under its base (or the output) and
        both volumes' transforms to world are those registered: the result is only right in that frame."""
        parent = self.moving.GetParentTransformNode()
        parent_id = parent.GetID() if parent is not None else None
        under_base = parent_id == (self.base.GetID() if self.base is not None else None) or (
            self.output_transform is not None and parent_id == self.output_transform.GetID())

        def unchanged(role: str, transform) -> bool:
            try:
                return np.allclose(transform_to_world(transform), self.worlds[role], rtol=0, atol=WORLD_TOLERANCE)
            except ValueError:  # made non-linear meanwhile
                return False

        for volume, kept in ((self.moving, under_base and unchanged("moving", self.base)),
                             (self.fixed, unchanged("fixed", self.fixed.GetParentTransformNode()))):
            if not kept:
                raise RegistrationError(f"{volume.GetName()}: its parent transforms changed while it was being "
                                        "registered; the scene is left as it is: apply again")


def register_volumes(fixed, moving, options: Options | None = None, *, fixed_mask=None, moving_mask=None,
                     output_transform=None, output_volume=None, progress: Callable[[str, float], None] | None = None,
                     python: str | None = None, workspace: str | None = None) -> Result:
    """Register ``moving`` onto ``fixed`` and wait for it (arguments as :class:`Registration`); ``progress`` gets
    ``(stage, fraction done)``."""
    registration = Registration(fixed, moving, options, fixed_mask=fixed_mask, moving_mask=moving_mask,
                                output_transform=output_transform, output_volume=output_volume, python=python,
                                workspace=workspace)
    try:
        while not registration.finished:
            for event in registration.poll():
                if event.kind == "progress" and progress is not None:
                    progress(event.text, event.fraction)
            time.sleep(0.05)
    except BaseException:
        registration.cancel()
        with contextlib.suppress(RegistrationError):
            registration.finish()  # no GUI to keep responsive here: wait for the process to end, delete its files
        raise
    return registration.finish()


OLDER_DPCN_MED = "the dpcn_med in Slicer's Python is older than this module; reinstall it"
REPORT_NUMBERS = ("confidence", "overlap_fraction")
"""report.json's values :class:`Result` shows; a dpcn_med too old to write them is refused before the scene changes."""


def _optional_number(value) -> float | None:
    """A report's optional number: ``None`` where it is absent or not a number."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _require(path: Path) -> None:
    """Raise :class:`RegistrationError` unless dpcn-med wrote ``path``."""
    if not path.is_file():
        raise RegistrationError(f"dpcn-med wrote no {path.name} in {path.parent}, though it exited with success; "
                                "the result is incomplete, so the scene is left as it was")


def _read_report(path: Path) -> dict:
    """dpcn-med's report.json, with :data:`REPORT_NUMBERS` checked to be numbers.

    Raises:
        RegistrationError: the file is missing, unreadable, not a JSON object, or lacks one of the numbers.
    """
    _require(path)
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RegistrationError(f"{path.name}: not a readable JSON file ({error})") from None
    if not isinstance(report, dict):
        raise RegistrationError(f"{path.name}: holds a {type(report).__name__}, expected a JSON object")
    for key in REPORT_NUMBERS:
        if key not in report:
            raise RegistrationError(f"{path.name} lacks {key}: {OLDER_DPCN_MED}")
        if isinstance(report[key], bool) or not isinstance(report[key], (int, float)):
            raise RegistrationError(f"{path.name}: {key} is {report[key]!r}, expected a number")
    return report


def _check_inputs(fixed, moving, output_volume, masks=(None, None)) -> None:
    for role, node in (("fixed", fixed), ("moving", moving)):
        if node is None:
            raise ValueError(f"choose a {role} volume")
        if not node.IsA("vtkMRMLScalarVolumeNode") or node.GetImageData() is None:
            raise ValueError(f"{node.GetName()}: the {role} volume holds no scalar image data")
    if fixed.GetID() == moving.GetID():
        raise ValueError(f"{fixed.GetName()}: is both the fixed and the moving volume; choose two volumes")
    inputs = [fixed.GetID(), moving.GetID()]
    for role, mask in zip(("fixed", "moving"), masks, strict=True):
        if mask is not None and mask.GetID() in inputs:
            raise ValueError(f"{mask.GetName()}: the {role} mask is one of the volumes being registered; choose a "
                             "label map")
    if output_volume is not None and output_volume.GetID() in inputs + [m.GetID() for m in masks if m is not None]:
        raise ValueError(f"{output_volume.GetName()}: the output volume is an input; choose or create another "
                         "(inputs are never overwritten)")


def _check_output_transform(fixed, moving, output_transform) -> None:
    if output_transform is None:
        return
    for role, parent in (("fixed", fixed.GetParentTransformNode()),
                         ("moving", base_transform_node(moving, output_transform))):
        # The moving volume directly under the output is a repeated registration; deeper, MRML would refuse to
        # put the output under the moving volume's base (a cycle) and the result would land elsewhere.
        while parent is not None:
            if parent.GetID() == output_transform.GetID():
                raise ValueError(f"{output_transform.GetName()}: the {role} volume depends on this output "
                                 "transform (through another transform); choose another output transform")
            parent = parent.GetParentTransformNode()
