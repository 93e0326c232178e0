"""Layer helpers of the widgets: results shown as layers (updated in place), the visible part
of an image, and the live preview's mechanics (one worker at a time, debounced triggers)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Generator, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import napari


def remove_layer(viewer: napari.Viewer, name: str) -> bool:
    """Remove the layer called ``name`` if there is one; return whether it was there."""
    if name in viewer.layers:
        viewer.layers.remove(name)
        return True
    return False


class LivePreviewMixin:
    """Live preview of a stage widget: one preview worker at a time, the newest settings
    computed once it is done, and the preview layer removed when the preview is turned off or
    another image is chosen.

    The widget provides ``_viewer``, ``_image`` (layer combo), ``_live`` (check box) and
    ``_start_preview()`` (starts the worker with ``on_finished=self._preview_done`` and sets
    ``_preview_layer`` when it shows the result), and calls :meth:`_init_live_preview`.
    """

    def _init_live_preview(self) -> None:
        self._preview_worker = None
        self._preview_pending = False
        self._preview_layer: str | None = None
        self._live.changed.connect(self._live_toggled)
        self._image.changed.connect(self._drop_preview)

    def _live_toggled(self, on: bool) -> None:
        if not on:
            self._drop_preview()

    def _drop_preview(self, *_args) -> None:
        """Remove the preview layer (preview turned off, or another image chosen)."""
        if self._preview_layer is not None:
            remove_layer(self._viewer, self._preview_layer)
            self._preview_layer = None

    def update_preview(self) -> None:
        """Recompute the preview (no-op unless live preview is on and an image is chosen)."""
        if not self._live.value or self._image.value is None:
            return
        if self._preview_worker is not None and not self._preview_worker.dslrxr_finished:
            self._preview_pending = True  # compute the newest settings when this one is done
            return
        self._start_preview()

    def _preview_done(self) -> None:
        if self._preview_pending:
            self._preview_pending = False
            self.update_preview()


# --------------------------------------------------------------------------- layers


def single_channel_layers(viewer: napari.Viewer) -> list[tuple[str, Any]]:
    """``(name, layer)`` of the image layers holding one 2-D channel (a detector's linear
    pixels; colour layers are left out), for a layer choice."""
    from napari.layers import Image

    return [(layer.name, layer) for layer in viewer.layers
            if isinstance(layer, Image) and not layer.rgb and np.ndim(layer.data) == 2]


def reset_choices(*widgets: Any) -> None:
    """Refresh the layer choices of ``widgets`` (a layer was added or removed)."""
    try:
        for widget in widgets:
            widget.reset_choices()
    except RuntimeError:  # widget already deleted while napari tears down
        pass


def show_layer(viewer: napari.Viewer, data: np.ndarray, name: str, layer_type: str = "image",
               **kwargs: Any) -> napari.layers.Layer:
    """Update the layer called ``name`` in place (same type and ndim), or add it.

    Re-running a stage therefore replaces its result layer instead of piling up copies, and
    keeps the GUI responsive: napari removes a layer with a full garbage collection (hundreds
    of milliseconds with a few images open) and builds a new one's controls and visual.
    """
    import napari.layers

    if name in viewer.layers:
        layer = viewer.layers[name]
        # isinstance, not the class name: a plugin's viewer hands out proxies of its layers.
        layer_class = getattr(napari.layers, layer_type.capitalize())
        if isinstance(layer, layer_class) and np.ndim(layer.data) == np.ndim(data) and (
            getattr(layer, "rgb", False) == bool(kwargs.get("rgb", False))
        ):
            layer.data = data
            # Set only what changed: every setter makes napari refresh the layer (costly
            # when a live preview updates it several times a second).
            for key in ("scale", "translate"):
                if key in kwargs and not np.allclose(getattr(layer, key)[-2:], kwargs[key]):
                    setattr(layer, key, kwargs[key])
            wanted = kwargs.get("colormap")  # a name or a napari Colormap
            if wanted is not None and getattr(layer.colormap, "name", None) != getattr(wanted, "name", wanted):
                layer.colormap = wanted
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
    layer = add(data, name=name, **kwargs)
    if layer_type == "image" and layer.rgb and np.ndim(data) == 3 and np.asarray(data).dtype != np.uint8:
        rgb_thumbnail_from_contrast_limits(layer)
    return layer


def rgb_thumbnail_from_contrast_limits(layer: napari.layers.Image) -> None:
    """Give a colour layer of counts (uint16, float) a thumbnail scaled by its contrast limits.

    napari makes a colour layer's thumbnail from the raw values as if they were 0-1 (or
    0-255), so a layer of camera counts shows an all-white thumbnail in the layer list
    although the canvas, which applies the contrast limits, is right. Whenever napari sets
    the thumbnail (public ``events.thumbnail``), it is replaced by a subsample of the data
    scaled by the contrast limits (32 x 32 pixels: negligible work).
    """
    replacing = [False]

    def replace(_event: Any = None) -> None:
        if replacing[0]:
            return  # our own assignment's event
        data = np.asarray(layer.data)
        step = max(1, int(np.ceil(max(data.shape[:2]) / 32)))
        low, high = (float(v) for v in layer.contrast_limits)
        sample = (data[::step, ::step, :3].astype(np.float32) - low) / max(high - low, 1e-12)
        alpha = np.full(sample.shape[:2] + (1,), float(layer.opacity), np.float32)
        replacing[0] = True
        try:
            layer.thumbnail = np.concatenate([np.clip(sample, 0.0, 1.0) ** float(layer.gamma), alpha], axis=2)
        finally:
            replacing[0] = False

    layer.events.thumbnail.connect(replace)
    replace()


#: Yielded by a display step (see ``run_in_worker``) when the next step adds a layer.
NEXT_STEP_ADDS_LAYER = "next step adds a layer"

#: What :meth:`ShownLayers.updating` keeps of a layer updated in place (``show_layer`` sets
#: these), in the order they are put back.
_KEPT = ("data", "scale", "translate", "colormap", "opacity", "visible", "metadata", "contrast_limits_range",
         "contrast_limits", "gamma")


class ShownLayers:
    """What a result's display (shown over several event-loop turns) changed so far, to put
    back when it stops midway: cancelled (``run_in_worker`` closes the display's generator)
    or a step raised. The layers it added are removed, the ones it updated in place get their
    previous state back, so no half-made set of result layers is left::

        shown = ShownLayers(viewer)
        with shown.put_back_if_stopped():
            yield from show_layer_steps(viewer, data, name, shown=shown)
            ...
    """

    def __init__(self, viewer: napari.Viewer):
        self._viewer = viewer
        self._undo: list[Callable[[], None]] = []

    def added(self, layer: napari.layers.Layer) -> None:
        self._undo.append(lambda: self._viewer.layers.remove(layer) if layer in self._viewer.layers else None)

    def updating(self, layer: napari.layers.Layer, attributes: tuple[str, ...] = _KEPT) -> None:
        """Keep ``layer``'s ``attributes`` (before it is updated in place)."""
        kept = {key: getattr(layer, key) for key in attributes if hasattr(layer, key)}
        kept = {key: (value.copy() if isinstance(value, dict) else value) for key, value in kept.items()}

        def restore() -> None:
            for key, value in kept.items():
                now = getattr(layer, key)
                same = now is value or (key != "data" and _equal(now, value))
                if not same:
                    setattr(layer, key, value)

        self._undo.append(restore)

    def undo_with(self, restore: Callable[[], None]) -> None:
        """Put back with ``restore()`` (a layer updated otherwise)."""
        self._undo.append(restore)

    @contextlib.contextmanager
    def put_back_if_stopped(self) -> Iterator[ShownLayers]:
        """Around a display's steps: when they stop midway (the generator closed by Cancel:
        ``GeneratorExit`` at a ``yield``; or a step raised), :meth:`put_back`, then re-raise."""
        try:
            yield self
        except BaseException:
            self.put_back()
            raise

    def put_back(self) -> None:
        """Undo everything recorded, the latest first (each undo's failure is reported)."""
        from ._jobs import reported_errors

        while self._undo:
            with reported_errors("putting back the layers"):
                self._undo.pop()()


def _equal(a: Any, b: Any) -> bool:
    if hasattr(a, "name") and hasattr(b, "name"):  # colormaps
        return a.name == b.name
    if isinstance(a, dict) or isinstance(b, dict):
        return a == b
    try:
        return bool(np.array_equal(a, b))
    except (TypeError, ValueError):
        return False


def show_layer_steps(viewer: napari.Viewer, data: np.ndarray, name: str, layer_type: str = "image",
                     shown: ShownLayers | None = None,
                     **kwargs: Any) -> Generator[str | None, None, napari.layers.Layer]:
    """:func:`show_layer` over event-loop turns when the layer is new: announced
    (:data:`NEXT_STEP_ADDS_LAYER`), added hidden, shown at the next turn (``yield`` between
    them; for a generator ``on_returned`` of :func:`run_in_worker`). napari builds a new
    layer's controls and visual when it is added and compiles its shaders when it first
    draws it; one after the other they froze the viewer longer than either alone.
    ``layer = yield from show_layer_steps(...)``. ``shown``: the display's record of what it
    changed (:class:`ShownLayers`); without one, a new layer is removed again when the display
    stops between its add and its reveal."""
    if name not in viewer.layers:
        yield NEXT_STEP_ADDS_LAYER
    new = name not in viewer.layers
    reveal = new and kwargs.get("visible", True)
    if shown is not None and not new:
        shown.updating(viewer.layers[name])
    if reveal:
        kwargs["visible"] = False
    layer = show_layer(viewer, data, name, layer_type, **kwargs)
    if shown is not None and new:
        shown.added(layer)
    if reveal:
        try:
            yield
        except BaseException:
            if shown is None and new and layer in viewer.layers:
                viewer.layers.remove(layer)  # no hidden, half-made layer left
            raise
        layer.visible = True
    return layer


#: New characters a text layer draws per event-loop turn when it is first shown (napari
#: renders each new glyph of the canvas font once, about 6 ms each on the GUI thread).
GLYPHS_PER_STEP = 4


def reveal_text_steps(layer: napari.layers.Layer, feature: str, texts: list[str],
                      glyphs_per_step: int = GLYPHS_PER_STEP) -> Iterator[None]:
    """Show a hidden layer whose text labels are ``layer.features[feature]`` (``texts``),
    its new glyphs rendered a few per event-loop turn.

    The canvas renders a glyph the first time it draws it; a label layer's first draw
    rendered all of them in one turn (20-odd glyphs: 0.1-0.2 s), on top of the layer's
    first draw (its shaders). The layer is drawn transparent (opacity 0), first without
    text, then with its labels growing a few new characters per turn, then shown at its own
    opacity with the whole labels.
    """
    opacity = layer.opacity
    prefixes: list[list[str]] = [[""] * len(texts)]  # the layer's first draw (its shaders) without text
    seen: set[str] = set()
    batch: set[str] = set()
    cut = [0] * len(texts)
    for i, text in enumerate(texts):
        for j, char in enumerate(text):
            if char not in seen and char not in batch:
                if len(batch) == glyphs_per_step:
                    prefixes.append([t[:c] for t, c in zip(texts, cut)])
                    seen |= batch
                    batch = set()
                batch.add(char)
            cut[i] = j + 1
    layer.opacity = 0.0
    layer.visible = True
    for partial in prefixes:
        layer.features = {feature: partial}
        yield
    layer.features = {feature: list(texts)}
    layer.opacity = opacity


def finish_steps(steps: Iterator[None]) -> Any:
    """Run a generator of display steps to its end at once; return its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


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
