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
