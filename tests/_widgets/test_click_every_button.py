"""Every push button of every widget, clicked with the mouse as a user does.

The plugin is opened the way ``dslrxr view`` opens it (every widget of the manifest docked,
tabbed), every sample is loaded through the plugin's sample commands (*File > Open Sample*),
then each widget's buttons are clicked with ``qtbot.mouseClick`` in the order a user would:
refusals first (a clear message is asserted as such), then the work, the buttons enabled only
after it (save psf.json, write and open the report) and Cancel while a job runs. Buttons are
enumerated from the Qt widget tree, so a new button fails :func:`check_all_clicked` until a
test clicks it. Every click is timed with an event-loop heartbeat into :data:`GAPS`; the
limit on those gaps is checked by benchmarks/bench_gui_responsiveness.py, not here (timings
are benchmarks, not unit tests).

The README screenshots are taken on this path, after the clicks: into ``docs/screenshots/``
with ``DSLRXR_UPDATE_SCREENSHOTS=1``, else into a temporary folder (an ordinary run leaves the
working tree clean).
"""

from __future__ import annotations

import os
import threading
import time
import webbrowser
from html import unescape
from pathlib import Path

import numpy as np
import pytest
from napari.utils.notifications import NotificationSeverity, notification_manager

from napari_dslrxr import _sample_data as samples
from napari_dslrxr._cli.view import plugin_widget_names, populate_viewer
from napari_dslrxr._widgets import contrast as contrast_module
from napari_dslrxr._widgets import deconvolution as deconvolution_module
from napari_dslrxr._widgets import qc as qc_module
from napari_dslrxr._widgets._jobs import EventLoopMonitor
from napari_dslrxr._widgets._layers import viewer_camera
from napari_dslrxr.core.psf.edge_images import MIN_ROI_PX
from napari_dslrxr.core.qc import QcParams
from napari_dslrxr.core.stages.contrast import ContrastParams
from napari_dslrxr.core.errors import WorkCancelled
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.psf import PSFModel, load_psf, save_psf

pytestmark = pytest.mark.gui

#: Longest GUI-thread block by (widget, button), in three phases: the click handler itself,
#: while the job computed in its worker, and showing the result (read by the benchmark).
GAPS: dict[tuple[str, str], dict[str, float]] = {}
#: Layers each job's result added, by (widget, button): ``(name, event-loop turn, repaints
#: held)`` (:class:`LayerAdds`); checked in :meth:`Plugin.click`.
RESULT_ADDS: dict[tuple[str, str], list[tuple[str, int, bool]]] = {}
#: The samples every test opens (the set holds radiograph, flat and dark); the first test opens
#: the three single ones too, so every sample command of the manifest is used.
SAMPLE_KEYS = ("dslr_set", "edges", "scene", "qc_set")
SINGLE_SAMPLE_KEYS = ("radiograph", "flat", "dark")
DOCS_SHOTS = Path(__file__).resolve().parents[2] / "docs" / "screenshots"


class LayerAdds:
    """The layers added to the viewer while it watches: their time, name, event-loop turn
    and whether the window's repaints were held then.

    A turn is the run of code between two passes of the event loop: a second layer added
    before the zero-delay timer that the first one posted has fired was added in the same
    turn (one freeze of the viewer).
    """

    def __init__(self, viewer):
        self.viewer = viewer
        self.window = viewer.window._qt_window
        self.adds: list[tuple[float, str, int, bool]] = []
        self._turn, self._in_turn = 0, False
        viewer.layers.events.inserted.connect(self._inserted)

    def _inserted(self, event) -> None:
        from qtpy.QtCore import QTimer

        if not self._in_turn:
            self._turn += 1
            self._in_turn = True
            QTimer.singleShot(0, self._turn_over)
        self.adds.append((time.perf_counter(), event.value.name, self._turn, not self.window.updatesEnabled()))

    def _turn_over(self) -> None:
        self._in_turn = False

    def since(self, start: float) -> list[tuple[str, int, bool]]:
        return [(name, turn, held) for t, name, turn, held in self.adds if t >= start]

    def close(self) -> None:
        self.viewer.layers.events.inserted.disconnect(self._inserted)


