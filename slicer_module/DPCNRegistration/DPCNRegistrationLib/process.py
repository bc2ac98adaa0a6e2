"""The registration as a separate Python process: command line, streamed progress, cancel.

Slicer's own Python (``PythonSlicer``) runs :mod:`DPCNRegistrationLib.run_registration`, which runs ``dpcn-med
register --progress json``. A reader thread turns the child's output into events that :meth:`Job.poll` hands out
without ever blocking, so a Qt timer can drive it and the application stays responsive.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

SCRIPT = Path(__file__).with_name("run_registration.py")
_NO_WINDOW = getattr(subprocess, "CREATE_NO_WINDOW", 0)
EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_LOW_CONFIDENCE = 0, 1, 2, 3
"""dpcn-med's exit codes (dpcn_med.cli); 3 means a result was written with a low confidence."""
KILL_AFTER_S = 3.0
"""Seconds a cancelled process has to end on SIGTERM before it is killed."""


@dataclass(frozen=True)
class Options:
    """What the widget offers; the names and defaults follow the ``dpcn-med register`` options."""

    mode: str = "rigid"
    model: str = "default"
    """``default`` (dpcn-med's default model), ``learning-free``, or the path of a model file."""
    refine: bool = True
    device: str = "auto"
    bandwidth: int | None = None
    """``None``: the model's (32 for the learning-free solver), as ``dpcn-med register`` takes it."""
    fixed_modality: str = "auto"
    """``auto`` (dpcn-med tells CT from MR by the intensities; it never detects ultrasound), ``ct``, ``mr`` or ``us``:
    an ultrasound volume must be named so, to be refined by LC2 rather than mutual information."""
    moving_modality: str = "auto"
    """As ``fixed_modality``, for the moving volume."""

    def arguments(self) -> list[str]:
        """The ``dpcn-med register`` options for these choices (a modality only where it is not ``auto``)."""
        arguments = ["--mode", self.mode, "--device", self.device]
        if self.bandwidth is not None:
            arguments[2:2] = ["--bandwidth", str(int(self.bandwidth))]
        for flag, modality in (("--fixed-modality", self.fixed_modality), ("--moving-modality", self.moving_modality)):
            if modality != "auto":
                arguments += [flag, modality]
        if self.model == "learning-free":
            arguments += ["--model", "none"]
        elif self.model != "default":
            arguments += ["--model", os.fspath(self.model)]
        if not self.refine:
            arguments.append("--no-refine")
        return arguments


@dataclass(frozen=True)
class Event:
    """One thing the child said: ``kind`` is ``progress`` (``fraction`` in [0, 1] and ``text`` the stage), ``log``
    (a line of output) or ``exit`` (``code`` set)."""

    kind: str
    text: str = ""
    fraction: float = 0.0
    code: int | None = None


def python_executable() -> str:
    """The Python to run the registration with: ``PythonSlicer`` inside 3D Slicer (the same site-packages as the
    application), else this interpreter."""
    inside_slicer = "slicer" in sys.modules and hasattr(sys.modules["slicer"], "app")
    found = shutil.which("PythonSlicer") if inside_slicer else None
    return found or sys.executable


def command(fixed: str | os.PathLike, moving: str | os.PathLike, output: str | os.PathLike, options: Options, *,
            fixed_mask: str | os.PathLike | None = None, moving_mask: str | os.PathLike | None = None,
            resampled: bool = True, python: str | None = None) -> list[str]:
    """The child's command line: register ``moving`` onto ``fixed`` (each restricted to its mask file, if any) into
    the folder ``output``, with the resampled moving volume only when ``resampled``. Never the overview figure:
    Slicer's own views show the result, and drawing it costs the child about a second."""
    masks = [argument for flag, path in (("--fixed-mask", fixed_mask), ("--moving-mask", moving_mask))
             if path is not None for argument in (flag, os.fspath(path))]
    skipped = ["--no-overview"] + ([] if resampled else ["--no-resampled"])
    return [python or python_executable(), os.fspath(SCRIPT), "register", os.fspath(fixed), os.fspath(moving),
            "-o", os.fspath(output), *options.arguments(), *masks, *skipped, "--progress", "json"]


