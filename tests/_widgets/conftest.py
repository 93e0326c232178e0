"""Fixtures for the widget tests: a viewer with a docked widget, and waiting for workers."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def wait_for_worker(qtbot):
    """``wait_for_worker(worker)``: wait until a ``run_in_worker`` worker finished and its
    result was shown (on the GUI thread)."""

    def wait(worker, timeout_ms: int = 60_000):
        assert worker is not None, "the widget did not start a worker (see the notifications)"
        qtbot.waitUntil(lambda: getattr(worker, "dslrxr_finished", False), timeout=timeout_ms)
        return worker

    return wait


@pytest.fixture
def errors_shown(monkeypatch):
    """Collect the error notifications the widgets show (they must never raise instead)."""
    shown: list[str] = []
    import napari.utils.notifications as notifications

    monkeypatch.setattr(notifications, "show_error", shown.append)
    return shown


@pytest.fixture
def pulsed_grey(rng):
    """``pulsed_grey(shape, n_pulses, gain)``: see :func:`make_pulsed_grey` (seeded)."""
    return lambda *args, **kwargs: make_pulsed_grey(rng, *args, **kwargs)


def make_pulsed_grey(rng: np.random.Generator, shape=(192, 192), n_pulses: int = 60,
                     gain: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth Poisson radiograph (gain counts per quantum) with single-pixel bright pulses.

    Returns the uint16 image and the bool mask of the injected pulses.
    """
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    mean = 800 + 600 * np.exp(-((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / (2 * (h / 4) ** 2))
    image = gain * rng.poisson(mean / gain)
    truth = np.zeros(h * w, bool)
    truth[rng.choice(h * w, n_pulses, replace=False)] = True
    truth = truth.reshape(h, w)
    image[truth] += 3000
    return image.astype(np.uint16), truth
