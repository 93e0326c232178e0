"""The widgets' work off the GUI thread: thread workers with progress and cancel, and error reporting.

The widgets are thin: they read layers and widget values, call the headless core, and show
the results. Everything runs on the GUI thread except the work handed to
:func:`run_in_worker`, which never touches a widget or a layer; :class:`JobPanel` is the progress
bar and Cancel button of a widget, and :class:`EventLoopMonitor` measures how long the GUI
thread was blocked (the tests' responsiveness check).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import DslrxrError, WorkCancelled
from ._layers import NEXT_STEP_ADDS_LAYER


_LOG = logging.getLogger(__name__)

#: Delay between the steps of a result shown over several event-loop turns. A zero (or 1 ms)
#: timer is served before the timers that fall due during the canvas redraw the step before
#: posted, so that redraw and the next step ran back to back as one freeze; 20 ms lets the
#: redraw, then the other timers and input, run first (six steps: about 0.1 s later in all).
SHOW_STEP_DELAY_MS = 20


# --------------------------------------------------------------------------- notifications


def notify_error(exc: BaseException | str, *, context: str = "") -> str:
    """Show an error as a napari notification (never raise); return the message shown.

    A :class:`DslrxrError` is the user's one-line message; anything else is a bug and is
    logged with its traceback as well.
    """
    from napari.utils.notifications import show_error

    if isinstance(exc, str):
        message = exc
    elif isinstance(exc, DslrxrError):
        message = str(exc)
    else:
        _LOG.error("napari-dslrxr: unexpected error%s\n%s", f" in {context}" if context else "",
                   "".join(traceback.format_exception(exc)))
        message = f"unexpected {type(exc).__name__}: {exc}"
    text = f"{context}: {message}" if context else message
    show_error(text)
    return text


def notify_info(message: str) -> None:
    """Show an information notification."""
    from napari.utils.notifications import show_info

    show_info(message)


@contextmanager
def reported_errors(context: str = "") -> Iterator[None]:
    """Run a block from a button or slider; turn any exception into a notification."""
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - the viewer must survive any failure
        notify_error(exc, context=context)


def guarded(context: str) -> Callable[[Callable], Callable]:
    """Decorator form of :func:`reported_errors` for widget callbacks.

    The wrapper keeps the method's signature (``functools.wraps``), so a signal connected to
    it passes only the arguments the method takes (a button's ``changed`` passes none to
    ``run(self)``). When the method fails and its widget has a ``_readout`` label, the
    read-out says so instead of keeping an old "running..." text.
    """

    def decorate(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                return fn(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - the viewer must survive any failure
                text = notify_error(exc, context=context)
                readout = getattr(args[0], "_readout", None) if args else None
                if readout is not None:
                    try:
                        readout.value = f"not done: {text}"
                    except RuntimeError:  # widget already deleted
                        pass
                return None

        return wrapper

    return decorate


# --------------------------------------------------------------------------- workers


def readout_label() -> Any:
    """A magicgui Label for a widget's results: selectable, word-wrapped (keeps the dock narrow)."""
    from magicgui.widgets import Label
    from qtpy.QtCore import Qt

    label = Label(value="")
    label.native.setWordWrap(True)
    label.native.setMinimumWidth(300)
    label.native.setAlignment(Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignVCenter)
    label.native.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
    return label


#: Lines a read-out shows before it scrolls (:func:`scroll_long_readout`).
READOUT_MAX_LINES = 10


