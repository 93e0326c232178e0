"""Robust statistics shared by the stages, the PSF fit and the diagnosis."""

from __future__ import annotations

import numpy as np

#: 1 / Phi^-1(3/4): scales the median absolute deviation to the standard deviation of a normal
#: distribution.
MAD_TO_SIGMA = 1.4826


def robust_sigma(values: np.ndarray, center: float | None = None) -> float:
    """Standard deviation estimated from the median absolute deviation, ``1.4826 * MAD``.

    Insensitive to up to half the values being outliers (pulses, edges, dust). The deviations
    are taken from the median, or from ``center`` when given (e.g. 0 for residuals of a fit).
    The arithmetic is done in the values' own dtype (float32 values give a float32 MAD).
    """
    values = np.asarray(values)
    deviation = values - (np.median(values) if center is None else center)
    return float(MAD_TO_SIGMA * np.median(np.abs(deviation)))


def robust_line_fit(x: np.ndarray, y: np.ndarray, *, rounds: int, clip_sigma: float, min_spread: float,
                    min_points: int) -> tuple[float, float] | None:
    """Straight line ``y = slope * x + intercept`` by least squares, refitted ``rounds`` times on
    the points within ``clip_sigma`` robust sigmas (at least ``min_spread``) of the last fit.

    Returns ``(slope, intercept)``, or None when fewer than ``min_points`` points remain (the
    caller says what that means for its input).
    """
    keep = np.ones(x.size, bool)
    for _ in range(rounds):
        slope, intercept = np.polyfit(x[keep], y[keep], 1)
        resid = y - (slope * x + intercept)
        spread = max(robust_sigma(resid[keep], center=0.0), min_spread)
        keep = np.abs(resid) < clip_sigma * spread
        if keep.sum() < min_points:
            return None
    slope, intercept = np.polyfit(x[keep], y[keep], 1)
    return float(slope), float(intercept)
