"""Long operators as step generators: one code path for the GUI, scripts and the CLI.

A *job* is a generator that yields ``(fraction, text)`` between steps and returns its
result (``StopIteration.value``).  It never writes Blender data: the operator's
``finish`` does that once, in the main thread, so a cancelled or failed job leaves the
scene as it was.

- Background mode, ``bpy.ops...()`` from a script (EXEC_DEFAULT) and the CLI run a job to
  the end at once (``run_sync``).
- From the sidebar (INVOKE_DEFAULT, with a window) ``JobOperator`` runs it as a modal
  operator: a timer steps the generator, the window manager's progress cursor, the
  status bar and the panel show how far it is, and Esc cancels.  Pure-numpy work (grid
  and BVH builds, tracing, calibration) runs in a worker thread (``Job.call``) so the
  interface keeps drawing; the worker never touches bpy.

Failures are ``HRCError`` subclasses whose ``str`` is a one-line reason and whose
``code`` is the CLI exit code (see ``operators/cli.py``).
"""

from __future__ import annotations

import os
import threading
import traceback
from pathlib import Path

import bpy

from ..settings import RUNNING


class HRCError(Exception):
    """A failure to report in one line; ``code`` is the CLI exit status."""

    code = 1


class BadInput(HRCError):
    code = 2


class NoGeometry(HRCError):
    code = 3


class Unwritable(HRCError):
    code = 4


def writable_dir(path, what: str) -> Path:
    """``path`` as a folder that exists (created if missing) and can be written; Unwritable otherwise.

    ``what`` names it in the one-line message (e.g. "--output", "the output folder").
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise Unwritable(f"unwritable path: cannot create {what} {path}: {e.strerror or e}") from None
    if not os.access(path, os.W_OK):
        raise Unwritable(f"unwritable path: {what} {path} is not writable")
    return path


class InvalidGeometry(HRCError):
    code = 5


class NothingToTrace(HRCError):
    """No active camera for the camera passes, or no mesh to bake."""

    code = 6


class Cancelled(HRCError):
    code = 130


class Job:
    """The context a job generator runs in: threaded or not, and the cancel flag."""

    def __init__(self, threaded: bool = False):
        self.threaded = threaded
        self.cancel_event = threading.Event()
        self.fraction = 0.0
        self.text = ""

    def check(self):
        """Raise Cancelled once the user has cancelled (called between chunks of work)."""
        if self.cancel_event.is_set():
            raise Cancelled("cancelled")

    def progress(self, fraction: float, text: str | None = None):
        """A progress callback for core functions (safe from a worker thread)."""
        self.fraction = float(fraction)
        if text:
            self.text = str(text)
        self.check()

    def call(self, fn, *args, **kwargs):
        """``result = yield from job.call(fn, ...)``: run pure-numpy work, in a worker
        thread when threaded (yielding progress until it ends), else directly."""
        if not self.threaded:
            return fn(*args, **kwargs)
        box = {}

        def work():
            try:
                box["value"] = fn(*args, **kwargs)
            except BaseException as e:  # handed to the main thread below
                box["error"] = e

        thread = threading.Thread(target=work, name="hybrid_raycast job", daemon=True)
        thread.start()
        while thread.is_alive():
            yield self.fraction, self.text
            thread.join(0.05)
        if "error" in box:
            raise box["error"]
        return box["value"]


def run_sync(gen):
    """Run a job generator to the end; its return value."""
    try:
        while True:
            next(gen)
    except StopIteration as stop:
        return stop.value


def report_messages(op, messages):
    """``messages``: (level, text) pairs, level in 'INFO', 'WARNING', 'ERROR'."""
    for level, text in messages:
        op.report({level}, text)


class JobOperator:
    """Mixin for operators whose work is a job: ``start(context, job)`` returns the
    generator (raising HRCError for bad input), ``finish(context, result)`` writes the
    result into Blender and returns (level, text) messages."""

    #: shown in the panel's progress bar and the status bar
    job_label = "Working"

    def start(self, context, job: Job):
        raise NotImplementedError

    def finish(self, context, result):
        raise NotImplementedError

    # -- synchronous: scripts, background, CLI ------------------------------------------
    def execute(self, context):
        try:
            result = run_sync(self.start(context, Job(threaded=False)))
            report_messages(self, self.finish(context, result))
        except HRCError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except Exception as e:  # a bug: one line in the UI, the traceback on the console
            traceback.print_exc()
            self.report({"ERROR"}, f"internal error ({type(e).__name__}: {e}); see the console")
            return {"CANCELLED"}
        return {"FINISHED"}

    # -- modal: the sidebar --------------------------------------------------------------
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        if RUNNING:
            self.report({"WARNING"}, f"{RUNNING.get('label', 'another job')} is still running (Esc cancels it)")
            return {"CANCELLED"}
        self._job = Job(threaded=True)
        try:
            self._gen = self.start(context, self._job)
        except HRCError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 1000)
        RUNNING.update(label=self.job_label, fraction=0.0, text="starting")
        self._status(context, "starting")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._stop(context)
            self.report({"WARNING"}, f"{self.job_label} cancelled; nothing was changed")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            fraction, text = next(self._gen)
        except StopIteration as stop:
            self._stop(context, close=False)
            try:
                report_messages(self, self.finish(context, stop.value))
            except HRCError as e:
                self.report({"ERROR"}, str(e))
                return {"CANCELLED"}
            except Exception as e:
                traceback.print_exc()
                self.report({"ERROR"}, f"internal error ({type(e).__name__}: {e}); see the console")
                return {"CANCELLED"}
            return {"FINISHED"}
        except HRCError as e:
            self._stop(context, close=False)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except Exception as e:
            self._stop(context, close=False)
            traceback.print_exc()
            self.report({"ERROR"}, f"internal error ({type(e).__name__}: {e}); see the console")
            return {"CANCELLED"}
        RUNNING.update(fraction=float(fraction), text=text)
        context.window_manager.progress_update(int(1000 * min(max(fraction, 0.0), 1.0)))
        self._status(context, text)
        return {"RUNNING_MODAL"}

    def cancel(self, context):  # Blender calls this when the window closes mid-job
        self._stop(context)

    def _status(self, context, text):
        RUNNING["text"] = text
        if context.workspace is not None:
            context.workspace.status_text_set(f"{self.job_label}: {text} ({RUNNING.get('fraction', 0) * 100:.0f} %) - Esc to cancel")
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()

    def _stop(self, context, close=True):
        self._job.cancel_event.set()  # a worker still running stops at its next check
        if close:
            self._gen.close()
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        RUNNING.clear()
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
