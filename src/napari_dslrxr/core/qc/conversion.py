"""The conversion function: mean dark-subtracted signal against air kerma, and the linearity check.

The NNPS normalisation and the DQE assume a detector whose signal is proportional to air
kerma after dark subtraction (or linearised before). With flats at two or more air kermas the
proportional fit S = a * K is checked point by point; a deviation beyond the tolerance refuses
the input, naming the flat that deviates most.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import InputError


class NonLinearResponseError(InputError):
    """The flats' mean signal is not proportional to air kerma after dark subtraction."""


@dataclass
class ConversionFunction:
    """Mean signal per air kerma and how well a proportional response describes it.

    Attributes
    ----------
    air_kerma_ugy, mean_signal : list of float
        One entry per flat (dark-subtracted mean of the central area).
    gain_per_ugy : float
        Slope of the proportional fit S = a K (signal units per µGy).
    intercept : float
        Offset of the free straight-line fit S = a' K + b (0 when only one air kerma).
    deviation_percent : list of float
        S / (a K) - 1 of each flat, in percent.
    max_deviation_percent : float
        Largest |deviation_percent|; NaN when only one air kerma was given.
    checked : bool
        True when at least two distinct air kermas were available.
    warnings : list of str
    """

    air_kerma_ugy: list
    mean_signal: list
    gain_per_ugy: float
    intercept: float
    deviation_percent: list
    max_deviation_percent: float
    checked: bool
    warnings: list = field(default_factory=list)


def conversion_function(mean_signal: Sequence[float], air_kerma_ugy: Sequence[float], *,
                        tolerance_percent: float = 5.0, names: Sequence[str] | None = None) -> ConversionFunction:
    """Fit the proportional conversion function S = a K and check the linearity.

    Parameters
    ----------
    mean_signal : sequence of float
        Dark-subtracted mean signal of each flat's central area.
    air_kerma_ugy : sequence of float
        Air kerma of each flat (µGy), same order.
    tolerance_percent : float
        Largest accepted deviation of any flat from the fit.
    names : sequence of str, optional
        File names for the refusal message.

    Raises
    ------
    NonLinearResponseError
        A flat deviates from the proportional fit by more than the tolerance.
    """
    s = np.asarray(mean_signal, dtype=float)
    k = np.asarray(air_kerma_ugy, dtype=float)
    names = list(names) if names is not None else [f"flat {i + 1}" for i in range(s.size)]
    if s.size != k.size or s.size == 0:
        raise InputError(None, f"{s.size} flats but {k.size} air kerma values")
    if not (k > 0).all():
        raise InputError(names[int(np.argmin(k))], "air kerma must be positive")
    gain = float((s * k).sum() / (k * k).sum())
    checked = np.unique(k).size >= 2
    warnings = []
    deviation = s / (gain * k) - 1.0
    if checked:
        intercept = float(np.polyfit(k, s, 1)[1])  # reported: a large one means an offset left in
        worst = int(np.argmax(np.abs(deviation)))
        max_dev = float(100.0 * abs(deviation[worst]))
        if max_dev > tolerance_percent:
            raise NonLinearResponseError(
                names[worst], f"signal is not linear in air kerma after dark subtraction: {s[worst]:.4g} at "
                f"{k[worst]:.4g} uGy is {100.0 * deviation[worst]:+.1f} % off the proportional fit "
                f"({gain:.4g} per uGy; tolerance {tolerance_percent:g} %); give linear (raw) data or "
                "linearise it first")
    else:
        intercept, max_dev = 0.0, float("nan")
        warnings.append("linearity not checked: all flats have the same air kerma (give flats at two or more "
                        "air kermas to check the conversion function)")
    return ConversionFunction(air_kerma_ugy=k.tolist(), mean_signal=s.tolist(), gain_per_ugy=gain,
                              intercept=float(intercept), deviation_percent=(100.0 * deviation).tolist(),
                              max_deviation_percent=max_dev, checked=bool(checked),
                              warnings=warnings)
