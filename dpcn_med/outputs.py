"""A registration's files: one pair registered into one output folder, written all at once or not at all.

``register_to_folder`` runs :func:`dpcn_med.register` and writes :data:`OUTPUT_NAMES` into a folder: each file is
staged in a hidden folder inside it, then renamed into place, ``report.json`` last (it marks a finished pair). The
report's ``request`` (:func:`registration_request`) says what was asked for, so a rerun can tell whether an earlier
result answers the same question (:mod:`dpcn_med.batch`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dpcn_med import io
from dpcn_med.errors import InputError

if TYPE_CHECKING:
    from dpcn_med.registration import Progress  # at run time registration imports torch, which outputs needs not

MIN_CONFIDENCE = 0.003
"""Default threshold on the solver's confidence: a result below it is written and flagged as possibly wrong.
See docs/design_notes/outputs.md for the measurements behind it."""

OUTPUT_NAMES = ("transform.tfm", "transform.h5", "inverse.tfm", "inverse.h5", "moving_resampled.nii.gz",
                "overview.png", "report.json")
"""What :func:`register_to_folder` writes into its output folder, in writing order; ``report.json`` last."""

STAGING_PREFIX = ".dpcn-med-"
"""Name prefix of the hidden staging folder inside an output folder."""

@dataclass(frozen=True)
class RegistrationSettings:
    """What a registration is asked to do and write, as ``dpcn-med register`` takes it.

    Attributes:
        mode: ``"rigid"`` or ``"similarity"``.
        model: ``"none"`` for the learning-free solver, or a model path (``NAME.safetensors``/``.json``/``NAME``).
        bandwidth: solver bandwidth B, or ``None`` for the model's (32 without one).
        refine: run the local Mattes mutual-information refinement.
        device: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        fixed_modality, moving_modality: ``"auto"``, ``"ct"``, ``"mr"`` or ``"us"``.
        min_confidence: without refinement (no success probability), results below this solver confidence are
            flagged (NaN is never confident).
        min_probability: results whose success probability (:mod:`dpcn_med.quality`) is below this are flagged;
            ``None``: the quality model's own threshold.
        mirror_check: register a flagged result's moving volume again mirrored left to right, and report whether
            that registers (report.json's ``mirrored``): a flipped header. About one more registration's time, on
            flagged results only.
        resampled: write ``moving_resampled.nii.gz``.
        overview: draw ``overview.png``.
    """

    mode: str = "rigid"
    model: str = "none"
    bandwidth: int | None = None
    refine: bool = True
    device: str = "auto"
    fixed_modality: str = "auto"
    moving_modality: str = "auto"
    min_confidence: float = MIN_CONFIDENCE
    min_probability: float | None = None
    mirror_check: bool = True
    resampled: bool = True
    overview: bool = True

    @property
    def outputs(self) -> tuple[str, ...]:
        """The files of :data:`OUTPUT_NAMES` written with these settings, in writing order."""
        skipped = {"moving_resampled.nii.gz": not self.resampled, "overview.png": not self.overview}
        return tuple(name for name in OUTPUT_NAMES if not skipped.get(name, False))

    @property
    def probability_threshold(self) -> float:
        """:attr:`min_probability`, or the shipped quality model's threshold."""
        from dpcn_med.quality import shipped_model

        return self.min_probability if self.min_probability is not None else shipped_model().threshold

    def flagged(self, report: dict) -> bool:
        """Whether a registration's ``report`` (report.json's content) is flagged as likely wrong: its
        ``success_probability`` below :attr:`probability_threshold`; where it has none, always if it is
        :func:`unverified` (an ultrasound registration), else (no refinement, or a report of an older dpcn_med) its
        ``confidence`` below :attr:`min_confidence` (NaN is never confident)."""
        probability = report.get("success_probability")
        if probability is not None:
            return not probability >= self.probability_threshold
        if unverified(report):
            return True
        return not report["confidence"] >= self.min_confidence


def unverified(report: dict) -> bool:
    """Whether a registration's ``report`` is one that nothing checks yet: an ultrasound registration, refined by
    LC2. The quality model was fitted on mutual information, and LC2 does not tell a right pose from a wrong one (a
    wrong pose can hold more of it than the true one); the solver's confidence let 5 of 80 wrong results of the
    ultrasound benchmark through (docs/benchmarks.md, "Ultrasound"). So such a result is flagged until a signal exists
    that tells."""
    from dpcn_med.result import SIMILARITY_NAMES  # here: the command line's start must not import torch

    return report.get("similarity") == SIMILARITY_NAMES["lc2"]


def check_output_folder(output: Path) -> None:
    """Refuse, before any work, an output folder that exists as a file or cannot be created or written.

    Raises:
        InputError: naming ``output`` and the reason.
    """
    try:
        if output.exists() and not output.is_dir():
            raise InputError(f"{output}: exists and is not a folder; choose another output folder")
        for existing in (output, *output.absolute().parents):
            if existing.exists():
                break
            if existing.is_symlink():  # mkdir would fail on it after the work
                raise InputError(f"{output}: cannot be created: {existing} is a link to {os.readlink(existing)}, which "
                                 "does not exist; choose another output folder")
        if not existing.is_dir():
            raise InputError(f"{output}: cannot be created: {existing} is a file; choose another output folder")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise InputError(f"{output}: cannot be written: no write permission in {existing}; choose another output "
                             "folder")
    except OSError as error:  # a name too long for the file system, a loop of links
        raise InputError(f"{output}: cannot be used ({error.strerror}); choose another output folder") from None


def make_folder(output: Path, *, staging: bool = False) -> Path:
    """Create ``output`` and its missing parents; with ``staging``, return a new hidden folder inside it.

    Raises:
        InputError: naming ``output``, where the checks before the work could not tell (``/proc/x``, a full disk).
    """
    try:
        output.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=output)) if staging else output
    except OSError as error:
        raise InputError(f"{output}: cannot be written ({error.strerror}); choose another output folder") from None


