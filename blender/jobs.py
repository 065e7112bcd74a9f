"""Long work as a generator of steps, driven by a loop (scripts, ``--background``) or a timer (UI).

A :class:`Job` has two parts:

- ``steps``: a generator yielding ``(fraction, text)`` before each slow step. It computes with the
  core only and never touches ``bpy``, so the UI driver can advance it in a worker thread. Its
  return value is the job's result.
- ``commit``: a function of that result that writes it into Blender (objects, meshes, properties,
  sidecar files) on the main thread. Nothing in the scene changes before ``commit`` runs, so
  cancelling (Esc) leaves the scene as it was.

A job either completes or leaves the scene as it was. ``commit`` (and the operator's
``finished``) run inside :func:`transaction`: if anything raises there, the datablocks made
meanwhile are removed, the selection and active object are put back and the changes to existing
data that the commit registered (:func:`assign`, :func:`assign_item`, :func:`on_undo`) are
undone; what the commit replaces is dropped only once the job succeeded (:func:`on_success`).

:func:`run` drains a job and commits it (printing ``[volumeevm] 42% building EVM`` lines under
``bpy.app.background``). :class:`JobOperator` is the operator mix-in: ``execute()`` runs the job
synchronously, ``invoke()`` runs it from a 0.1 s modal timer with a progress bar (sidebar and
status bar) and Esc to cancel. Any exception ends the job: the operator reports it (an
unexpected one with its traceback printed to the console), the running-job marker
:data:`CURRENT` and the timer go, and the scene is as it was before the job. While a job's
steps run, the core's kernels use the scene's render threads and a kernel's first use in the
session shows in the progress (:mod:`.kernels`).
"""

import functools
import traceback
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Generator

import bpy

from ..volumeevm_addon import VolumeEVMError
from . import kernels

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
    preview: Any = None  # what the viewport draws while the job runs (:func:`show_preview`)


#: The job running in the UI, if any (one at a time).
CURRENT = None

#: While a commit runs (see :func:`transaction`): callables that put back the changes it made to
#: existing data, and callables that drop what it replaced once the job succeeded.
_undo = None
_on_success = None


def show_preview(preview):
    """Hand the job running from the UI a preview that the viewport draws until the job ends
    (:mod:`.preview`); called from the job's steps (any thread). Returns False, doing nothing,
    when no job runs from the UI (a script, ``--background``: no viewport to draw it)."""
    job = CURRENT
    if job is None:
        return False
    job.preview = preview
    return True


def wants_preview():
    """Whether a job runs from the UI, whose viewport would draw a preview."""
    return CURRENT is not None


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
    fraction = 0.0

    def show(text):  # a kernel's first use, during the step at ``fraction``
        if verbose:
            print(progress_line(fraction, text), flush=True)

    with kernels.job_settings(show):
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
    """Drain ``job.steps`` and commit the result (in a :func:`transaction`).

    Returns what ``commit`` returns; any error is raised with the scene as it was.
    """
    value = drain(job.steps, verbose=verbose)
    with transaction():
        return job.commit(value)


def _datablocks():
    """Every datablock in ``bpy.data`` (objects, meshes, images, ...)."""
    for prop in bpy.data.bl_rna.properties:
        if prop.type == "COLLECTION":
            yield from getattr(bpy.data, prop.identifier)


@contextmanager
def transaction():
    """Run a commit all or nothing: if the block raises, Blender is put back as it was.

    Datablocks made inside the block are removed, the selection and active object restored and
    the changes registered with :func:`assign` or :func:`on_undo` undone (newest first); the
    error is raised again. Callables given to :func:`on_success` run when the block succeeded.
    A transaction inside another one joins it.
    """
    global _undo, _on_success
    if _undo is not None:
        yield
        return
    view_layer = bpy.context.view_layer
    selected = set() if view_layer is None else {
        o.session_uid for o in view_layer.objects if o.select_get()}
    active = None if view_layer is None else view_layer.objects.active
    before = {block.session_uid for block in _datablocks()}
    _undo, _on_success = [], []
    try:
        yield
    except BaseException:
        undo, _undo, _on_success = _undo, None, None
        for step in reversed(undo):
            _quietly(step)
        _quietly(lambda: bpy.data.batch_remove(
            [block for block in _datablocks() if block.session_uid not in before]))
        if view_layer is not None:
            _quietly(lambda: _select(view_layer, selected, active))
        raise
    success, _undo, _on_success = _on_success, None, None
    for step in success:
        _quietly(step)


def _quietly(step):
    """Run one step of a rollback or clean-up; a failure is printed and the rest goes on."""
    try:
        step()
    except Exception:  # noqa: BLE001 - the job's own error is the one to report
        traceback.print_exc()


def _select(view_layer, selected, active):
    view_layer.update()  # sync the layer with the removals before selecting
    for obj in view_layer.objects:
        obj.select_set(obj.session_uid in selected)
    view_layer.objects.active = active


