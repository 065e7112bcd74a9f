"""Long work as a generator of steps, driven by a loop (scripts, ``--background``) or a timer (UI).

A :class:`Job` has two parts:

- ``steps``: a generator yielding ``(fraction, text)`` before each slow step. It computes with the
  core only and never touches ``bpy``, so the UI driver can advance it in a worker thread. Its
  return value is the job's result.
- ``commit``: a function of that result that writes it into Blender (objects, meshes, properties,
  sidecar files) on the main thread. Nothing in the scene changes before ``commit`` runs, so
  cancelling (Esc) leaves the scene as it was.

:func:`run` drains a job and commits it (printing ``[volumeevm] 42% building EVM`` lines under
``bpy.app.background``). :class:`JobOperator` is the operator mix-in: ``execute()`` runs the job
synchronously, ``invoke()`` runs it from a 0.1 s modal timer with a progress bar (sidebar and
status bar) and Esc to cancel.
"""

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Generator

import bpy

from ..volumeevm_addon import VolumeEVMError

#: The errors an operator reports to the user (bad input, unreadable or unwritable files).
REPORTED_ERRORS = (VolumeEVMError, OSError)


@dataclass
class Job:
    """One long task: ``steps`` (pure computation) and ``commit`` (writes into Blender)."""

    label: str
    steps: Generator
    commit: Callable[[Any], Any]


@dataclass
class Progress:
    """What the UI shows while a job runs from a modal timer."""

    label: str
    fraction: float = 0.0
    text: str = ""


#: The job running in the UI, if any (one at a time).
CURRENT = None


def progress_line(fraction, text):
    """The line printed for a step in background mode."""
    return f"[volumeevm] {round(100 * fraction):3d}% {text}"


def drain(steps, *, verbose=None):
    """Run a step generator to its end and return its value.

    Parameters
    ----------
    steps : generator of (float, str)
        Yields ``(fraction, text)`` before each slow step.
    verbose : bool, optional
        Print a progress line per step; default: when Blender runs in the background.
    """
    verbose = bpy.app.background if verbose is None else verbose
    while True:
        try:
            fraction, text = next(steps)
        except StopIteration as stop:
            if verbose:
                print(progress_line(1.0, "done"), flush=True)
            return stop.value
        if verbose:
            print(progress_line(fraction, text), flush=True)


def run(job, *, verbose=None):
    """Drain ``job.steps`` and commit the result; returns what ``commit`` returns."""
    return job.commit(drain(job.steps, verbose=verbose))


def _advance(steps):
    """One step in the worker thread: ``("step", (fraction, text))`` or ``("done", value)``."""
    try:
        return "step", next(steps)
    except StopIteration as stop:
        return "done", stop.value


def _redraw(context):
    screen = context.screen
    if screen is None:
        return
    for area in screen.areas:
        if area.type in {"VIEW_3D", "STATUSBAR"}:
            area.tag_redraw()


#: Events passed on to Blender while a job runs (view navigation); all others are held.
_PASS_THROUGH = {
    "MIDDLEMOUSE", "WHEELUPMOUSE", "WHEELDOWNMOUSE", "MOUSEMOVE", "INBETWEEN_MOUSEMOVE",
    "TRACKPADPAN", "TRACKPADZOOM", "MOUSEROTATE", "NDOF_MOTION",
}


class JobOperator:
    """Operator mix-in for long work: subclasses define ``job(context) -> Job``.

    ``job()`` reads the operator's properties and Blender state and may raise a reported
    error (:data:`REPORTED_ERRORS`); ``finished(context, result)`` may report a summary.
    """

    def job(self, context):
        raise NotImplementedError

    def finished(self, context, result):
        """Called after a successful commit; report a summary here."""

    # ---------------------------------------------------------------- synchronous
    def execute(self, context):
        try:
            job = self.job(context)
            result = run(job)
        except REPORTED_ERRORS as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        self.finished(context, result)
        return {"FINISHED"}

    # ---------------------------------------------------------------- modal (UI)
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        return self.start(context)

    def start(self, context):
        """Start the job from a modal timer (the UI path of ``invoke``)."""
        global CURRENT
        if CURRENT is not None:
            self.report({"ERROR"}, f"VolumeEVM is busy: {CURRENT.label}; wait or press Esc")
            return {"CANCELLED"}
        try:
            self._job = self.job(context)
        except REPORTED_ERRORS as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        CURRENT = Progress(self._job.label, 0.0, "starting")
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="volumeevm")
        self._future = self._executor.submit(_advance, self._job.steps)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        _redraw(context)
        return {"RUNNING_MODAL"}

    def _stop(self, context):
        global CURRENT
        CURRENT = None
        context.window_manager.event_timer_remove(self._timer)
        steps = self._job.steps
        # Close the generator after its current step (in the worker thread), then let it go.
        self._executor.submit(steps.close)
        self._executor.shutdown(wait=False)
        _redraw(context)

    def modal(self, context, event):
        if event.type == "ESC":
            self._stop(context)
            self.report({"WARNING"}, f"{self._job.label}: cancelled, nothing changed")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"} if event.type in _PASS_THROUGH else {"RUNNING_MODAL"}
        if not self._future.done():
            return {"RUNNING_MODAL"}
        try:
            kind, value = self._future.result()
            if kind == "step":
                CURRENT.fraction, CURRENT.text = value
                self._future = self._executor.submit(_advance, self._job.steps)
                _redraw(context)
                return {"RUNNING_MODAL"}
            self._stop(context)
            result = self._job.commit(value)
        except REPORTED_ERRORS as error:
            if CURRENT is not None:
                self._stop(context)
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        self.finished(context, result)
        return {"FINISHED"}