def scroll_long_readout(label: Any, max_lines: int = READOUT_MAX_LINES) -> Any:
    """Put a read-out (:func:`readout_label`, already placed in its widget) in a scroll area
    ``max_lines`` lines high; return the scroll area.

    The docks have no scroll area of their own: a result's read-out of a dozen wrapped lines
    (detector quality, diagnosis, PSF fit) raised the widget's minimum height above the
    window's, so Qt grew the main window past the screen (1000 to 1112 px) and resized the
    canvas, whose full redraw fell in the turn that showed the result.
    """
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QFrame, QScrollArea, QSizePolicy

    native = label.native
    parent = native.parentWidget()
    layout = None if parent is None else parent.layout()
    scroll = QScrollArea()
    scroll.setWidgetResizable(True)
    scroll.setFrameShape(QFrame.Shape.NoFrame)
    scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    scroll.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Preferred)
    # A fixed height: a result of any length then changes nothing in the dock's layout (no
    # relayout in the turn that shows it); longer text scrolls.
    scroll.setFixedHeight(max_lines * native.fontMetrics().lineSpacing() + 6)
    scroll.setMinimumWidth(native.minimumWidth())
    if layout is not None:
        layout.replaceWidget(native, scroll)
    scroll.setWidget(native)
    scroll.setToolTip(label.tooltip or "")
    return scroll


class JobPanel:
    """Progress bar, Cancel button and status line of a widget's long operation.

    Lives inside the widget (not only in napari's activity dock). The bar is determinate when
    the job reports ``(done, total)`` (a generator yielding them, or the core's progress
    callback :meth:`callback`), else busy. Cancel stops a job at its next progress report
    (generator step or callback) and at once detaches it from the widget: the buttons are
    enabled again, its result is never shown (no half-made layer), and a job without progress
    reports that is still computing is left to finish in its thread, unseen. A job whose
    result is being shown over several event-loop turns stops showing it: the display's
    generator is closed at its current step and puts back what it changed (``run_in_worker``).
    """

    #: How often the bar follows the progress the worker thread reports. Every change of the
    #: bar or the status repaints the main window (with napari's GL canvas composed in), so
    #: they change only when what they show changes: the bar by whole percents, the elapsed
    #: time by whole seconds, and no busy animation (it repaints continuously).
    POLL_MS = 250

    def __init__(self, cancel_text: str = "Cancel", tooltip: str = "stop the running operation; "
                 "nothing of it is shown"):
        from magicgui.widgets import Container, ProgressBar, PushButton

        self.bar = ProgressBar(value=0, min=0, max=1000, label="progress")
        self.bar.native.setTextVisible(False)
        self.bar.tooltip = "progress of the running operation"
        self.cancel_button = PushButton(text=cancel_text, enabled=False, tooltip=tooltip)
        self.status = readout_label()  # word-wrapped: a long message must not widen the dock
        self.status.value = "idle"
        # Two lines, fixed: the status changes every tick while a job runs, and a label that
        # changed height would re-lay out (and redraw) the whole widget each time.
        metrics = self.status.native.fontMetrics()
        self.status.native.setFixedHeight(2 * metrics.lineSpacing() + 4)
        self.status.tooltip = "state of the last operation started from this widget"
        self.row = Container(widgets=[self.bar, self.cancel_button], layout="horizontal", labels=False)
        self.row.margins = (0, 0, 0, 0)
        self.cancel_event = threading.Event()
        self.worker = None
        self.desc = ""
        self._state: tuple = ()
        self._started = 0.0
        self._on_detach: Callable[[], None] | None = None
        self.cancel_button.changed.connect(self.cancel)
        from qtpy.QtCore import QTimer

        self._timer = QTimer(self.row.native)
        self._timer.setInterval(self.POLL_MS)
        self._timer.timeout.connect(self._tick)

    @property
    def widgets(self) -> list:
        """The magicgui widgets to place in the stage widget."""
        return [self.row, self.status]

    @property
    def running(self) -> bool:
        return self.worker is not None

    # -- called from the worker thread ----------------------------------------------------------
    def callback(self, *args: Any) -> None:
        """Progress callback for the core: ``(done, total)`` or a message; raises
        :class:`WorkCancelled` once Cancel was pressed (the core stops there)."""
        if self.cancel_event.is_set():
            raise WorkCancelled(f"{self.desc}: cancelled")
        self._state = args

    # -- GUI thread -----------------------------------------------------------------------------
    def begin(self, worker: Any, desc: str, on_detach: Callable[[], None] | None) -> None:
        self.cancel_event.clear()
        self.worker, self.desc, self._on_detach = worker, desc, on_detach
        self._state = ()
        self._started = time.perf_counter()
        self._set_bar(0)
        self.cancel_button.enabled = True
        self.status.value = f"{desc}: running..."
        self._timer.start()

    def update(self, value: Any) -> None:
        """Take ``(done, total)`` (from a generator's yield) or a message; shown at the next
        tick (a job yielding fast must not flood the GUI thread with repaints)."""
        self._state = tuple(value) if isinstance(value, (tuple, list)) else (value,)

    def _tick(self) -> None:
        if self.worker is None:
            return
        state, elapsed = self._state, time.perf_counter() - self._started
        message = ""
        if len(state) == 2 and all(isinstance(v, (int, float, np.integer, np.floating)) for v in state):
            done, total = (float(v) for v in state)
            if total > 0:
                permille = 10 * int(100 * min(max(done / total, 0.0), 1.0))
                self._set_bar(permille)
        elif len(state) == 1 and isinstance(state[0], str):
            message = f" ({state[0]})"
        text = f"{self.desc}: running {int(elapsed)} s{message}"
        if self.status.value != text:
            self.status.value = text

    def _set_bar(self, permille: int) -> None:
        """Move the bar without an immediate repaint: QProgressBar.setValue repaints at once,
        and with napari's GL canvas in the window that composes the whole window (and draws
        the canvas if a redraw is pending) then and there, 0.05-0.2 s under software GL. With
        updates off the value changes silently; turning them on asks for an ordinary, deferred
        repaint."""
        if self.bar.value == permille:
            return
        native = self.bar.native
        native.setUpdatesEnabled(False)
        try:
            self.bar.value = permille
        finally:
            native.setUpdatesEnabled(True)

    def end(self, worker: Any, outcome: str) -> bool:
        """The job's thread ended; returns False when the job was detached already (cancelled)."""
        if worker is not self.worker:
            return False
        self._finish(outcome)
        return True

    def _finish(self, outcome: str) -> None:
        self._timer.stop()
        self.worker = None
        self._set_bar(0)
        self.cancel_button.enabled = False
        self.status.value = outcome
        on_detach, self._on_detach = self._on_detach, None
        if on_detach is not None:
            with reported_errors(self.desc):
                on_detach()

    def cancel(self) -> None:
        """Stop the running job (button slot); a no-op when nothing runs."""
        worker = self.worker
        if worker is None:
            return
        self.cancel_event.set()
        worker.dslrxr_cancelled = True
        quit_ = getattr(worker, "quit", None)
        if quit_ is not None:
            quit_()
        desc = self.desc
        self._finish(f"{desc}: cancelled")
        stop_display = getattr(worker, "dslrxr_stop_display", None)
        if stop_display is not None:  # its result was being shown: stop, and put back what it changed
            stop_display()
        notify_info(f"{desc}: cancelled")


