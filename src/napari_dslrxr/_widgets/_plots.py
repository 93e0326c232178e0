"""Figures of the widgets drawn in the worker and shown as a picture.

A matplotlib figure drawn on the GUI thread freezes the viewer for a few hundred milliseconds
(building the axes and ticks, then rendering). The figure is therefore made and rendered with
the Agg backend inside the job's worker (:func:`render_figure`; a figure no other thread
touches), and the GUI thread only shows the finished pixels (:class:`WorkerPlot`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

#: Dots per inch of the widgets' figures (their fonts are sized for it).
PLOT_DPI = 80


def render_figure(draw: Callable[[Any], None], size_px: tuple[int, int]) -> tuple[Any, np.ndarray]:
    """Make a figure of ``size_px`` (width, height), let ``draw(figure)`` fill it, render it.

    Returns the figure (its axes and lines, for whoever reads them) and its RGBA pixels.
    Runs in a worker thread.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width_px, height_px = (max(int(v), 50) for v in size_px)
    figure = Figure(figsize=(width_px / PLOT_DPI, height_px / PLOT_DPI), dpi=PLOT_DPI, tight_layout=True)
    canvas = FigureCanvasAgg(figure)
    draw(figure)
    canvas.draw()
    return figure, np.array(canvas.buffer_rgba(), copy=True)


class WorkerPlot:
    """The place of a widget's figure: a fixed-height picture (a read-out changing its length
    must not resize it) showing what :func:`render_figure` made in the worker."""

    def __init__(self, container: Any, height_px: int):
        from qtpy.QtWidgets import QLabel

        self.figure = None
        self.label = QLabel()
        self.label.setFixedHeight(height_px)
        self.label.setMinimumWidth(100)
        container.native.layout().addWidget(self.label)

    def size_px(self) -> tuple[int, int]:
        """The picture's size now (width, height): the figure is drawn at it."""
        return self.label.width(), self.label.height()

    def show(self, figure: Any, rgba: np.ndarray) -> None:
        """Show the pixels of a figure rendered in the worker."""
        from qtpy.QtGui import QImage, QPixmap

        self.figure = figure
        height_px, width_px = rgba.shape[:2]
        image = QImage(rgba.data, width_px, height_px, rgba.strides[0], QImage.Format.Format_RGBA8888)
        self.label.setPixmap(QPixmap.fromImage(image.copy()))  # copy: the array may go


def worker_plot(container: Any, height_px: int, readout: Any, what: str) -> WorkerPlot | None:
    """The widget's plot place, or None (and the read-out says so) without matplotlib (optional:
    ``pip install 'napari-dslrxr[napari]'``)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        readout.value = f"install matplotlib to see {what}"
        return None
    return WorkerPlot(container, height_px)


class ShownFigureMixin:
    """``_figure``: the figure a widget's ``_plot`` (:func:`worker_plot`) shows, None before the
    first result or without matplotlib."""

    @property
    def _figure(self):
        plot = getattr(self, "_plot", None)
        return None if plot is None else plot.figure