def refuse_overwriting_inputs(inputs: dict[str, str], targets: Iterable[Path]) -> None:
    """Refuse, before any work, a run that would write one of ``targets`` over one of its ``inputs``.

    Args:
        inputs: input paths, each with what messages call it.
        targets: the files the run may write. A path is compared by the file it names however spelt: a link, or
            ``out/x/../in.nii.gz`` with no ``x`` yet, which names ``out/in.nii.gz`` once the folders are made.

    Raises:
        InputError: naming the target and the input it would replace.
    """
    existing = {}
    for path, description in inputs.items():
        with contextlib.suppress(OSError):
            found = os.stat(os.path.realpath(path))
            existing.setdefault((found.st_dev, found.st_ino), description)
    for target in targets:
        try:
            found = os.stat(os.path.realpath(target))
        except OSError:  # not there: nothing to overwrite
            continue
        if (found.st_dev, found.st_ino) in existing:
            raise InputError(f"{target}: is {existing[found.st_dev, found.st_ino]}, which this run would replace; "
                             "choose another output folder (inputs are never overwritten)")


def model_identity(model: str) -> str | dict[str, str]:
    """A model as a request names it: ``"none"`` for the learning-free solver, else its files' real paths and SHA-256.

    Files that cannot be read keep their path alone (the registration then says what is wrong).
    """
    from dpcn_med.models.weights import model_paths
    from dpcn_med.options import LEARNING_FREE

    if model.lower() in LEARNING_FREE:
        return "none"
    identity = {}
    for kind, path in zip(("weights", "config"), model_paths(model)):
        identity[kind] = os.path.realpath(path)
        with contextlib.suppress(OSError):
            identity[f"{kind}_sha256"] = io.file_sha256(path)
    return identity