def hold_repaints(widget: Any) -> Callable[[], None]:
    """Hold back the repaints of ``widget``'s window (the viewer's main window when the widget
    is docked in it); return the function that lets them go.

    A step that adds a layer is followed by the window's repaint (layer list, new controls,
    canvas). Qt serves that repaint before any timer or input, so the step and the repaint
    froze the viewer as one block (together over 0.1 s under software GL). With updates off
    during the step, Qt repaints the window once when they are turned on again (deferred), in
    a later turn, and the viewer answers in between. A window already held is left alone.
    """
    window = None if widget is None else widget.window()
    if window is None or not window.updatesEnabled():
        return lambda: None
    window.setUpdatesEnabled(False)

    def release() -> None:
        try:
            window.setUpdatesEnabled(True)
        except RuntimeError:  # the window was closed meanwhile
            pass

    return release


_COLLECTOR_HOLDS = [0]
#: The longest a result's display holds the garbage collector (its steps take about 1 s).
COLLECTOR_HOLD_MAX_MS = 10_000


def hold_collections() -> Callable[[], None]:
    """Postpone Python's automatic garbage collections while a result is shown; return the
    function that allows them again (call it once).

    Adding a layer allocates tens of thousands of objects, so the collector's full pass (over
    every object made since the viewer opened: about 0.1 s of GUI time after a few results)
    tended to fall inside a step that adds a layer, and the two froze the viewer as one block.
    Held for the second or so a result takes to show, it runs after the result is shown, not
    on top of a step's work. Nested holds (two results showing at once) release at the last; a collector the
    host application turned off stays off.
    """
    import gc

    if _COLLECTOR_HOLDS[0] == 0:
        if not gc.isenabled():
            return lambda: None
        gc.disable()
    _COLLECTOR_HOLDS[0] += 1
    released = [False]

    def release() -> None:
        if released[0]:
            return
        released[0] = True
        _COLLECTOR_HOLDS[0] -= 1
        if _COLLECTOR_HOLDS[0] == 0:
            gc.enable()

    return release