def on_undo(step):
    """Register how to put back a change a commit makes to existing data (run if it fails).

    Outside a :func:`transaction` the change simply stays.
    """
    if _undo is not None:
        _undo.append(step)


def on_success(step):
    """Run ``step`` (e.g. removing a replaced mesh) once the transaction succeeded, or now
    outside one."""
    if _on_success is None:
        step()
    else:
        _on_success.append(step)


def assign(struct, **values):
    """Set properties of existing Blender data; they are put back if the transaction fails."""
    for name, value in values.items():
        old = getattr(struct, name)
        if isinstance(old, bpy.types.bpy_prop_array):
            old = old[:]
        on_undo(functools.partial(setattr, struct, name, old))
        setattr(struct, name, value)


def assign_item(block, key, value):
    """Set a custom property of a datablock; put back (or removed) if the transaction fails."""
    if key in block:
        on_undo(functools.partial(block.__setitem__, key, block[key]))
    else:
        on_undo(functools.partial(block.pop, key))
    block[key] = value


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


def report_failure(operator, error, label=""):
    """Report the error that ended an operator's work as an ERROR; returns ``{"CANCELLED"}``.

    A reported error (:data:`REPORTED_ERRORS`) is shown as it is; any other is called unexpected
    (prefixed with ``label``, e.g. the job's) and its traceback is printed to the console.
    """
    if isinstance(error, REPORTED_ERRORS):
        message = str(error)
    else:
        traceback.print_exception(error)
        message = (f"{label + ': ' if label else ''}unexpected error "
                   f"({type(error).__name__}: {error}); nothing was changed, the traceback is in "
                   f"the console")
    operator.report({"ERROR"}, message)
    return {"CANCELLED"}


#: Events passed on to Blender while a job runs (view navigation); all others are held.
_PASS_THROUGH = {
    "MIDDLEMOUSE", "WHEELUPMOUSE", "WHEELDOWNMOUSE", "MOUSEMOVE", "INBETWEEN_MOUSEMOVE",
    "TRACKPADPAN", "TRACKPADZOOM", "MOUSEROTATE", "NDOF_MOTION",
}


class JobOperator:
    """Operator mix-in for long work: subclasses define ``job(context) -> Job``.

    ``job()`` reads the operator's properties and Blender state and may raise a reported
    error (:data:`REPORTED_ERRORS`); ``finished(context, result)`` may report a summary. Any
    other exception ends the job too: it is reported as unexpected, its traceback printed.
    """

    def job(self, context):
        raise NotImplementedError

    def finished(self, context, result):
        """Called after a successful commit (in its transaction); report a summary here."""

    # ---------------------------------------------------------------- synchronous
    def execute(self, context):
        job = None
        try:
            job = self.job(context)
            value = drain(job.steps)
        except Exception as error:
            return report_failure(self, error, job.label if job is not None else "")
        return self._commit(context, job, value)

    def _commit(self, context, job, value):
        """Commit and report the summary, all or nothing (see :func:`transaction`)."""
        try:
            with transaction():
                self.finished(context, job.commit(value))
        except Exception as error:
            return report_failure(self, error, job.label)
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
        except Exception as error:
            return report_failure(self, error)
        CURRENT = Progress(self._job.label, 0.0, "starting")
        show = functools.partial(setattr, CURRENT, "text")  # set from the worker, read by the UI
        self._settings = ExitStack()  # the kernels' threads and first-use text, until _stop
        self._settings.enter_context(kernels.job_settings(show))
        self._timer = None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="volumeevm")
        try:
            self._future = self._executor.submit(_advance, self._job.steps)
            wm = context.window_manager
            self._timer = wm.event_timer_add(0.1, window=context.window)
            wm.modal_handler_add(self)
        except Exception as error:
            self._stop(context)
            return report_failure(self, error, self._job.label)
        _redraw(context)
        return {"RUNNING_MODAL"}

    def _stop(self, context):
        """End the modal job: clear :data:`CURRENT`, remove the timer, let the worker go."""
        global CURRENT
        CURRENT = None
        self._settings.close()
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        # Close the generator after its current step (in the worker thread), then let it go.
        self._executor.submit(self._job.steps.close)
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
            if CURRENT.text == kernels.FIRST_USE:  # the step waits for kernels to compile: say so
                _redraw(context)
            return {"RUNNING_MODAL"}
        try:
            kind, value = self._future.result()
            if kind == "step":
                CURRENT.fraction, CURRENT.text = value
                self._future = self._executor.submit(_advance, self._job.steps)
                _redraw(context)
                return {"RUNNING_MODAL"}
        except Exception as error:
            self._stop(context)
            return report_failure(self, error, self._job.label)
        self._stop(context)
        return self._commit(context, self._job, value)
