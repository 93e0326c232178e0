"""Impulse-noise (zinger) removal widget over :func:`napari_dslrxr.core.stages.impulse.remove_impulses`.

The user picks an image layer, the colour space, the passes per channel (H, S, V for
colour, grey for grey images) and the polarity of the spots (bright, dark or both). The
cleaned image appears as ``"<layer> cleaned"`` and the detected pulses of each channel as
a mask layer ``"<layer> pulses <channel>"`` (1 = pulse), drawn in the channel's own colour and
transparent elsewhere, so noise patches of H, S and V can be compared by colour. They are
image layers, not Labels layers: napari sets a Labels layer up with its painting tools
(several times the GUI-thread time of an image layer), and a mask is only looked at. Pulse
counts, the estimated pulse rate and the estimated Poisson gain are shown under the button.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, PushButton, create_widget

from ..core.errors import ParameterError
from ..core.stages.impulse import ImpulseParams, ImpulseResult, remove_impulses
from ._controls import param_widget, restore_defaults_button
from ._jobs import JobPanel, guarded, job_done, readout_label, run_in_worker, scroll_long_readout
from ._layers import ShownLayers, robust_limits, same_geometry, show_layer_steps
from ._registry import register_stage_widget

if TYPE_CHECKING:
    import napari

#: Colour (RGB) of each channel's pulse mask: distinct, bright on a grey radiograph.
CHANNEL_COLOUR = {"grey": (1.0, 0.0, 1.0), "H": (1.0, 0.0, 1.0), "S": (1.0, 1.0, 0.0), "V": (0.0, 1.0, 1.0),
                  "R": (1.0, 0.2, 0.2), "G1": (0.2, 1.0, 0.2), "G2": (0.6, 1.0, 0.2), "B": (0.3, 0.5, 1.0)}


def pulse_colormap(channel: str):
    """napari colormap of a channel's 0/1 pulse mask: transparent at 0, its colour at 1."""
    from napari.utils.colormaps import Colormap

    colour = CHANNEL_COLOUR.get(channel, (1.0, 0.0, 1.0))
    return Colormap([[0.0, 0.0, 0.0, 0.0], [*colour, 1.0]], name=f"pulses {channel}")


def pulse_summary(result: ImpulseResult) -> str:
    """One line per channel: pulse count, pulse rate and gain (for the widget's read-out)."""
    lines = []
    for name, mask in result.masks.items():
        gain = result.gain.get(name, float("nan"))
        rate = result.pulse_rate.get(name, float("nan"))
        gain_text = "n/a (ratio channel)" if not np.isfinite(gain) else f"{gain:.4g} counts/quantum"
        rate_text = "n/a" if not np.isfinite(rate) else f"{rate:.2e}"
        lines.append(f"{name}: {int(np.count_nonzero(mask))} px replaced, pulse rate {rate_text}, "
                     f"gain {gain_text}")
    lines.append(f"any channel: {int(np.count_nonzero(result.any_mask()))} px")
    return "\n".join(lines)


def clean_for_display(image: np.ndarray, params: ImpulseParams, space: str,
                      progress=None) -> tuple[ImpulseResult, tuple[float, float], dict[str, np.ndarray], str]:
    """Worker job: the core stage, then what the widget shows of it (computed here, not on
    the GUI thread, where a full-size pass per channel would freeze the viewer): the cleaned
    image's display range, the pulse masks as 0/1 images, the read-out."""
    result = remove_impulses(image, params, space=space, progress=progress)
    masks = {name: np.ascontiguousarray(mask, dtype=np.uint8) for name, mask in result.masks.items()}
    return result, robust_limits(result.image), masks, pulse_summary(result)