class Plugin:
    """A viewer opened like ``dslrxr view`` with every sample loaded, and a clicker."""

    def __init__(self, viewer, qtbot):
        self.viewer, self.qtbot = viewer, qtbot
        self.widgets = dict(zip(plugin_widget_names(), populate_viewer(viewer, []), strict=True))
        for key in SAMPLE_KEYS:
            viewer.open_sample("napari-dslrxr", key)
        self.clicked: dict[str, set[str]] = {name: set() for name in self.widgets}
        self._seen = len(notification_manager.records)

    # -- buttons ----------------------------------------------------------------------------
    def buttons(self, widget_name: str) -> dict[str, object]:
        """Every QPushButton of the widget by its text (a FileEdit's "Select file" included)."""
        from qtpy.QtWidgets import QPushButton

        found: dict[str, object] = {}
        for button in self.widgets[widget_name].native.findChildren(QPushButton):
            text = button.text()
            key, n = text, 2
            while key in found:  # two file pickers both say "Select file"
                key, n = f"{text} #{n}", n + 1
            found[key] = button
        return found

    def show(self, widget_name: str) -> None:
        """Bring the widget's tab to the front (a user clicks the tab)."""
        from qtpy.QtWidgets import QApplication, QDockWidget

        native = self.widgets[widget_name].native
        dock = native
        while dock is not None and not isinstance(dock, QDockWidget):
            dock = dock.parent()
        dock.raise_()
        QApplication.processEvents()

    def click(self, widget_name: str, text: str, *, refused: str | None = None, wait: bool = True,
              timeout_ms: int = 60_000) -> list[str]:
        """Click a button, wait for the job it starts, check the notifications.

        ``refused``: the click must give exactly one error notification containing it (a
        clear refusal); otherwise it must give none. Returns the new notification texts.
        """
        from qtpy.QtCore import Qt

        self.show(widget_name)
        button = self.buttons(widget_name)[text]
        assert button.isEnabled(), f"{widget_name}: '{text}' is disabled"
        widget = self.widgets[widget_name]
        monitor = EventLoopMonitor().start()
        adds = LayerAdds(self.viewer)
        clicked_at = time.perf_counter()
        self.qtbot.mouseClick(button, Qt.MouseButton.LeftButton)
        handled_at = time.perf_counter()
        job = getattr(widget, "_job", None)
        worker = None if job is None else job.worker
        try:
            if wait and worker is not None:
                self.qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=timeout_ms)
            self.qtbot.wait(20)
        finally:
            monitor.stop()
            adds.close()
        if wait and worker is not None and not worker.dslrxr_cancelled:
            self.check_result_adds(widget_name, text, adds.since(getattr(worker, "dslrxr_returned_at", handled_at)))
        phases = GAPS.setdefault((widget_name, text), {"click": 0.0, "job": 0.0, "result": 0.0})
        phases["click"] = max(phases["click"], handled_at - clicked_at)
        if wait and worker is not None:
            returned_at = getattr(worker, "dslrxr_returned_at", time.perf_counter())
            phases["job"] = max(phases["job"], monitor.max_gap_between(handled_at, returned_at))
            phases["result"] = max(phases["result"], monitor.max_gap_between(returned_at, float("inf")))
            # the GUI thread's own CPU time in its longest turn, when the monitor measures it
            # (the benchmark's does: on a loaded machine a gap's length is mostly waiting)
            cpu_between = getattr(monitor, "max_cpu_between", None)
            if cpu_between is not None:
                for phase, (a, b) in {"job_cpu": (handled_at, returned_at),
                                      "result_cpu": (returned_at, float("inf"))}.items():
                    phases[phase] = max(phases.get(phase, 0.0), cpu_between(a, b))
        self.clicked[widget_name].add(text)
        return self.check_notifications(f"{widget_name}: '{text}'", refused)

    @staticmethod
    def check_result_adds(widget_name: str, text: str, added: list[tuple[str, int, bool]]) -> None:
        """A job's result adds its layers one per event-loop turn, each in a step announced
        as adding a layer (the window's repaints held; see ``run_in_worker``): napari builds a
        new layer's controls and visual in that turn, about 80 ms of GUI time idle, so two in
        one turn, or one with the window's repaint on top, freeze the viewer past 0.1 s."""
        RESULT_ADDS.setdefault((widget_name, text), []).extend(added)
        turns = [turn for _, turn, _ in added]
        crowded = [name for name, turn, _ in added if turns.count(turn) > 1]
        assert not crowded, f"{widget_name}: '{text}' added {crowded} in one event-loop turn"
        unheld = [name for name, _, held in added if not held]
        assert not unheld, f"{widget_name}: '{text}' added {unheld} without holding the window's repaints"

    def toggle_live_preview(self, widget_name: str, preview: str) -> None:
        """The live preview layer appears only when switched on, and goes when switched off."""
        widget, layers = self.widgets[widget_name], self.viewer.layers
        assert preview not in layers
        widget._live.value = True
        self.qtbot.waitUntil(lambda: preview in layers, timeout=20_000)
        widget._live.value = False
        assert preview not in layers
        self.check_notifications(f"{widget_name} preview")

    def snap(self, folder: Path, name: str, widget_name: str, visible: list[str], *,
             center: tuple[float, float] | None = None, zoom: float | None = None) -> Path:
        """Only the ``visible`` layers shown, the widget's tab in front, the whole window
        saved at 1300x800; the canvas must show something (black = broken GL)."""
        from qtpy.QtWidgets import QApplication

        viewer = self.viewer
        for layer in viewer.layers:
            layer.visible = layer.name in visible
        viewer.layers.selection.active = viewer.layers[visible[-1]]
        self.show(widget_name)
        viewer.window.resize(1300, 800)
        for _ in range(5):
            QApplication.processEvents()
        # Frame the shown layers (napari's reset_view frames hidden ones too).
        extents = np.array([viewer.layers[n].extent.world[:, -2:] for n in visible])
        lo, hi = extents[:, 0].min(axis=0), extents[:, 1].max(axis=0)
        canvas_h, canvas_w = viewer.canvas.size
        camera = viewer_camera(viewer)
        camera.center = (0, *(center if center is not None else (lo + hi) / 2))
        camera.zoom = zoom if zoom is not None else 0.9 * min(canvas_h / max(hi[0] - lo[0], 1e-9),
                                                              canvas_w / max(hi[1] - lo[1], 1e-9))
        # No notification toast over the canvas.
        from napari._qt.dialogs.qt_notification import NapariQtNotification

        for toast in viewer.window._qt_window.findChildren(NapariQtNotification):
            toast.close()
        self.qtbot.wait(50)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{name}.png"
        window = viewer.screenshot(str(path), canvas_only=False, flash=False)
        canvas = viewer.screenshot(canvas_only=True, flash=False)
        assert window.shape[0] >= 700 and window.shape[1] >= 1200
        assert canvas[..., :3].mean() > 5, "canvas rendered black (GL under the virtual display?)"
        return path

    def check_notifications(self, what: str, refused: str | None = None) -> list[str]:
        new = notification_manager.records[self._seen:]
        self._seen = len(notification_manager.records)
        errors = [str(n.message) for n in new if n.severity >= NotificationSeverity.ERROR]
        assert not any("unexpected" in e or "Traceback" in e for e in errors), (what, errors)
        if refused is None:
            assert not errors, f"{what} gave error notifications: {errors}"
        else:
            assert len(errors) == 1 and refused in errors[0], f"{what}: expected a refusal '{refused}', got {errors}"
        return [str(n.message) for n in new]

    def check_all_clicked(self, widget_name: str) -> None:
        missing = set(self.buttons(widget_name)) - self.clicked[widget_name]
        assert not missing, f"{widget_name}: buttons no test clicks: {sorted(missing)}"