def job_done(button: Any, panel: JobPanel, readout: Any) -> Callable[[], None]:
    """The ``on_finished`` of a widget's job (any outcome): its button enabled again, and the
    read-out, if still at a "...ing..." text, replaced by the outcome in the panel's status
    (it never stays at "running..." after an error or a cancel)."""

    def done() -> None:
        button.enabled = True
        if readout.value.endswith("..."):
            readout.value = panel.status.value

    return done


def run_in_worker(work: Callable, *args: Any, desc: str,
                  on_returned: Callable[[Any], None],
                  on_finished: Callable[[], None] | None = None,
                  progress_bar: bool = True,
                  panel: JobPanel | None = None,
                  readout: Any = None,
                  **kwargs: Any):
    """Run ``work(*args, **kwargs)`` in a napari thread worker.

    Parameters
    ----------
    work : callable
        Either a generator function that yields ``(done, total)`` and returns its result
        (``worker.quit()`` stops it at the next yield), or a plain function.
    desc : str
        What runs, for the progress display and messages.
    on_returned : callable
        Called on the GUI thread with the result; exceptions in it become notifications.
        Never called for a cancelled job. When it is a generator function, each ``yield``
        hands the event loop back (the viewer draws and takes input) before the next step
        runs: a result made of several new layers is shown one layer per event-loop turn
        (napari builds each new layer's controls and visual on the GUI thread, 0.1-0.4 s each
        under software GL), and the job counts as finished after the last step. A step that
        yields :data:`NEXT_STEP_ADDS_LAYER` announces that the next one adds a layer: the
        window's repaint after it waits a turn (:func:`hold_repaints`). Python's automatic
        garbage collections wait until the last step (:func:`hold_collections`). When the job
        is cancelled while its steps run, the generator is closed (``GeneratorExit`` at its
        current ``yield``) and no further step runs; a generator that makes layers puts back
        what it changed then, and when a step raises (:class:`._layers.ShownLayers`).
    on_finished : callable, optional
        Called on the GUI thread once the job is over for the widget: after success, error,
        or at once when Cancel is pressed (e.g. to re-enable a button).
    progress_bar : bool
        Without a ``panel``: show a bar in napari's activity dock (off for live previews).
    panel : JobPanel, optional
        The widget's own progress bar and Cancel button; pass ``progress=panel.callback`` to
        a core function that takes a progress callback so Cancel stops it promptly.
    readout : magicgui Label, optional
        Set to the error message when the job fails, so it never keeps "running...".

    Returns
    -------
    napari.qt.threading.WorkerBase
        The started worker. Its attribute ``dslrxr_finished`` becomes True on the GUI thread
        once the thread ended and ``on_returned``/``on_finished`` have run (tests wait for it
        with ``qtbot.waitUntil``); ``dslrxr_cancelled`` is True when the user cancelled it.
    """
    from napari.qt.threading import GeneratorWorker, create_worker
    from napari.utils import cancelable_progress, progress

    worker = create_worker(work, *args, _start_thread=False, _ignore_errors=True, **kwargs)
    worker.dslrxr_finished = False
    worker.dslrxr_cancelled = False
    pbar = None
    if panel is not None:
        panel.begin(worker, desc, on_finished)
        if isinstance(worker, GeneratorWorker):
            worker.yielded.connect(panel.update)
    elif progress_bar and isinstance(worker, GeneratorWorker):
        pbar = cancelable_progress(total=0, desc=desc, cancel_callback=worker.quit)

        def _yielded(value: Any) -> None:
            try:
                done, total = (int(v) for v in value)
            except (TypeError, ValueError):
                return
            if pbar.total != total:
                pbar.total = total
            if done > pbar.n:
                pbar.update(done - pbar.n)

        worker.yielded.connect(_yielded)
        worker.aborted.connect(lambda: notify_info(f"{desc}: cancelled"))
    elif progress_bar:
        pbar = progress(total=0, desc=desc)
    outcome = {"text": f"{desc}: done"}
    # The steps of a result shown over several event-loop turns, and whether the thread's end
    # came while they ran (the job finishes after the last step).
    showing: dict[str, Any] = {"steps": None, "finish_after": False, "in_step": False, "stop": False}

    def _returned(result: Any) -> None:
        from qtpy.QtCore import QTimer

        worker.dslrxr_returned_at = time.perf_counter()  # the result reaches the GUI thread
        if worker.dslrxr_cancelled:
            return
        started = getattr(panel, "_started", None)
        if started:
            outcome["text"] = f"{desc}: done in {time.perf_counter() - started:.1f} s"
        with reported_errors(desc):
            shown = on_returned(result)
            if isinstance(shown, Iterator):
                showing["steps"] = shown
                release_collector = hold_collections()
                showing["release_collector"] = release_collector
                # a fail-safe: if the steps never finish (the viewer closed midway), collections
                # resume anyway rather than stay off for the rest of the process
                QTimer.singleShot(COLLECTOR_HOLD_MAX_MS, release_collector)
                _next_step()

    def _next_step() -> None:
        from qtpy.QtCore import QTimer

        steps = showing["steps"]
        if steps is None:  # stopped (cancelled) meanwhile
            return
        release = showing.pop("release_repaints", lambda: None)
        showing["in_step"] = True
        try:
            if next(steps) is NEXT_STEP_ADDS_LAYER:
                showing["release_repaints"] = hold_repaints(None if panel is None else panel.row.native)
        except StopIteration:
            steps = None
        except Exception as exc:  # noqa: BLE001 - the viewer must survive any failure
            text = notify_error(exc, context=desc)
            outcome["text"] = f"failed: {text}"  # not "done" in the status and the read-out
            if readout is not None:
                try:
                    readout.value = f"failed: {text}"
                except RuntimeError:
                    pass
            steps = None
        finally:
            showing["in_step"] = False
        if showing["stop"] and steps is not None:  # cancelled from inside this step
            release()
            _stop_display()
            return
        QTimer.singleShot(SHOW_STEP_DELAY_MS, lambda: _repainted(release, steps is not None))

    def _stop_display() -> None:
        """Cancel while the result is shown: the steps' generator closed (it puts back what it
        changed), no further step; the job ends."""
        steps = showing["steps"]
        if steps is None:
            return
        if showing["in_step"]:  # Cancel from inside a step (a nested event loop): after it
            showing["stop"] = True
            return
        showing["steps"] = None
        showing.pop("release_repaints", lambda: None)()
        try:
            steps.close()
        except Exception as exc:  # noqa: BLE001 - the viewer must survive any failure
            notify_error(exc, context=desc)
        showing.pop("release_collector", lambda: None)()
        if showing["finish_after"]:
            showing["finish_after"] = False  # once (a step's timer may still be pending)
            _finished()

    worker.dslrxr_stop_display = _stop_display

    def _repainted(release: Callable[[], None], more: bool) -> None:
        from qtpy.QtCore import QTimer

        release()  # a held window repaints now, a turn after the step that added a layer
        if more and showing["steps"] is None:  # stopped (cancelled) meanwhile
            return
        if more:
            QTimer.singleShot(SHOW_STEP_DELAY_MS, _next_step)
            return
        showing["steps"] = None
        showing.pop("release_collector", lambda: None)()
        if showing["finish_after"]:
            _finished()

    def _finished() -> None:
        if showing["steps"] is not None:
            showing["finish_after"] = True  # finish once the result is shown
            return
        if pbar is not None:
            pbar.close()
        if panel is not None:
            if panel.end(worker, outcome["text"]):
                pass  # on_finished ran as the panel's detach hook
        elif on_finished is not None:
            with reported_errors(desc):
                on_finished()
        worker.dslrxr_finished = True  # set on the GUI thread after the result was shown

    def _errored(exc: BaseException) -> None:
        if worker.dslrxr_cancelled:
            return  # the user was told when pressing Cancel
        if isinstance(exc, WorkCancelled):
            outcome["text"] = f"{desc}: cancelled"
            notify_info(f"{desc}: cancelled")
            return
        text = notify_error(exc, context=desc)
        outcome["text"] = f"failed: {text}"
        if readout is not None:
            try:
                readout.value = f"failed: {text}"
            except RuntimeError:
                pass

    worker.returned.connect(_returned)
    worker.errored.connect(_errored)
    worker.finished.connect(_finished)
    worker.start()
    return worker


