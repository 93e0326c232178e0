"""Helpers shared by the widgets: thread workers with progress and cancel, notifications, layers.

The widgets are thin: they read layers and widget values, call the headless core, and show
the results. Everything here runs on the GUI thread except the work handed to
:func:`run_in_worker`, which never touches a widget or a layer.
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.errors import DslrxrError

if TYPE_CHECKING:
    import napari

_LOG = logging.getLogger(__name__)


class WorkCancelled(DslrxrError):
    """Raised inside a worker (e.g. from a core progress callback) when the user cancels."""


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
    """Decorator form of :func:`reported_errors` for widget callbacks."""

    def decorate(fn: Callable) -> Callable:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            with reported_errors(context):
                return fn(*args, **kwargs)
            return None

        wrapper.__name__ = fn.__name__
        wrapper.__doc__ = fn.__doc__
        return wrapper

    return decorate


# --------------------------------------------------------------------------- workers


def run_in_worker(work: Callable, *args: Any, desc: str,
                  on_returned: Callable[[Any], None],
                  on_finished: Callable[[], None] | None = None,
                  progress_bar: bool = True,
                  **kwargs: Any):
    """Run ``work(*args, **kwargs)`` in a napari thread worker with a progress bar.

    Parameters
    ----------
    work : callable
        Either a generator function that yields ``(done, total)`` and returns its result
        (the bar shows the fraction and has a cancel button that stops the worker at the
        next yield), or a plain function (indeterminate bar).
    desc : str
        Progress bar label.
    on_returned : callable
        Called on the GUI thread with the result; exceptions in it become notifications.
    on_finished : callable, optional
        Called on the GUI thread after success, error or cancel (e.g. to re-enable a button).
    progress_bar : bool
        Show a bar in napari's activity dock (off for sub-second live previews).

    Returns
    -------
    napari.qt.threading.WorkerBase
        The started worker; ``worker.quit()`` cancels. Its attribute ``dslrxr_finished``
        becomes True on the GUI thread once ``on_returned``/``on_finished`` have run (tests
        wait for it with ``qtbot.waitUntil``).
    """
    from napari.qt.threading import GeneratorWorker, create_worker
    from napari.utils import cancelable_progress, progress

    worker = create_worker(work, *args, _start_thread=False, _ignore_errors=True, **kwargs)
    worker.dslrxr_finished = False
    if not progress_bar:
        pbar = None
    elif isinstance(worker, GeneratorWorker):
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
    else:
        pbar = progress(total=0, desc=desc)

    def _returned(result: Any) -> None:
        with reported_errors(desc):
            on_returned(result)

    def _finished() -> None:
        if pbar is not None:
            pbar.close()
        worker.dslrxr_finished = True  # set on the GUI thread after the result was shown
        if on_finished is not None:
            with reported_errors(desc):
                on_finished()

    def _errored(exc: BaseException) -> None:
        if isinstance(exc, WorkCancelled):
            notify_info(f"{desc}: cancelled")
        else:
            notify_error(exc, context=desc)

    worker.returned.connect(_returned)
    worker.errored.connect(_errored)
    worker.finished.connect(_finished)
    worker.start()
    return worker


# --------------------------------------------------------------------------- layers


def show_layer(viewer: napari.Viewer, data: np.ndarray, name: str, layer_type: str = "image",
               **kwargs: Any) -> napari.layers.Layer:
    """Update the layer called ``name`` in place (same type and ndim), or add it.

    Re-running a stage therefore replaces its result layer instead of piling up copies.
    """
    if name in viewer.layers:
        layer = viewer.layers[name]
        if layer._type_string == layer_type and np.ndim(layer.data) == np.ndim(data) and (
            getattr(layer, "rgb", False) == bool(kwargs.get("rgb", False))
        ):
            layer.data = data
            # Set only what changed: every setter makes napari refresh the layer (costly
            # when a live preview updates it several times a second).
            for key in ("scale", "translate"):
                if key in kwargs and not np.allclose(getattr(layer, key)[-2:], kwargs[key]):
                    setattr(layer, key, kwargs[key])
            if "colormap" in kwargs and getattr(layer.colormap, "name", None) != kwargs["colormap"]:
                layer.colormap = kwargs["colormap"]
            for key in ("opacity", "visible"):
                if key in kwargs and getattr(layer, key) != kwargs[key]:
                    setattr(layer, key, kwargs[key])
            if "metadata" in kwargs:
                layer.metadata = kwargs["metadata"]
            if layer_type == "image":
                limits = tuple(kwargs.get("contrast_limits") or robust_limits(data))
                if tuple(layer.contrast_limits_range) != limits:
                    layer.contrast_limits_range = limits
                if tuple(layer.contrast_limits) != limits:
                    layer.contrast_limits = limits
            return layer
        viewer.layers.remove(layer)
    if layer_type == "image" and "contrast_limits" not in kwargs:
        kwargs["contrast_limits"] = robust_limits(data)
    add = getattr(viewer, f"add_{layer_type}")
    return add(data, name=name, **kwargs)


def robust_limits(data: np.ndarray, percentiles: tuple[float, float] = (0.5, 99.5)) -> tuple[float, float]:
    """Display range of an image ignoring outliers (pulses, unexposed pixels): percentiles of
    a subsample of at most ~1e6 values."""
    flat = np.asarray(data).reshape(-1)
    step = max(1, flat.size // 1_000_000)
    sample = flat[::step]
    sample = sample[np.isfinite(sample)] if sample.dtype.kind == "f" else sample
    if sample.size == 0:
        return (0.0, 1.0)
    lo, hi = (float(v) for v in np.percentile(sample, percentiles))
    return (lo, hi) if hi > lo else (lo, lo + 1.0)


def readout_label() -> Any:
    """A magicgui Label for a widget's results: selectable, word-wrapped (keeps the dock narrow)."""
    from magicgui.widgets import Label
    from qtpy.QtCore import Qt

    label = Label(value="")
    label.native.setWordWrap(True)
    label.native.setMinimumWidth(300)
    label.native.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
    return label