@pytest.fixture
def shots(tmp_path) -> Path:
    """Where screenshots go: the README's folder only when asked to refresh it."""
    return DOCS_SHOTS if os.environ.get("DSLRXR_UPDATE_SCREENSHOTS") == "1" else tmp_path / "screenshots"


@pytest.fixture
def plugin(make_napari_viewer, qtbot, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # files chosen by name land here (and short names show in pictures)
    viewer = make_napari_viewer(show=True)
    return Plugin(viewer, qtbot)


def gate(module, name: str, monkeypatch) -> threading.Event:
    """Hold ``module.name`` (the core call a widget runs) until the returned event is set,
    so Cancel is clicked while the job certainly runs. Generator functions stay generators."""
    import inspect

    real = getattr(module, name)
    release = threading.Event()
    if inspect.isgeneratorfunction(real):
        def held(*args, **kwargs):
            yield (0, 1)
            release.wait(20)
            return (yield from real(*args, **kwargs))
    else:
        def held(*args, **kwargs):
            release.wait(20)
            return real(*args, **kwargs)
    monkeypatch.setattr(module, name, held)
    return release


class _Hold(threading.Event):
    """A gate that remembers when it was opened."""

    released_at = float("nan")

    def set(self) -> None:
        self.released_at = time.perf_counter()
        super().set()


def hold_halfway(panel, monkeypatch) -> _Hold:
    """Hold the core stage at its first progress report past half of its steps until the
    returned event is set (just after Cancel was clicked), so Cancel is clicked while the real
    stage certainly runs (nothing of the core is replaced); after the hold, the panel's own
    callback stops it at its next report. The event's ``reports`` lists the progress the
    stage reported and ``stop_s`` the seconds from the release to the core's stop."""
    real = panel.callback
    release = _Hold()
    release.reached = threading.Event()  # the stage waits at its halfway report
    release.reports = []
    release.stop_s = float("inf")

    def held(*args):
        release.reports.append(args)
        try:
            real(*args)
        except WorkCancelled:
            release.stop_s = time.perf_counter() - release.released_at
            raise
        if len(args) == 2 and 2 * args[0] >= args[1] and not release.is_set():
            release.reached.set()
            release.wait(20)

    monkeypatch.setattr(panel, "callback", held)
    return release


def cancel_running(plugin: Plugin, widget_name: str, start: str, cancel: str, release: threading.Event | None,
                   result_layer: str) -> float:
    """Start a job, click Cancel while it runs; the widget is usable at once, the job's thread
    ends, and its result layer never appears. Returns seconds from Cancel to the thread's end."""
    widget = plugin.widgets[widget_name]
    plugin.click(widget_name, start, wait=False)
    worker = widget._job.worker
    assert worker is not None and widget._job.running, f"{widget_name}: '{start}' started no job"
    if hasattr(release, "reached"):  # held inside the core: Cancel when it got there
        plugin.qtbot.waitUntil(release.reached.is_set, timeout=60_000)
    plugin.click(widget_name, cancel)
    clicked_at = time.perf_counter()
    assert not widget._job.running and "cancelled" in widget._job.status.value
    if release is not None:
        release.set()
    plugin.qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=60_000)
    stopped_s = time.perf_counter() - clicked_at
    assert result_layer not in plugin.viewer.layers, f"{widget_name}: cancelled job left '{result_layer}'"
    return stopped_s