def registration_request(fixed: str, moving: str, *, fixed_mask: str | None, moving_mask: str | None,
                         settings: RegistrationSettings, bandwidth: int,
                         model: str | dict[str, str] | None = None) -> dict:
    """What a registration was asked for (report.json's ``request``): the inputs' real paths and the settings that
    change its result.

    Args:
        bandwidth: the bandwidth resolved (the settings' or the model's).
        model: :func:`model_identity` of ``settings.model`` where the caller has it already (read when ``None``).
    """
    resolved = {key: None if value is None else os.path.realpath(value) for key, value in
                (("fixed", fixed), ("moving", moving), ("fixed_mask", fixed_mask), ("moving_mask", moving_mask))}
    return {**resolved, "mode": settings.mode, "bandwidth": bandwidth,
            "model": model_identity(settings.model) if model is None else model, "refine": settings.refine,
            "fixed_modality": settings.fixed_modality, "moving_modality": settings.moving_modality}


def earlier_outputs(output: Path) -> set[str]:
    """The files of :data:`OUTPUT_NAMES` that an earlier run's report.json in ``output`` lists (none if unreadable)."""
    try:
        return set(OUTPUT_NAMES) & set(io.read_json(output / "report.json")["outputs"])
    except (InputError, KeyError, TypeError):  # none, unreadable, or not a report
        return set()


def register_to_folder(fixed: str, moving: str, output: Path, *, settings: RegistrationSettings,
                       fixed_mask: str | None = None, moving_mask: str | None = None,
                       progress: Progress | None = None, model: str | dict[str, str] | None = None) -> dict:
    """Register ``moving`` onto ``fixed`` and write every output into ``output`` at once.

    Args:
        fixed, moving, fixed_mask, moving_mask: input paths, as :func:`dpcn_med.register` reads them.
        output: the pair's folder (created with its parents; removed again if the run fails).
        settings: what to do and write.
        progress: ``progress(stage, fraction)`` callback.
        model: :func:`model_identity` of ``settings.model`` where the caller has it already.

    Returns:
        The report written as report.json (``confidence``, ``final``, ``timings_s``, ``request``, ``outputs``...).

    Raises:
        InputError: a bad input or output folder, before anything is written.
    """
    from dpcn_med.registration import register
    from dpcn_med.report import registration_report

    _check_targets(output, {p: "an input of this run" for p in (fixed, moving, fixed_mask, moving_mask)
                            if p is not None})
    started, begun = time.perf_counter(), time.time()
    result = register(fixed, moving, mode=settings.mode, model=settings.model, bandwidth=settings.bandwidth,
                      refine=settings.refine, device=settings.device, fixed_mask=fixed_mask, moving_mask=moving_mask,
                      fixed_modality=settings.fixed_modality, moving_modality=settings.moving_modality,
                      resample=settings.resampled, progress=progress)
    report = registration_report(result, fixed=fixed, moving=moving, fixed_mask=fixed_mask, moving_mask=moving_mask,
                                 settings=settings, outputs=list(settings.outputs))
    if settings.mirror_check and result.success_probability is not None and settings.flagged(report):
        report["mirrored"] = check_mirrored(result, settings, fixed_mask, moving_mask)
    report["timings_s"] = {**report["timings_s"], "total": time.perf_counter() - started}  # not result.timings
    report["request"] = registration_request(fixed, moving, fixed_mask=fixed_mask, moving_mask=moving_mask,
                                             settings=settings, bandwidth=result.bandwidth, model=model)
    _write_staged(output, begun, settings.outputs, lambda staging: _write_files(
        staging, result, report, settings, title=f"{Path(moving).name} onto {Path(fixed).name}"))
    return report


def check_mirrored(result, settings: RegistrationSettings, fixed_mask: str | None, moving_mask: str | None) -> dict:
    """A flagged result's second look: the moving volume mirrored left to right (:func:`mirrored_copy`) and
    registered again with the same settings. ``{"success_probability": p, "likely": p >= threshold}``: ``likely``
    where the mirrored copy registers as a success would, the sign of a flipped header."""
    from dpcn_med.registration import mirrored_copy, register

    try:
        moving_mask_image = None if moving_mask is None else mirrored_copy(
            io.read_mask(moving_mask, result.moving_image, role="moving mask"))
        mirrored = register(result.fixed_image, mirrored_copy(result.moving_image), mode=settings.mode,
                            model=settings.model, bandwidth=settings.bandwidth, device=settings.device,
                            fixed_mask=fixed_mask, moving_mask=moving_mask_image,
                            fixed_modality=settings.fixed_modality, moving_modality=settings.moving_modality)
    except InputError as error:  # the result stands; the second look could not be taken
        return {"success_probability": None, "likely": False, "error": str(error)}
    probability = mirrored.success_probability
    return {"success_probability": probability,
            "likely": probability is not None and probability >= settings.probability_threshold}


