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
    if isinstance(worker, GeneratorWorker):
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
        pbar.close()
        worker.dslrxr_finished = True  # set on the GUI thread after the result was shown
        if on_finished is not None:
            with reported_errors(desc):
                on_finished()

    worker.returned.connect(_returned)
    worker.errored.connect(lambda exc: notify_error(exc, context=desc))
    worker.finished.connect(_finished)
    worker.start()
    return worker


# --------------------------------------------------------------------------- layers


def layer_array(layer: napari.layers.Layer, *, dtype: type | None = np.float32) -> np.ndarray:
    """The layer's data as an in-memory array (cast to ``dtype`` unless None)."""
    data = np.asarray(layer.data)
    return data if dtype is None else data.astype(dtype, copy=False)


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
            for key in ("scale", "translate", "metadata", "colormap", "opacity", "visible"):
                if key in kwargs:
                    setattr(layer, key, kwargs[key])
            if layer_type == "image" and "contrast_limits" in kwargs:
                layer.contrast_limits = kwargs["contrast_limits"]
            elif layer_type == "image":
                layer.reset_contrast_limits()
            return layer
        viewer.layers.remove(layer)
    add = getattr(viewer, f"add_{layer_type}")
    return add(data, name=name, **kwargs)


def same_geometry(reference: napari.layers.Layer) -> dict:
    """Keyword arguments that place a derived layer over ``reference`` in world coordinates."""
    return {"scale": tuple(reference.scale[-2:]), "translate": tuple(reference.translate[-2:])}


def visible_region(layer: napari.layers.Layer, shape: tuple[int, ...] | None = None,
                   *, margin_px: int = 0) -> tuple[slice, slice]:
    """Row and column slices of ``layer``'s data currently visible on the canvas.

    Uses ``layer.corner_pixels`` (data coordinates of the drawn region, updated by napari
    on every camera change), grown by ``margin_px`` and clipped to the image.
    """
    shape = tuple(shape or np.shape(layer.data))[:2]
    corners = np.asarray(layer.corner_pixels)
    r0, c0 = (int(v) for v in corners[0][-2:]) if corners.size else (0, 0)
    r1, c1 = (int(v) + 1 for v in corners[1][-2:]) if corners.size else shape
    if r1 - r0 < 2 or c1 - c0 < 2:  # not drawn yet: use the whole image
        r0, c0, (r1, c1) = 0, 0, shape
    r0, c0 = max(0, r0 - margin_px), max(0, c0 - margin_px)
    r1, c1 = min(shape[0], r1 + margin_px), min(shape[1], c1 + margin_px)
    return slice(r0, r1), slice(c0, c1)