def cancel_inside_core(plugin: Plugin, widget_name: str, start: str, result_layer: str, monkeypatch) -> None:
    """Cancel stops the core stage itself (its progress callback raises) within 1 s of the
    click, before its last step, while it runs at its halfway report."""
    release = hold_halfway(plugin.widgets[widget_name]._job, monkeypatch)
    stopped_s = cancel_running(plugin, widget_name, start, "Cancel", release, result_layer)
    assert release.stop_s < 1.0, f"{widget_name}: the core computed on {release.stop_s:.2f} s after Cancel"
    assert stopped_s < 5.0, f"{widget_name}: the thread ended {stopped_s:.1f} s after Cancel"
    done, total = release.reports[-1]
    assert done < total, f"{widget_name}: the stage ran to its end"
    monkeypatch.undo()


def answer_file_dialog(file_edit, path) -> None:
    """The file picker's dialog returns ``path`` (None: the user closes it)."""
    file_edit._show_file_dialog = lambda *args, **kwargs: None if path is None else str(path)


# --------------------------------------------------------------------------- the plugin


def test_dslrxr_view_docks_every_widget_and_no_preview_appears(plugin, shots):
    """Opening the plugin and every sample computes nothing and adds no preview layer."""
    from npe2 import PluginManager

    manifest = PluginManager.instance().get_manifest("napari-dslrxr")
    keys = {sample.key for sample in manifest.contributions.sample_data}
    assert keys == set(SAMPLE_KEYS) | set(SINGLE_SAMPLE_KEYS)
    assert set(plugin.widgets) == set(plugin_widget_names()) and len(plugin.widgets) == 8
    plugin.qtbot.wait(300)  # longer than any preview debounce
    names = [layer.name for layer in plugin.viewer.layers]
    assert not [n for n in names if "preview" in n or "contrast" in n], names
    assert "DSLR radiograph" in names and "edge SOD 500 mm" in names and "simulated recording" in names
    plugin.check_notifications("opening the samples")
    plugin.widgets["Impulse removal"]._image.value = plugin.viewer.layers["DSLR radiograph"]  # the user picks it
    plugin.snap(shots, "all_widgets", "Impulse removal", ["DSLR radiograph"])
    for key in SINGLE_SAMPLE_KEYS:  # the single-frame sample commands work too (after the picture: no "[1]")
        plugin.viewer.open_sample("napari-dslrxr", key)
    plugin.qtbot.wait(300)
    assert not [n for n in (layer.name for layer in plugin.viewer.layers) if "preview" in n or "contrast" in n]
    plugin.check_notifications("opening the single samples")


def test_impulse_removal_buttons(plugin, monkeypatch, shots):
    name, widget = "Impulse removal", plugin.widgets["Impulse removal"]
    widget._image.value = plugin.viewer.layers["DSLR radiograph"]
    widget._passes["H"].value = 5
    plugin.click(name, "Restore defaults")
    assert widget.get_params().passes_h == 3
    cancel_inside_core(plugin, name, "Remove impulses", "DSLR radiograph cleaned", monkeypatch)
    plugin.click(name, "Remove impulses")
    assert "DSLR radiograph cleaned" in plugin.viewer.layers
    assert "px replaced" in widget._readout.value and "done in" in widget._job.status.value
    # the layers hold the core stage's result for the panel's parameters, and it replaced pixels
    from napari_dslrxr.core.stages.impulse import remove_impulses

    source = np.asarray(plugin.viewer.layers["DSLR radiograph"].data)
    expected = remove_impulses(source, widget.get_params(), space=widget._space.value)
    cleaned = np.asarray(plugin.viewer.layers["DSLR radiograph cleaned"].data)
    np.testing.assert_array_equal(cleaned, expected.image)
    assert np.count_nonzero(np.any(cleaned != source, axis=-1) if cleaned.ndim == 3 else cleaned != source) > 0
    for channel, mask in expected.masks.items():
        np.testing.assert_array_equal(plugin.viewer.layers[f"DSLR radiograph pulses {channel}"].data > 0, mask)
    # running again updates the result layers in place (removing one costs napari a full
    # garbage collection on the GUI thread, adding one builds its controls and visual anew)
    shown = list(plugin.viewer.layers)
    plugin.click(name, "Remove impulses")
    assert all(a is b for a, b in zip(plugin.viewer.layers, shown, strict=True))
    np.testing.assert_array_equal(plugin.viewer.layers["DSLR radiograph cleaned"].data, expected.image)
    plugin.check_all_clicked(name)
    plugin.snap(shots, "impulse", name, ["DSLR radiograph cleaned", "DSLR radiograph pulses H",
                                         "DSLR radiograph pulses S", "DSLR radiograph pulses V"],
                center=(200, 330), zoom=3.0)