def _check_targets(output: Path, inputs: dict[str, str]) -> None:
    refuse_overwriting_inputs(inputs, [output / name for name in OUTPUT_NAMES])
    check_output_folder(output)
    for name in OUTPUT_NAMES:
        if (output / name).is_dir() and not (output / name).is_symlink():
            raise InputError(f"{output / name}: exists and is a folder, where {name} is to be written; move it or "
                             "choose another output folder")


def _write_files(staging: Path, result, report: dict, settings: RegistrationSettings, *, title: str) -> None:
    """Write a result's files into the staging folder."""
    io.write_transform(result.fixed_to_moving, staging / "transform.tfm")
    io.write_transform(result.fixed_to_moving, staging / "transform.h5")
    io.write_transform(result.moving_to_fixed, staging / "inverse.tfm")
    io.write_transform(result.moving_to_fixed, staging / "inverse.h5")
    from concurrent.futures import ThreadPoolExecutor  # here: `dpcn-med --help` imports this module

    # The resampled volume is compressed while the overview is drawn: zlib lets go of Python's lock (io.write_image).
    with ThreadPoolExecutor(max_workers=1) as pool:
        resampled = pool.submit(io.write_image, result.resampled, staging / "moving_resampled.nii.gz") \
            if settings.resampled else None
        if settings.overview:
            from dpcn_med.report import overview_figure

            overview_figure(result.fixed_image, result.moving_image, result.fixed_to_moving, staging / "overview.png",
                            title=f"{title}: {_quality_text(result)}, overlap {result.overlap:.0%}",
                            centre=result.fixed_grid.centre,  # the fixed foreground centre, already found
                            foregrounds=(result.fixed_foreground, result.moving_foreground))
        if resampled is not None:
            resampled.result()  # its error, if any, is this call's
    io.write_json(report, staging / "report.json")


def _quality_text(result) -> str:
    """``success probability P%`` where the result has one, else ``confidence C``."""
    if result.success_probability is not None:
        return f"success probability {result.success_probability:.0%}"
    return f"confidence {result.confidence:.3f}"


def _write_staged(output: Path, begun: float, outputs: tuple[str, ...], write: Callable[[Path], None]) -> None:
    """Write ``outputs`` with ``write(staging)`` into a hidden folder inside ``output``, then rename them into place.

    One file system, so the moves are renames: a failed or interrupted run leaves no partial result, nor the folders
    it created. Staging folders older than ``begun`` (a run killed outright) are removed first.
    """
    created = [folder for folder in (output, *output.absolute().parents) if not folder.exists()]
    for stale in output.glob(f"{STAGING_PREFIX}*"):
        with contextlib.suppress(OSError):
            if stale.is_dir() and not stale.is_symlink() and stale.stat().st_mtime < begun:
                shutil.rmtree(stale)
    staging, finished = None, False
    try:
        staging = make_folder(output, staging=True)
        write(staging)
        earlier = earlier_outputs(output)
        with io.interrupts_deferred():  # Ctrl-C between two renames would leave two runs' files side by side
            (output / "report.json").unlink(missing_ok=True)  # first: killed outright, the pair reads as unfinished
            # An earlier run's files this one does not write would read as this one's; a file its report does not
            # list is not known to be a run's (the user's own overview.png), and stays.
            for name in earlier - set(outputs):
                (output / name).unlink(missing_ok=True)
            for name in outputs:  # report.json last: it marks the pair as finished
                os.replace(staging / name, output / name)
            finished = True
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        if not finished:
            for folder in created:  # deepest first; one holding anything else stays
                try:
                    folder.rmdir()
                except OSError:
                    break

