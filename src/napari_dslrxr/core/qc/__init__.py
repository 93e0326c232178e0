"""Detector quality per IEC 62220-1-1: presampled MTF, NNPS and DQE (``dslrxr qc``).

Headless (numpy/scipy), no threads; long steps report ``progress(done, total)``.

* :func:`slanted_edge_mtf` - presampled MTF from a slanted edge;
* :func:`edge_method_mtf` - what that measurement reads from a known presampled MTF (its LSF
  window included), to compare a blur model with it like for like;
* :func:`nnps_from_flats` - NNPS from detrended, half-overlapping ROIs of flats;
* :func:`conversion_function` - mean signal against air kerma; refuses a non-linear response;
* :func:`dqe` - DQE = MTF² / (q NNPS);
* :func:`measure_detector_quality` - all of it from flats, darks and edges;
* :func:`write_qc_outputs` - ``qc.json``, ``qc.csv`` and ``qc.html`` with sidecars.

Methods, formulas and defaults: ``docs/algorithms/qc.md``.
"""

from __future__ import annotations

from .._lazy import lazy_exports

_PUBLIC: dict[str, tuple[str, ...]] = {
    "params": ("QcParams", "SNR2_IN_PER_UGY", "EDGE_ANGLE_RANGE_DEG"),
    "edge": ("EdgeMTF", "edge_method_mtf", "slanted_edge_mtf"),
    "nnps": ("NNPSResult", "nnps_from_flats"),
    "conversion": ("ConversionFunction", "NonLinearResponseError", "conversion_function"),
    "measure": ("DetectorQuality", "DirectionResult", "dqe", "measure_detector_quality", "photon_fluence_per_mm2"),
    "report": ("write_qc_outputs", "qc_figures"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
