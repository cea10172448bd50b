"""The worker-thread machinery of the long operators (Adapt, Bake): a Job runs core work (numpy, no
bpy) on a thread, a Run pairs that work with what to write to the scene when it is done, Modal gives an
operator invoke (from a button: a timer shows progress, Esc cancels) and execute (bpy.ops: waited for).
Nothing is written to the scene before the work is done, so a cancel leaves the scene as it was.
"""

from ..core.exceptions import HeadAdaptError


def show_progress(context, fraction, message):
    """Progress of a long operator: the window manager's bar (cursor), the status bar's text, and the
    scene setting progress_text the panels (and tests) read."""
    context.window_manager.progress_update(int(100 * fraction))
    text = f"HeadAdapt: {100 * fraction:.0f}% {message}" if message else ""
    context.scene.headadapt.progress_text = text
    if context.workspace is not None:
        context.workspace.status_text_set(text or None)


class Cancelled(Exception):
    """Raised inside a Job's work at its next progress step after cancel()."""


class Job:
    """A core computation (numpy, no bpy) on a worker thread, so Blender's window stays responsive:
    work(say) -> value, where say(fraction, message) reports progress and, after cancel(), stops the
    work at its next step (Cancelled). Nothing in the scene changes until the caller uses .value."""

    def __init__(self, work):
        import threading
        self.fraction, self.message, self.value, self.error = 0.0, "starting", None, None
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(work,), daemon=True)

    def start(self):
        self._thread.start()
        return self

    def _say(self, fraction, message):
        if self._cancel.is_set():
            raise Cancelled
        self.fraction, self.message = fraction, message

    def _run(self, work):
        try:
            self.value = work(self._say)
        except BaseException as exc:       # handed to the main thread, which reports it
            self.error = exc

    def cancel(self):
        self._cancel.set()

    @property
    def done(self):
        return not self._thread.is_alive()

    def wait(self, seconds=None):
        self._thread.join(seconds)
        return self.done


_RUNNING = []          # the Runs started from a button and not yet ended (one at a time: busy())


def busy():
    """What a long operator started from a button is doing now ('Adapt', 'Bake', 'Suggest the Rest'), or '' if none."""
    return _RUNNING[0].what if _RUNNING else ""


def drop_all(wm=None):
    """Cancel every running job and forget them (another file loaded, the add-on unregistered: their
    modal operators are gone, and nothing would end them); with the window manager, their timers, the
    progress cursor and the status bar's text go too."""
    for run in _RUNNING:
        run.job.cancel()
        if wm is not None and getattr(run, "timer", None) is not None:
            wm.event_timer_remove(run.timer)
    if _RUNNING and wm is not None:
        wm.progress_end()
        for window in wm.windows:
            window.workspace.status_text_set(None)
    _RUNNING.clear()


def alive(*ids):
    """Whether every Blender ID given is still there (not removed, not replaced by an undo)."""
    try:
        return all(data.name is not None for data in ids)
    except ReferenceError:
        return False


class Run:
    """A long operator's run (a subclass gives work and job, and finish): self.work(say) (numpy only) on a Job, self.finish(context, value, report)
    in the main thread when it is done. The modal operator feeds it its events (step); Esc cancels
    and leaves the scene as it was (nothing is written to the scene before finish). A run whose
    objects (self.needs()) were removed while it ran (deleted, or undone) writes nothing and says so."""
    what = "the work"

    def needs(self):
        """The Blender IDs finish writes to or reads from."""
        return ()

    def step(self, context, event_type, report):
        """Handle one event: ESC cancels, TIMER shows progress and finishes when the job is done;
        returns the operator's answer. report(kind set, text) as Operator.report."""
        if event_type == "ESC":
            self.job.cancel()
            self.end(context)
            report({"WARNING"}, f"{self.what} cancelled: the scene is as it was")
            return {"CANCELLED"}
        if event_type != "TIMER":
            return {"PASS_THROUGH"}
        if not self.job.done:
            show_progress(context, self.job.fraction, self.job.message)
            return {"RUNNING_MODAL"}
        if self.job.error is not None:
            self.end(context)
            if isinstance(self.job.error, HeadAdaptError):
                report({"ERROR"}, str(self.job.error))
                return {"CANCELLED"}
            raise self.job.error
        if not alive(*self.needs()):
            self.end(context)
            report({"ERROR"}, f"{self.what}: an object it works on was removed while it ran (deleted or undone); "
                              "nothing was written")
            return {"CANCELLED"}
        try:
            return self.finish(context, self.job.value, report)
        finally:
            self.end(context)

    def run_here(self, context, report):
        """The same work in the calling thread, waited for (bpy.ops from scripts and tests)."""
        context.window_manager.progress_begin(0, 100)
        try:
            value = self.work(lambda f, msg: show_progress(context, f, msg))
        except HeadAdaptError as exc:
            self.end(context)
            report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        try:
            return self.finish(context, value, report)
        finally:
            self.end(context)

    def end(self, context):
        if self in _RUNNING:
            _RUNNING.remove(self)
        context.window_manager.progress_end()
        context.scene.headadapt.progress_text = ""
        if context.workspace is not None:
            context.workspace.status_text_set(None)


class Modal:
    """invoke/modal of an operator whose make_run(context) gives a Run (or a problem string)."""

    def invoke(self, context, _event):
        """From a button: the work on a thread, progress and Esc through a timer."""
        if context.window is None:
            return self.execute(context)
        run = self.make_run(context)
        if isinstance(run, str):
            return self.fail(run)
        self._run = run
        wm = context.window_manager
        wm.progress_begin(0, 100)
        self._timer = run.timer = wm.event_timer_add(0.25, window=context.window)
        wm.modal_handler_add(self)
        _RUNNING.append(run)
        run.job.start()
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "Z" and getattr(event, "value", "") == "PRESS" and (
                getattr(event, "ctrl", False) or getattr(event, "oskey", False)):
            # an undo now would take back the step before the run (Calibrate), and the run's result
            # would then be thrown away as its objects' undoing: held until the run ends
            self.report({"WARNING"}, f"{self._run.what} is running: Esc cancels it; undo waits until it has ended")
            return {"RUNNING_MODAL"}
        answer = self._run.step(context, event.type, self.report)
        if answer & {"FINISHED", "CANCELLED"}:
            context.window_manager.event_timer_remove(self._timer)
        return answer

    def execute(self, context):
        """From Python (bpy.ops, scripts): the same work, waited for."""
        run = self.make_run(context)
        if isinstance(run, str):
            return self.fail(run)
        return run.run_here(context, self.report)