def test_flat_field_buttons(plugin, monkeypatch, tmp_path):
    name, widget = "Flat field", plugin.widgets["Flat field"]
    layers = plugin.viewer.layers
    widget._image.value = layers["DSLR radiograph"]
    widget._flat.value = None
    plugin.click(name, "Apply flat field", refused="choose a flat")
    # Flat and dark from files, through their pickers.
    frames = samples._phantom()
    write_tiff(tmp_path / "flat.tif", frames.flat)
    write_tiff(tmp_path / "dark.tif", frames.dark)
    answer_file_dialog(widget._flat_file, "flat.tif")
    answer_file_dialog(widget._dark_file, "dark.tif")
    plugin.click(name, "Select file")
    plugin.click(name, "Select file #2")
    assert widget._flat.value is layers["flat: flat"] and widget._dark.value is layers["dark: dark"]
    widget._smoothing.value = 9.0
    plugin.click(name, "Restore defaults")
    assert widget.get_params().flat_smoothing_px == 4.0
    cancel_inside_core(plugin, name, "Apply flat field", "DSLR radiograph flat-fielded", monkeypatch)
    plugin.click(name, "Apply flat field")
    assert "DSLR radiograph flat-fielded" in layers
    plugin.check_all_clicked(name)


def rectangle(r0, c0, r1, c1):
    return np.array([[r0, c0], [r0, c1], [r1, c1], [r1, c0]], float)


def drag_rectangle(plugin: Plugin, shapes, r0: float, c0: float, r1: float, c1: float) -> None:
    """Draw a rectangle with the mouse on the canvas (the Shapes layer in its rectangle mode):
    press at data (r0, c0), move, release at (r1, c1); a new shape must result."""
    from qtpy.QtCore import QPoint, Qt
    from qtpy.QtTest import QTest

    canvas = plugin.viewer.window._qt_viewer.canvas
    transform = canvas.view.transform * canvas.view.scene.transform

    def point(r, c) -> QPoint:
        world = shapes.data_to_world((r, c))
        x, y = transform.map([world[-1], world[-2]])[:2]
        return QPoint(int(round(x)), int(round(y)))

    assert shapes.mode == "add_rectangle"
    before = len(shapes.data)
    native = canvas.native
    start, end = point(r0, c0), point(r1, c1)
    QTest.mousePress(native, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, start)
    for f in (0.25, 0.5, 0.75, 1.0):
        QTest.mouseMove(native, start + (end - start) * f)
        plugin.qtbot.wait(10)
    QTest.mouseRelease(native, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, end)
    plugin.qtbot.wait(20)
    assert len(shapes.data) == before + 1, "the drag drew no rectangle"


def test_psf_from_edges_buttons(plugin, tmp_path, shots):
    name, widget = "PSF from edges", plugin.widgets["PSF from edges"]
    viewer = plugin.viewer
    near, far = viewer.layers["edge SOD 500 mm"], viewer.layers["edge SOD 900 mm"]
    plugin.click(name, "Fit PSF", refused="draw at least one rectangle")
    widget._pitch.value = 0.2
    plugin.click(name, "Restore defaults")
    assert widget._pitch.value == 0.1
    # ROIs on the near image: drawn as rectangles in the shapes layer the button makes.
    widget._image.value = near
    plugin.click(name, "Draw ROIs on this image")
    shapes = viewer.layers["edge SOD 500 mm ROIs"]
    assert viewer.layers.selection.active is shapes and shapes.mode == "add_rectangle"
    viewer.window.resize(1300, 800)
    viewer_camera(viewer).center, viewer_camera(viewer).zoom = (0, 64, 64), 4.0  # the user zooms in
    plugin.qtbot.wait(50)
    drag_rectangle(plugin, shapes, 32, 32, 96, 96)
    # Too small an ROI is refused by its number and the fit's minimum, not dropped: under 8 px
    # and between 8 px and the minimum alike.
    for side in (5, 12):
        drag_rectangle(plugin, shapes, 40, 40, 40 + side, 40 + side)
        texts = plugin.click(name, "Fit PSF", refused="ROI 2 on 'edge SOD 500 mm' is ")
        assert f"draw it at least {MIN_ROI_PX}x{MIN_ROI_PX} px" in texts[-1] and f"{side}x{side} px" in texts[-1]
        shapes.data = shapes.data[:1]
    # An ROI without an edge says so.
    drag_rectangle(plugin, shapes, 100, 0, 128, 40)
    plugin.click(name, "Fit PSF", refused="ROI 2 on 'edge SOD 500 mm': no edge found")
    assert "no edge found" in widget._readout.value  # the read-out does not stay at "fitting..."
    shapes.data = shapes.data[:1]
    # One distance only: the read-out says the focal spot was not fitted.
    plugin.click(name, "Fit PSF")
    assert "focal spot: not fitted" in widget._readout.value and "0 x 0" not in widget._readout.value
    kernel_before = viewer.layers["PSF kernel"].data.copy()
    # ROIs on the far image; Cancel while the joint fit runs leaves the last result alone.
    widget._image.value = far
    plugin.click(name, "Draw ROIs on this image")
    viewer.layers["edge SOD 900 mm ROIs"].add_rectangles([rectangle(32, 32, 96, 96), rectangle(32, 160, 96, 224)])
    model_before = widget.model
    stopped_s = cancel_running(plugin, name, "Fit PSF", "Cancel fit", None, "no such layer")
    assert stopped_s < 5.0, f"the fit ran on {stopped_s:.1f} s after Cancel"
    assert widget.model is model_before
    np.testing.assert_array_equal(viewer.layers["PSF kernel"].data, kernel_before)
    plugin.click(name, "Fit PSF", timeout_ms=120_000)
    assert "focal spot FWHM x, y: 0.4" in widget._readout.value or "focal spot FWHM x, y: 0.3" in widget._readout.value
    assert widget.model.fit_report["n_images"] == 3
    # Save psf.json, enabled by the fit; the path chosen through the picker.
    answer_file_dialog(widget._path, "psf.json")
    plugin.click(name, "Select file")
    plugin.click(name, "Save psf.json")
    assert load_psf(tmp_path / "psf.json").source_fwhm_x_mm == pytest.approx(widget.model.source_fwhm_x_mm)
    plugin.check_all_clicked(name)
    plugin.snap(shots, "psf_edges", name, ["edge SOD 900 mm", "edge SOD 900 mm ROIs", "PSF kernel"])