# --------------------------------------------------------------------------- responsiveness


class EventLoopMonitor:
    """How long the GUI thread was blocked: the largest gap between ticks of a fast timer.

    ``start()``, do things (click, wait for workers), ``stop()`` returns the largest gap in
    seconds (the timer interval included, so an idle loop gives about ``interval_ms``).
    """

    def __init__(self, interval_ms: int = 5):
        from qtpy.QtCore import QTimer

        self.interval_s = interval_ms / 1000.0
        self._timer = QTimer()
        self._timer.setInterval(interval_ms)
        self._timer.timeout.connect(self._tick)
        self.max_gap_s = 0.0
        self._last = 0.0
        self.gaps: list[tuple[float, float]] = []  # (start, end) of every gap over 3 intervals

    def start(self) -> EventLoopMonitor:
        self.max_gap_s = 0.0
        self.gaps = []
        self._last = time.perf_counter()
        self._timer.start()
        return self

    def _tick(self) -> None:
        now = time.perf_counter()
        gap = now - self._last
        self.max_gap_s = max(self.max_gap_s, gap)
        if gap > 3 * self.interval_s:
            self.gaps.append((self._last, now))
        self._last = now

    def max_gap_between(self, start: float, end: float) -> float:
        """Largest gap that ended in ``(start, end]`` (e.g. while a worker computed: a gap
        ending after the result arrived was caused by showing it)."""
        inside = [b - a for a, b in self.gaps if start < b <= end]
        return max(inside, default=self.interval_s)

    def stop(self) -> float:
        self._tick()
        self._timer.stop()
        return self.max_gap_s


