"""A job's result shown over several event-loop turns (one new layer per turn)."""

from __future__ import annotations

import pytest

from napari_dslrxr._widgets._jobs import run_in_worker

pytestmark = pytest.mark.gui


def test_result_steps_run_one_per_event_loop_turn_and_the_job_finishes_after_the_last(qtbot, wait_for_worker):
    from qtpy.QtCore import QTimer

    ticks = [0]
    heartbeat = QTimer()
    heartbeat.setInterval(2)
    heartbeat.timeout.connect(lambda: ticks.__setitem__(0, ticks[0] + 1))
    heartbeat.start()
    seen: list[tuple] = []  # (what, heartbeat ticks so far, job finished yet)
    worker = None

    def show(value):
        for step in range(3):
            if step:
                yield
            seen.append((f"step {step}: {value}", ticks[0], worker.dslrxr_finished))

    worker = run_in_worker(lambda: 7, desc="stepwise", progress_bar=False, on_returned=show,
                           on_finished=lambda: seen.append(("finished", ticks[0], worker.dslrxr_finished)))
    wait_for_worker(worker)
    heartbeat.stop()
    assert [what for what, _, _ in seen] == ["step 0: 7", "step 1: 7", "step 2: 7", "finished"]
    assert not any(done for _, _, done in seen), "the job counted as finished before its result was shown"
    step_ticks = [t for _, t, _ in seen[:3]]
    # Other timers ran between the steps: the event loop was not held through them all.
    assert step_ticks[0] < step_ticks[1] < step_ticks[2]


def test_a_failing_step_is_a_notification_and_the_job_still_finishes(qtbot, wait_for_worker, errors_shown):
    finished = []

    def show(_value):
        yield
        raise ValueError("bad step")

    worker = run_in_worker(lambda: 1, desc="stepwise", progress_bar=False, on_returned=show,
                           on_finished=lambda: finished.append(True))
    wait_for_worker(worker)
    assert finished == [True]
    assert len(errors_shown) == 1 and "stepwise" in errors_shown[0] and "bad step" in errors_shown[0]


def test_the_progress_bar_moves_with_a_deferred_repaint_not_an_immediate_one(qtbot):
    from qtpy.QtCore import QEvent, QObject

    from napari_dslrxr._widgets._jobs import JobPanel

    panel = JobPanel()
    bar = panel.bar.native
    qtbot.addWidget(panel.row.native)
    panel.row.native.show()
    qtbot.waitExposed(panel.row.native)
    paints = []

    class CountPaints(QObject):
        def eventFilter(self, watched, event):  # noqa: N802 - Qt's spelling
            if event.type() == QEvent.Type.Paint:
                paints.append(event)
            return False

    counter = CountPaints()
    bar.installEventFilter(counter)
    for permille in (100, 550, 1000, 0):
        paints.clear()
        panel._set_bar(permille)
        assert panel.bar.value == permille and bar.value() == permille
        assert not paints, "the bar repainted synchronously (and with it the whole window)"
        qtbot.waitUntil(lambda: bool(paints), timeout=2_000)  # repainted at the next turn


def test_a_step_that_adds_a_layer_has_the_window_repainted_a_turn_later_and_collections_wait(qtbot, wait_for_worker):
    """A step announced by NEXT_STEP_ADDS_LAYER runs with the window's updates off (its
    repaint is not served in the same block); they are on again before the next step and
    after the last, and the garbage collector, off while the result shows, is on again."""
    import gc

    from napari_dslrxr._widgets._jobs import JobPanel
    from napari_dslrxr._widgets._layers import NEXT_STEP_ADDS_LAYER

    panel = JobPanel()
    window = panel.row.native
    qtbot.addWidget(window)
    window.show()
    seen: list[tuple[str, bool, bool]] = []  # (step, window updates on, collector on)

    def show(_value):
        seen.append(("plain", window.updatesEnabled(), gc.isenabled()))
        yield NEXT_STEP_ADDS_LAYER
        seen.append(("adds", window.updatesEnabled(), gc.isenabled()))
        yield
        seen.append(("after", window.updatesEnabled(), gc.isenabled()))

    assert gc.isenabled()
    worker = run_in_worker(lambda: 1, desc="adds", on_returned=show, panel=panel)
    wait_for_worker(worker)
    assert seen == [("plain", True, False), ("adds", False, False), ("after", True, False)]
    assert window.updatesEnabled() and gc.isenabled()


def test_collections_held_twice_resume_at_the_last_release_and_a_host_collector_left_off_stays_off():
    import gc

    from napari_dslrxr._widgets._jobs import hold_collections

    assert gc.isenabled()
    first, second = hold_collections(), hold_collections()
    first()
    first()  # a second call of the same release changes nothing
    assert not gc.isenabled()
    second()
    assert gc.isenabled()
    gc.disable()
    try:
        hold_collections()()
        assert not gc.isenabled()
    finally:
        gc.enable()


def test_a_result_still_showing_after_the_hold_limit_gives_the_collector_back(qtbot, wait_for_worker, monkeypatch):
    """The collector's hold has a fail-safe: a display whose steps outlast it (or never end, the
    viewer closed midway) does not leave garbage collection off for the rest of the process."""
    import gc

    from napari_dslrxr._widgets import _jobs

    monkeypatch.setattr(_jobs, "COLLECTOR_HOLD_MAX_MS", 50)
    seen: list[bool] = []

    def show(_value):
        for _ in range(40):  # about 40 turns of SHOW_STEP_DELAY_MS each
            seen.append(gc.isenabled())
            yield

    worker = run_in_worker(lambda: 1, desc="long", on_returned=show)
    wait_for_worker(worker)
    assert not seen[0] and seen[-1], "the collector stayed off past the hold's limit"
    assert gc.isenabled()


def test_cancel_while_the_result_is_shown_closes_its_steps_and_no_later_step_runs(qtbot, wait_for_worker):
    """Cancel between two display steps: the display's generator is closed at its ``yield``
    (it can put back what it changed), no step runs after it, the job ends as cancelled."""
    from napari_dslrxr._widgets._jobs import JobPanel

    panel = JobPanel()
    seen: list[str] = []

    def show(_value):
        try:
            for step in range(6):
                seen.append(f"step {step}")
                if step == 1:
                    panel.cancel()  # from inside a step: takes effect once it returned
                yield
        except GeneratorExit:
            seen.append("closed")
            raise

    worker = run_in_worker(lambda: 1, desc="stepwise", panel=panel, on_returned=show,
                           on_finished=lambda: seen.append("finished"))
    wait_for_worker(worker)
    qtbot.wait(200)  # longer than the steps' timers
    assert seen == ["step 0", "step 1", "finished", "closed"]
    assert worker.dslrxr_cancelled and not panel.running and "cancelled" in panel.status.value