def test_deconvolution_buttons(plugin, monkeypatch, tmp_path, shots):
    name, widget = "Deconvolution", plugin.widgets["Deconvolution"]
    viewer = plugin.viewer
    image = viewer.layers["edge SOD 900 mm"]
    widget._image.value = image
    widget._kernel_layer.value = None
    plugin.click(name, "Estimate regularisation", refused="choose a kernel layer or a psf.json")
    plugin.click(name, "Apply to the whole image", refused="choose a kernel layer or a psf.json")
    assert widget._readout.value.startswith("not done:")
    save_psf(PSFModel(**samples.EDGE_TRUTH), tmp_path / "psf.json")
    answer_file_dialog(widget._psf_file, "psf.json")
    plugin.click(name, "Select file")
    widget._sod.value, widget._sdd.value = 900.0, 1000.0
    widget._method.value = "wiener"
    plugin.click(name, "Restore defaults")
    assert widget._method.value == "adaptive" and widget._reg.value == pytest.approx(100.0, rel=0.02)
    plugin.click(name, "Estimate regularisation")
    assert widget._readout.value.startswith("estimated regularisation")
    assert widget._reg.value != pytest.approx(100.0, rel=0.02)
    plugin.toggle_live_preview(name, "edge SOD 900 mm deconvolved (preview)")
    release = gate(deconvolution_module, "deconvolve_steps", monkeypatch)
    cancel_running(plugin, name, "Apply to the whole image", "Cancel", release, "edge SOD 900 mm deconvolved")
    monkeypatch.undo()
    plugin.click(name, "Apply to the whole image")
    result = viewer.layers["edge SOD 900 mm deconvolved"]
    # Display range from the result's own values, and the read-out states them.
    lo, hi = np.percentile(result.data, [0.5, 99.5])
    assert result.contrast_limits == pytest.approx([lo, hi], rel=1e-3)
    assert "values" in widget._readout.value and "(input" in widget._readout.value
    plugin.check_all_clicked(name)
    result.translate = (0, 270)  # beside its input, for the picture
    plugin.snap(shots, "deconvolution", name, ["edge SOD 900 mm", "edge SOD 900 mm deconvolved"])


def test_contrast_buttons(plugin, monkeypatch):
    name, widget = "Contrast", plugin.widgets["Contrast"]
    viewer = plugin.viewer
    widget._image.value = viewer.layers["DSLR radiograph"]
    widget._sliders[("contrast", "bone_contrast")].value = 2.9
    plugin.click(name, "Restore defaults")
    assert widget.pipeline_params().contrast.bone_contrast == ContrastParams().bone_contrast
    release = gate(contrast_module, "render", monkeypatch)
    cancel_running(plugin, name, "Apply at full resolution", "Cancel", release, "DSLR radiograph contrast")
    monkeypatch.undo()
    plugin.click(name, "Apply at full resolution")
    assert viewer.layers["DSLR radiograph contrast"].data.shape == samples.PHANTOM_SHAPE
    # the layer holds the display stages' output for the panel's parameters at full resolution,
    # not the shape-matching scaled input or a default-parameter render
    from napari_dslrxr.core.display import apply_display_stages

    params = widget.pipeline_params()
    prepared = contrast_module.prepare_input(np.asarray(viewer.layers["DSLR radiograph"].data), widget._kind.value,
                                             widget.preview_max_pixels, params)
    expected = apply_display_stages(prepared.image, prepared.mask, params)
    np.testing.assert_allclose(viewer.layers["DSLR radiograph contrast"].data, expected, atol=1e-6)
    assert np.std(expected) > 0.05  # a picture, not a constant
    plugin.toggle_live_preview(name, "DSLR radiograph contrast (preview)")
    plugin.check_all_clicked(name)