class ImpulseWidget(Container):
    """Remove impulse noise from an image layer; show per-channel pulse masks in colour."""

    SECTION = "impulse"

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._image = create_widget(annotation="napari.layers.Image", label="image")
        self._image.tooltip = "the radiograph (grey or colour camera image) to clean of bright pulses (zingers)"
        self._space = ComboBox(choices=["auto", "hsv", "grey"], value="auto", label="colour space",
                               tooltip="colour space the pulses are detected in: auto = HSV for colour images, "
                                       "grey for grey ones; hsv = hue, saturation, value; grey = one channel")
        names = {"H": "hue", "S": "saturation", "V": "value", "grey": "grey"}
        self._passes = {
            name: param_widget(ImpulseParams, f"passes_{name.lower()}", label=f"passes on {names[name]}",
                               section="impulse")
            for name in ("H", "S", "V", "grey")
        }
        self._window = param_widget(ImpulseParams, "window_px", label="median window (px)", section="impulse")
        self._spots = param_widget(ImpulseParams, "spots", label="spots", section="impulse")
        self._run_button = PushButton(text="Remove impulses",
                                      tooltip="detect the pulses and replace them by the local median; adds "
                                              "'<image> cleaned' and one pulse-mask layer per channel")
        self._restore = restore_defaults_button(lambda: self.set_params(ImpulseParams()))
        self._job = JobPanel()
        self._readout = readout_label()
        super().__init__(widgets=[self._image, self._space, *self._passes.values(), self._window,
                                  self._spots, self._run_button, *self._job.widgets, self._readout, self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self._extra: dict = {}
        self.result: ImpulseResult | None = None
        self._run_button.changed.connect(self.run)
        register_stage_widget(viewer, self)

    # -- parameters (shared TOML section [impulse]) --------------------------------------
    def get_params(self) -> ImpulseParams:
        """The widget's values as core parameters (other fields as last loaded)."""
        values = dict(self._extra)
        values.update({f"passes_{k.lower()}": int(w.value) for k, w in self._passes.items()})
        values["window_px"] = int(self._window.value)
        values["spots"] = str(self._spots.value)
        values["space"] = str(self._space.value)
        return ImpulseParams(**values)

    def set_params(self, params: ImpulseParams) -> None:
        """Show ``params`` in the widget (fields without a control are kept for saving)."""
        from dataclasses import asdict

        values = asdict(params)
        for name, widget in self._passes.items():
            widget.value = values.pop(f"passes_{name.lower()}")
        self._window.value = values.pop("window_px")
        self._spots.value = values.pop("spots")
        if values["space"] in self._space.choices:  # "cfa" (raw files) stays in the saved file
            self._space.value = values.pop("space")
        self._extra = values

    # -- action ----------------------------------------------------------------------------
    @guarded("impulse removal")
    def run(self):
        """Start impulse removal in a thread worker; return the worker (None if nothing to do)."""
        layer = self._image.value
        if layer is None:
            raise ParameterError("choose an image layer first")
        image = np.asarray(layer.data)
        params = self.get_params()
        space = self._space.value
        self._run_button.enabled = False
        self._readout.value = "running..."
        return run_in_worker(clean_for_display, image, params, space, progress=self._job.callback,
                             desc="impulse removal",
                             on_returned=lambda out: self._show_steps(layer, *out),
                             on_finished=job_done(self._run_button, self._job, self._readout),
                             panel=self._job, readout=self._readout)

    def _show_steps(self, layer: napari.layers.Image, result: ImpulseResult, limits: tuple[float, float],
                    masks: dict[str, np.ndarray], summary: str) -> Iterator[None]:
        """Show the result one layer per event-loop turn, each new one over two turns
        (:func:`show_layer_steps`: napari sets a new layer up, then draws it first, on the GUI
        thread). Stopped midway (Cancel), the layers are put back as they were
        (:class:`ShownLayers`)."""
        geometry = same_geometry(layer)
        shown = ShownLayers(self._viewer)
        with shown.put_back_if_stopped():
            yield from show_layer_steps(self._viewer, result.image, f"{layer.name} cleaned", "image",
                                        rgb=bool(getattr(layer, "rgb", False)), contrast_limits=limits, shown=shown,
                                        **geometry)
            for name, mask in masks.items():
                yield
                yield from show_layer_steps(self._viewer, mask, f"{layer.name} pulses {name}", "image",
                                            colormap=pulse_colormap(name), contrast_limits=(0.0, 1.0), opacity=0.8,
                                            blending="translucent", shown=shown, **geometry)
            yield
        self.result = result
        self._readout.value = summary