class ReportButtonsMixin:
    """The run, "Write report" and "Open report" buttons of a measuring widget.

    The widget provides ``_run``, ``_write`` and ``_open`` (push buttons), ``_readout``,
    ``_job`` (:class:`JobPanel`), ``result`` (None until a run showed one) and
    ``report_paths`` (the report writer's paths by name), and sets :attr:`REPORT_PAGE` (the
    key of the page to open) and :attr:`REPORT_NAME` (for the messages).
    """

    REPORT_PAGE = "report"
    REPORT_NAME = "report"

    def _done(self) -> None:
        """The run's job is over (any outcome): :func:`job_done` of the run button."""
        job_done(self._run, self._job, self._readout)()

    def _written(self, folder: Path, paths: dict) -> None:
        self.report_paths = paths
        self._open.enabled = True
        notify_info(f"{self.REPORT_NAME} written to {folder}")

    def _write_done(self) -> None:
        self._write.enabled = self.result is not None

    @guarded("open report")
    def open_report(self) -> bool:
        """Open the report's page in the web browser."""
        import webbrowser

        page = self.report_paths.get(self.REPORT_PAGE)
        if page is None or not Path(page).is_file():
            from ..core.errors import ParameterError

            raise ParameterError("write the report first")
        return webbrowser.open(Path(page).resolve().as_uri())