def test_diagnosis_buttons(plugin, tmp_path, monkeypatch, shots):
    name, widget = "Diagnosis", plugin.widgets["Diagnosis"]
    viewer = plugin.viewer
    offered = [layer.name for layer in widget._recording.choices]
    assert "simulated recording" in offered and "DSLR radiograph" not in offered and "flat" not in offered
    widget._recording.value = viewer.layers["simulated recording"]
    assert not plugin.buttons(name)["Write report"].isEnabled()
    answer_file_dialog(widget._scene_file, None)  # the user closes the dialog: the layer's scene is used
    plugin.click(name, "Select file")
    widget._max_terms.value = 7
    plugin.click(name, "Restore defaults")
    assert widget._max_terms.value == 4
    widget._max_terms.value = 1
    stopped_s = cancel_running(plugin, name, "Diagnose", "Cancel", None, "residual z (final model)")
    assert stopped_s < 5.0, f"the diagnosis ran on {stopped_s:.1f} s after Cancel"
    RESULT_ADDS.pop((name, "Diagnose"), None)
    plugin.click(name, "Diagnose", timeout_ms=120_000)
    assert "veiling_glare" in widget._readout.value
    # the first result's six layers, each in its own turn (Plugin.check_result_adds)
    added = RESULT_ADDS[(name, "Diagnose")]
    assert {n for n, _, _ in added} == {"residual z (base model)", "residual z (final model)",
                                        "residual z 4x4 (base model)", "residual z 4x4 (final model)",
                                        "residual map labels", "mismatch regions"}, added
    assert len({turn for _, turn, _ in added}) == len(added) == 6
    before, after = viewer.layers["residual z 4x4 (base model)"], viewer.layers["residual z 4x4 (final model)"]
    assert before.visible and after.visible and after.translate[1] > before.translate[1]
    answer_file_dialog(widget._report_dir, "report")
    plugin.click(name, "Choose directory")
    plugin.click(name, "Write report")
    html = unescape((tmp_path / "report" / "report.html").read_text(encoding="utf-8"))
    assert "recording layer 'simulated recording'" in html and "Created: " in html and "max-width:100%" in html
    opened = []
    monkeypatch.setattr(webbrowser, "open", lambda url: opened.append(url) or True)
    plugin.click(name, "Open report")
    assert opened == [(tmp_path / "report" / "report.html").resolve().as_uri()]
    plugin.check_all_clicked(name)
    plugin.snap(shots, "diagnosis", name, ["residual z 4x4 (base model)", "residual z 4x4 (final model)",
                                           "mismatch regions", "residual map labels"])


def test_detector_quality_buttons(plugin, tmp_path, monkeypatch, shots):
    name, widget = "Detector quality", plugin.widgets["Detector quality"]
    viewer = plugin.viewer
    offered = widget._flats.choices
    for choice in (widget._flats, widget._darks):  # several entries visible (not two and a scroll bar)
        rows_shown = choice.native.viewport().height() / choice.native.sizeHintForRow(0)
        assert rows_shown >= qc_module.LIST_ROWS - 0.5, rows_shown
    assert "QC flat 1" in offered and "DSLR radiograph" not in offered  # colour layers are not a detector channel
    plugin.click(name, "Measure MTF, NNPS, DQE", refused="choose at least one flat layer")
    widget._flats.value = ["QC flat 1", "QC flat 2"]
    widget._darks.value = ["QC dark"]
    widget._edge.value = viewer.layers["QC edge"]
    assert widget._pitch.value == 0.1 and widget._kerma.value == 2.5  # from the sample's metadata
    widget._beam.value, widget._roi_size.value = "RQA9", 128
    widget._kerma.value, widget._pitch.value = 7.0, 0.25
    plugin.click(name, "Restore defaults")
    # the [qc] defaults, then the edge layer's own pitch and air kerma from its metadata
    assert widget._beam.value == QcParams().beam and widget._roi_size.value == QcParams().roi_size_px
    assert widget._kerma.value == 2.5 and widget._pitch.value == 0.1
    # The edge inside a rectangle of its ROI layer, drawn on the layer the button makes.
    plugin.click(name, "Draw edge ROI")
    shapes = viewer.layers["QC edge ROIs"]
    assert viewer.layers.selection.active is shapes and shapes.mode == "add_rectangle"
    shapes.add_rectangles([rectangle(96, 160, 416, 352)])
    real = qc_module.measure_detector_quality
    release = gate(qc_module, "measure_detector_quality", monkeypatch)
    cancel_running(plugin, name, "Measure MTF, NNPS, DQE", "Cancel", release, "no such layer")
    assert widget.result is None
    monkeypatch.setattr(qc_module, "measure_detector_quality", real)  # (undo() would also leave tmp_path)
    plugin.click(name, "Measure MTF, NNPS, DQE", timeout_ms=120_000)
    result = widget.result
    assert result.edges[0].direction == "horizontal" and result.edges[0].angle_deg == pytest.approx(2.5, abs=0.2)
    assert result.edge_rois == [[96, 160, 416, 352]]
    # The sample's truth: Gaussian light spread (sigma 0.7 px) after detection, 0.1 mm pixels
    truth = samples.QC_TRUTH
    i = int(np.abs(result.frequency_cy_per_mm - 2.5).argmin())
    f_px = result.frequency_cy_per_mm[i] * truth["pixel_pitch_mm"]
    mtf_truth = np.exp(-2 * (np.pi * truth["light_spread_sigma_px"] * f_px) ** 2) * np.sinc(f_px)
    assert result.mtf[i] == pytest.approx(mtf_truth, abs=0.03)
    # DQE of Poisson detection followed by a deterministic spread: eta sinc^2 (read noise: 1-7 % less)
    eta = truth["quanta_per_ugy"] / (29653.0 * truth["pixel_pitch_mm"] ** 2)
    assert result.dqe[i] == pytest.approx(eta * np.sinc(f_px) ** 2, rel=0.15)
    assert "from flat layer 'QC flat 1'; flat layer 'QC flat 2'; dark layer 'QC dark'" in widget._readout.value
    assert "2.5 c/mm: MTF" in widget._readout.value and "DQE" in widget._readout.value
    left, right = widget._figure.axes
    assert {"MTF horizontal", "DQE horizontal"} <= {line.get_label() for line in left.lines}
    assert "horizontal" in {line.get_label() for line in right.lines}  # the NNPS
    answer_file_dialog(widget._report_dir, "qc_report")
    plugin.click(name, "Choose directory")
    plugin.click(name, "Write report")
    written = {p.name for p in (tmp_path / "qc_report").iterdir()}
    assert {"qc.json", "qc.csv", "qc.html"} <= written
    assert "flat layer 'QC flat 1'" in unescape((tmp_path / "qc_report" / "qc.html").read_text(encoding="utf-8"))
    opened = []
    monkeypatch.setattr(webbrowser, "open", lambda url: opened.append(url) or True)
    plugin.click(name, "Open report")
    assert opened == [(tmp_path / "qc_report" / "qc.html").resolve().as_uri()]
    plugin.check_all_clicked(name)
    plugin.snap(shots, "qc", name, ["QC edge", "QC edge ROIs"])