def parse_line(line: str) -> Event:
    """An output line as an event: dpcn-med's JSON progress objects become ``progress``, anything else ``log``."""
    text = line.rstrip("\n")
    if text.startswith("{"):
        try:
            message = json.loads(text)
        except json.JSONDecodeError:
            message = None
        if isinstance(message, dict) and "stage" in message and "fraction" in message:
            return Event("progress", text=str(message["stage"]), fraction=float(message["fraction"]))
    return Event("log", text=text)


class Job:
    """A running registration process; :meth:`poll` returns what happened since the last call."""

    def __init__(self, arguments: list[str], *, environment: dict[str, str] | None = None) -> None:
        self.arguments = arguments
        self.events: queue.Queue[Event] = queue.Queue()
        self.log: list[str] = []
        self.returncode: int | None = None
        self.cancelled = False
        # UTF-8 both ways, undecodable bytes replaced: a byte the reader cannot decode ended its thread, and the job
        # never finished; a child on a legacy code page failed to print a non-ASCII path after its work.
        environment = {**(os.environ if environment is None else environment), "PYTHONUTF8": "1",
                       "PYTHONIOENCODING": "utf-8"}
        self._process = subprocess.Popen(arguments, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                         encoding="utf-8", errors="replace", bufsize=1, env=environment,
                                         # Windows: no console window beside Slicer's (as Slicer's own launcher)
                                         creationflags=_NO_WINDOW,
                                         # POSIX: its own process group, so that cancel reaches what it starts
                                         start_new_session=os.name == "posix")
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self._process.stdout is not None
        for line in self._process.stdout:
            self.events.put(parse_line(line))
        self.events.put(Event("exit", code=self._process.wait()))

    def poll(self) -> list[Event]:
        """Events since the last call, oldest first, without waiting; the last one is ``exit`` when it ended."""
        events = []
        while True:
            try:
                event = self.events.get_nowait()
            except queue.Empty:
                return events
            if event.kind == "log":
                self.log.append(event.text)
            elif event.kind == "exit":
                self.returncode = event.code
            events.append(event)

    @property
    def finished(self) -> bool:
        return self.returncode is not None

    def wait(self, timeout: float | None = None) -> list[Event]:
        """Block until the process ends (or ``timeout`` seconds); every event not yet polled."""
        self._reader.join(timeout)
        return self.poll()

    def cancel(self) -> None:
        """Stop the process and the processes it started, without waiting: it has ended when :attr:`finished`.

        PythonSlicer is a launcher that runs Slicer's Python as its child, so stopping the launcher alone would leave
        the registration running. On POSIX its process group gets SIGTERM, then SIGKILL after :data:`KILL_AFTER_S`
        seconds; on Windows ``taskkill /T /F`` ends its process tree. Partial outputs are the caller's to delete.
        """
        if self.cancelled:
            return
        self.cancelled = True
        threading.Thread(target=self._stop, daemon=True).start()

    def _stop(self) -> None:
        if os.name == "nt":
            # /F: no gentler way reaches a process without a console (CREATE_NO_WINDOW), Ctrl+Break included.
            subprocess.run(["taskkill", "/T", "/F", "/PID", str(self._process.pid)], stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, creationflags=_NO_WINDOW, check=False)
            return
        # While the reader runs, a process still holds the output pipe and the group leader is not reaped yet (the
        # reader reaps it), so its process group ID cannot have been reused by another group.
        for number in (signal.SIGTERM, signal.SIGKILL):
            if not self._reader.is_alive():
                return
            try:
                os.killpg(self._process.pid, number)
            except ProcessLookupError:
                return
            self._reader.join(KILL_AFTER_S)

    def error_message(self) -> str:
        """dpcn-med's one-line error (its last line starting ``dpcn-med:``), else the child's last line of output."""
        lines = [line for line in self.log if line.strip()]
        own = [line for line in lines if line.startswith("dpcn-med:")]
        if own or lines:
            return (own or lines)[-1]
        return f"the registration process ended with code {self.returncode}"