def same_geometry(reference: napari.layers.Layer) -> dict:
    """Keyword arguments that place a derived layer over ``reference`` in world coordinates."""
    return {"scale": tuple(reference.scale[-2:]), "translate": tuple(reference.translate[-2:])}


def viewer_camera(viewer: napari.Viewer):
    """The viewer's camera model (``viewer.scene.camera`` since napari 0.9, else ``viewer.camera``)."""
    scene = getattr(viewer, "scene", None)
    camera = getattr(scene, "camera", None)
    return camera if camera is not None else viewer.camera


def visible_region(viewer: napari.Viewer, layer: napari.layers.Layer,
                   shape: tuple[int, ...] | None = None, *, margin_px: int = 0) -> tuple[slice, slice]:
    """Row and column slices of ``layer``'s data visible on the canvas (2-D view).

    Computed from the camera (centre, zoom) and the canvas size, so it is current as soon as
    the camera changes (``layer.corner_pixels`` only follows at the next redraw). Assumes the
    layer is placed by scale and translate only (no rotation or shear). Grown by
    ``margin_px`` and clipped to the image.
    """
    shape = tuple(shape or np.shape(layer.data))[:2]
    height_px, width_px = viewer.canvas.size
    camera = viewer_camera(viewer)
    zoom = float(camera.zoom)
    centre = np.asarray(camera.center[-2:], float)
    half = np.array([height_px, width_px], float) / (2.0 * zoom)
    scale = np.asarray(layer.scale[-2:], float)
    translate = np.asarray(layer.translate[-2:], float)
    low = (centre - half - translate) / scale
    high = (centre + half - translate) / scale
    r0 = int(np.clip(np.floor(low[0] + 0.5) - margin_px, 0, shape[0] - 1))
    c0 = int(np.clip(np.floor(low[1] + 0.5) - margin_px, 0, shape[1] - 1))
    r1 = int(np.clip(np.ceil(high[0] + 0.5) + margin_px, r0 + 1, shape[0]))
    c1 = int(np.clip(np.ceil(high[1] + 0.5) + margin_px, c0 + 1, shape[1]))
    return slice(r0, r1), slice(c0, c1)


# --------------------------------------------------------------------------- live preview


def debounced(owner: Any, fn: Callable[[], None], timeout_ms: int) -> Callable[..., None]:
    """A trigger that calls ``fn()`` once, ``timeout_ms`` after the last of a burst of calls.

    The timer belongs to ``owner.native`` (a magicgui widget), so it dies with the widget; a
    trigger arriving while napari tears the widget down (layer lists emptied) is ignored.
    """
    from superqt.utils import qdebounced

    def call() -> None:
        try:
            fn()
        except RuntimeError as exc:  # the Qt side of the widget is already deleted
            if "deleted" not in str(exc):
                raise

    throttled = qdebounced(call, timeout_ms, parent=owner.native)

    def trigger(*_args: Any) -> None:
        try:
            throttled()
        except RuntimeError as exc:
            if "deleted" not in str(exc):
                raise

    trigger.cancel = throttled.cancel  # type: ignore[attr-defined]
    trigger.flush = throttled.flush  # type: ignore[attr-defined]
    return trigger