def test_parameter_file_buttons(plugin, tmp_path):
    name, widget = "Parameter file", plugin.widgets["Parameter file"]
    contrast = plugin.widgets["Contrast"]
    path = tmp_path / "params.toml"
    answer_file_dialog(widget._path, "params.toml")
    plugin.click(name, "Select file")
    plugin.click(name, "Load", refused="params.toml")
    contrast._sliders[("contrast", "bone_contrast")].value = 2.5
    plugin.click(name, "Save")
    assert "bone_contrast = 2.5" in path.read_text(encoding="utf-8")
    plugin.click(name, "Restore defaults")
    assert contrast.pipeline_params().contrast.bone_contrast == ContrastParams().bone_contrast
    plugin.click(name, "Load")
    assert contrast.pipeline_params().contrast.bone_contrast == 2.5
    plugin.check_all_clicked(name)


def test_paper_pipeline_by_mouse_alone(plugin, shots):
    """impulse -> flat -> PSF from edges -> deconvolution -> contrast, each step on the previous
    step's layer, by clicks only (layer choices are the combo boxes a user sets)."""
    viewer, w = plugin.viewer, plugin.widgets
    w["Impulse removal"]._image.value = viewer.layers["DSLR radiograph"]
    plugin.click("Impulse removal", "Remove impulses")
    flat = w["Flat field"]
    flat._image.value = viewer.layers["DSLR radiograph cleaned"]
    flat._flat.value, flat._dark.value = viewer.layers["flat"], viewer.layers["dark"]
    plugin.click("Flat field", "Apply flat field")
    flat_fielded = viewer.layers["DSLR radiograph cleaned flat-fielded"]
    psf = w["PSF from edges"]
    for name, roi in (("edge SOD 500 mm", rectangle(32, 32, 96, 96)), ("edge SOD 900 mm", rectangle(32, 160, 96, 224))):
        psf._image.value = viewer.layers[name]
        plugin.click("PSF from edges", "Draw ROIs on this image")
        viewer.layers[f"{name} ROIs"].add_rectangles([roi])
    plugin.click("PSF from edges", "Fit PSF", timeout_ms=120_000)
    assert "focal spot FWHM" in psf._readout.value
    deconvolution = w["Deconvolution"]
    deconvolution._image.value = flat_fielded
    deconvolution._kernel_layer.value = viewer.layers["PSF kernel"]
    plugin.click("Deconvolution", "Estimate regularisation")
    plugin.click("Deconvolution", "Apply to the whole image")
    deblurred = viewer.layers["DSLR radiograph cleaned flat-fielded deconvolved"]
    assert deblurred.data.shape == flat_fielded.data.shape
    contrast = w["Contrast"]
    contrast._image.value = deblurred
    plugin.click("Contrast", "Apply at full resolution")
    final = viewer.layers["DSLR radiograph cleaned flat-fielded deconvolved contrast"]
    assert final.data.shape == samples.PHANTOM_SHAPE and 0.0 <= final.data.min() < final.data.max() <= 1.0
    plugin.snap(shots, "flatfield", "Flat field", ["DSLR radiograph cleaned flat-fielded"])
    plugin.snap(shots, "contrast", "Contrast", ["DSLR radiograph cleaned flat-fielded deconvolved contrast"])

