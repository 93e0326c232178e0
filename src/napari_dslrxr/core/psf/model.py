"""SABER-style blur model: source (focal-spot) PSF, detector PSF, and the kernel sampler.

The model follows Mohan, Panas and Cuadra, "SABER: A systems approach to blur estimation and
reduction in X-ray imaging", IEEE TIP 2020 (see ``docs/algorithms/psf.md``, section 'Model'):

* every component has the exponential-power profile ``exp(-(s * r) ** p)`` with
  ``s = 2 * ln(2) ** (1 / p) / FWHM`` (``p = 1`` exponential, ``p = 2`` Gaussian);
* the source PSF is an axis-aligned ellipse with source-plane FWHMs ``F_x`` (columns) and
  ``F_y`` (rows); on the detector its widths are multiplied by ``ODD / SOD = M - 1``
  (``M = SDD / SOD``), so it vanishes for an object lying on the detector;
* the detector PSF is geometry independent: ``w * core + (1 - w) * tail``, two isotropic
  components, each normalised to unit sum;
* the blur kernel of a radiograph is ``source PSF (at its magnification) * detector PSF``.

Kernel sampling
---------------
Kernels are **pixel-area integrated** (each kernel value is the mean of the continuous PSF over
the detector pixel), computed by supersampling every pixel with an odd factor that grows as the
component narrows (``ceil(12 / FWHM_px)``, capped at 41). Point sampling at pixel centres, as
pysaber does, misrepresents components narrower than about 2 px (a 0.5 px FWHM exponential
point-sampled puts almost all mass in one pixel); area integration also matches the way a
detector pixel records the edge radiographs the model is fitted on.

The support of each component reaches ``10 * FWHM / 2`` (SABER's cutoff multiplier 10) and is
**never cropped to an image size**: a long detector tail keeps its full extent, limited only by
the ``max_radius_px`` argument (default :data:`DEFAULT_MAX_RADIUS_PX`).

All lengths in this module are millimetres unless the name ends in ``_px`` (detector pixels).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError
from ..io import atomic_write

#: Largest kernel half-width (pixels) when the caller gives none: a 4097 x 4097 kernel.
DEFAULT_MAX_RADIUS_PX = 2048
#: Support half-width of a component in units of its FWHM (SABER: 10 x FWHM / 2).
SUPPORT_FWHM_MULTIPLE = 5.0
#: Components narrower than this (pixels) are a delta function.
DELTA_FWHM_PX = 1e-3
_MAX_SUPERSAMPLING = 41

PSF_FORMAT = "napari-dslrxr psf"
PSF_FORMAT_VERSION = 1
PARAMETER_NAMES = ("source_fwhm_x_mm", "source_fwhm_y_mm", "detector_fwhm_core_mm",
                   "detector_fwhm_tail_mm", "detector_weight_core")


def fwhm_to_scale(fwhm: float, shape_power: float) -> float:
    """Scale ``s`` of ``exp(-(s r)^p)`` with the given full width at half maximum.

    Parameters
    ----------
    fwhm : float
        Full width at half maximum (any length unit, > 0).
    shape_power : float
        Exponential-power ``p``.

    Returns
    -------
    float
        ``s = 2 ln(2)^(1/p) / fwhm`` in inverse units of ``fwhm``.
    """
    return 2.0 * math.log(2.0) ** (1.0 / shape_power) / fwhm


def scale_to_fwhm(scale: float, shape_power: float) -> float:
    """Inverse of :func:`fwhm_to_scale`."""
    return 2.0 * math.log(2.0) ** (1.0 / shape_power) / scale


def magnification_factor(source_to_object_mm: float, source_to_detector_mm: float) -> float:
    """``ODD / SOD = M - 1``: the factor projecting source-plane widths onto the detector.

    Raises
    ------
    ParameterError
        When a distance is not finite, not positive, or the object lies beyond the detector.
    """
    sod, sdd = float(source_to_object_mm), float(source_to_detector_mm)
    if not (np.isfinite(sod) and np.isfinite(sdd)) or sod <= 0 or sdd <= 0:
        raise ParameterError(f"source_to_object_mm and source_to_detector_mm must be finite and > 0, "
                             f"got {sod!r} and {sdd!r}")
    if sdd < sod:
        raise ParameterError(f"source_to_detector_mm ({sdd:g}) must be >= source_to_object_mm ({sod:g})")
    return (sdd - sod) / sod


def _supersampling(fwhm_px: float) -> int:
    """Odd sub-samples per pixel and axis so that a component of this FWHM is well integrated."""
    n = int(math.ceil(12.0 / max(fwhm_px, 1e-6)))
    n = min(max(n, 1), _MAX_SUPERSAMPLING)
    return n if n % 2 == 1 else n + 1


def _radius_px(fwhm_px: float, max_radius_px: int) -> int:
    return int(min(math.ceil(SUPPORT_FWHM_MULTIPLE * fwhm_px), max_radius_px))


def _delta() -> np.ndarray:
    return np.ones((1, 1), dtype=np.float64)


def sample_exponential_power(fwhm_x_px: float, fwhm_y_px: float, shape_power: float, *,
                             radius_x_px: int, radius_y_px: int) -> np.ndarray:
    """Pixel-area-integrated ``exp(-((s_x x)^2 + (s_y y)^2)^(p/2))`` normalised to unit sum.

    Parameters
    ----------
    fwhm_x_px, fwhm_y_px : float
        FWHM along columns and rows, detector pixels (> 0).
    shape_power : float
        Exponential-power ``p``.
    radius_x_px, radius_y_px : int
        Half-width of the returned array (columns, rows); its shape is
        ``(2 radius_y_px + 1, 2 radius_x_px + 1)``.

    Returns
    -------
    ndarray of float64
        Centred kernel, sums to 1.
    """
    n = _supersampling(min(fwhm_x_px, fwhm_y_px))
    scale_x = fwhm_to_scale(fwhm_x_px, shape_power)
    scale_y = fwhm_to_scale(fwhm_y_px, shape_power)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    x = (np.arange(-radius_x_px, radius_x_px + 1)[:, None] + offsets[None, :]).ravel()
    y = (np.arange(-radius_y_px, radius_y_px + 1)[:, None] + offsets[None, :]).ravel()
    r2 = (scale_y * y[:, None]) ** 2 + (scale_x * x[None, :]) ** 2
    values = np.exp(-(r2 ** (shape_power / 2.0)))
    ny, nx = 2 * radius_y_px + 1, 2 * radius_x_px + 1
    kernel = values.reshape(ny, n, nx, n).sum(axis=(1, 3))
    return kernel / kernel.sum()


def _centre_pad(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape, dtype=kernel.dtype)
    r0 = (shape[0] - kernel.shape[0]) // 2
    c0 = (shape[1] - kernel.shape[1]) // 2
    out[r0:r0 + kernel.shape[0], c0:c0 + kernel.shape[1]] = kernel
    return out


def _centre_crop(kernel: np.ndarray, radius_px: int) -> np.ndarray:
    ry = min(radius_px, kernel.shape[0] // 2)
    rx = min(radius_px, kernel.shape[1] // 2)
    cy, cx = kernel.shape[0] // 2, kernel.shape[1] // 2
    return kernel[cy - ry:cy + ry + 1, cx - rx:cx + rx + 1]


def _finish(kernel: np.ndarray) -> np.ndarray:
    """Clip FFT round-off below zero, renormalise to unit sum, float32."""
    kernel = np.clip(kernel, 0.0, None)
    kernel = kernel / kernel.sum()
    return kernel.astype(np.float32)


def _check_cap(max_radius_px) -> int:
    if max_radius_px is None:
        return DEFAULT_MAX_RADIUS_PX
    if isinstance(max_radius_px, bool) or not float(max_radius_px).is_integer() or max_radius_px < 0:
        raise ParameterError(f"max_radius_px must be a non-negative integer, got {max_radius_px!r}")
    return int(max_radius_px)


@dataclass(frozen=True)
class PSFModel:
    """Source + detector blur model (SABER), fitted by :func:`napari_dslrxr.core.psf.edge_fit.fit_edges`.

    Parameters
    ----------
    pixel_pitch_mm : float
        Detector pixel pitch on the scintillator plane, mm (> 0). Use 1.0 to work in pixels.
    source_fwhm_x_mm, source_fwhm_y_mm : float
        Focal-spot FWHM in the source plane along columns (x) and rows (y), mm (>= 0).
    detector_fwhm_core_mm, detector_fwhm_tail_mm : float
        FWHM of the detector PSF's narrow core and long tail, mm (>= 0).
    detector_weight_core : float
        Weight ``w`` of the core in ``[0, 1]``; the tail has ``1 - w``.
    shape_power : float
        Exponential-power ``p`` of every component, in ``(0, 2]`` (1 exponential, 2 Gaussian).
    uncertainty : dict
        One-sigma uncertainty per parameter name (same units as the parameter).
    fit_report : dict
        Residual RMS, cost, number of images and other fit diagnostics (JSON types).
    """

    pixel_pitch_mm: float
    source_fwhm_x_mm: float
    source_fwhm_y_mm: float
    detector_fwhm_core_mm: float
    detector_fwhm_tail_mm: float
    detector_weight_core: float
    shape_power: float = 1.0
    uncertainty: dict = field(default_factory=dict)
    fit_report: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("pixel_pitch_mm",) + PARAMETER_NAMES + ("shape_power",):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ParameterError(f"PSF parameter {name} must be a number, got {value!r}")
            if not np.isfinite(value):
                raise ParameterError(f"PSF parameter {name} must be finite, got {value!r}")
            if value < 0:
                raise ParameterError(f"PSF parameter {name} must be >= 0, got {value!r}")
        if self.pixel_pitch_mm <= 0:
            raise ParameterError(f"PSF parameter pixel_pitch_mm must be > 0, got {self.pixel_pitch_mm!r}")
        if self.detector_weight_core > 1:
            raise ParameterError(f"PSF parameter detector_weight_core must be in [0, 1], "
                                 f"got {self.detector_weight_core!r}")
        if not 0 < self.shape_power <= 2:
            raise ParameterError(f"PSF parameter shape_power must be in (0, 2], got {self.shape_power!r}")
        if not isinstance(self.uncertainty, dict) or not isinstance(self.fit_report, dict):
            raise ParameterError("PSF uncertainty and fit_report must be dictionaries")

    # -- widths on the detector ---------------------------------------------------------------
    def source_fwhm_on_detector_px(self, source_to_object_mm: float,
                                   source_to_detector_mm: float) -> tuple[float, float]:
        """Focal-spot FWHM projected onto the detector, ``(columns, rows)`` in pixels."""
        factor = magnification_factor(source_to_object_mm, source_to_detector_mm)
        return (self.source_fwhm_x_mm * factor / self.pixel_pitch_mm,
                self.source_fwhm_y_mm * factor / self.pixel_pitch_mm)

    # -- kernels --------------------------------------------------------------------------------
    def source_kernel(self, source_to_object_mm: float, source_to_detector_mm: float, *,
                      max_radius_px: int | None = None) -> np.ndarray:
        """Source (focal-spot) blur on the detector pixel grid at this geometry.

        Parameters
        ----------
        source_to_object_mm, source_to_detector_mm : float
            SOD and SDD in mm (``SDD >= SOD > 0``).
        max_radius_px : int, optional
            Cap on the kernel half-width in pixels (default :data:`DEFAULT_MAX_RADIUS_PX`).

        Returns
        -------
        ndarray of float32
            Odd-sized, centred, sums to 1; ``(1, 1)`` when the spot projects to nothing.
        """
        cap = _check_cap(max_radius_px)
        fwhm_x_px, fwhm_y_px = self.source_fwhm_on_detector_px(source_to_object_mm, source_to_detector_mm)
        return _finish(self._source_kernel_f64(fwhm_x_px, fwhm_y_px, cap))

    def detector_kernel(self, *, max_radius_px: int | None = None) -> np.ndarray:
        """Detector blur (core + tail mixture) on the pixel grid; independent of the geometry.

        Returns
        -------
        ndarray of float32
            Odd-sized, centred, sums to 1.
        """
        return _finish(self._detector_kernel_f64(_check_cap(max_radius_px)))

    def kernel(self, source_to_object_mm: float, source_to_detector_mm: float, *,
               max_radius_px: int | None = None) -> np.ndarray:
        """Total blur kernel of a radiograph at this geometry: source PSF convolved with detector PSF.

        Parameters
        ----------
        source_to_object_mm, source_to_detector_mm : float
            SOD and SDD in mm (``SDD >= SOD > 0``).
        max_radius_px : int, optional
            Cap on the kernel half-width in pixels (default :data:`DEFAULT_MAX_RADIUS_PX`); the
            support is otherwise ``5 x FWHM`` of the widest component, never the image size.

        Returns
        -------
        ndarray of float32
            Square, odd-sized, centred on the middle pixel, non-negative, sums to 1.
        """
        from scipy.signal import fftconvolve

        cap = _check_cap(max_radius_px)
        fwhm_x_px, fwhm_y_px = self.source_fwhm_on_detector_px(source_to_object_mm, source_to_detector_mm)
        source = self._source_kernel_f64(fwhm_x_px, fwhm_y_px, cap)
        detector = self._detector_kernel_f64(cap)
        if source.size == 1:
            total = detector
        elif detector.size == 1:
            total = source
        else:
            total = fftconvolve(detector, source, mode="full")
        size = max(total.shape)
        total = _centre_crop(_centre_pad(total, (size, size)), cap)
        return _finish(total)

    def _source_kernel_f64(self, fwhm_x_px: float, fwhm_y_px: float, cap: int) -> np.ndarray:
        if max(fwhm_x_px, fwhm_y_px) < DELTA_FWHM_PX:
            return _delta()
        # A vanishing axis becomes a thin line: give it a tiny but finite width.
        fwhm_x_px = max(fwhm_x_px, DELTA_FWHM_PX)
        fwhm_y_px = max(fwhm_y_px, DELTA_FWHM_PX)
        return sample_exponential_power(fwhm_x_px, fwhm_y_px, self.shape_power,
                                        radius_x_px=_radius_px(fwhm_x_px, cap),
                                        radius_y_px=_radius_px(fwhm_y_px, cap))

    def _detector_kernel_f64(self, cap: int) -> np.ndarray:
        weight = float(self.detector_weight_core)
        components = []
        for fwhm_mm, w in ((self.detector_fwhm_core_mm, weight), (self.detector_fwhm_tail_mm, 1.0 - weight)):
            if w <= 0:
                continue
            fwhm_px = fwhm_mm / self.pixel_pitch_mm
            if fwhm_px < DELTA_FWHM_PX:
                components.append((w, _delta()))
            else:
                radius = _radius_px(fwhm_px, cap)
                components.append((w, sample_exponential_power(fwhm_px, fwhm_px, self.shape_power,
                                                               radius_x_px=radius, radius_y_px=radius)))
        size = max(k.shape[0] for _, k in components)
        total = np.zeros((size, size))
        for w, k in components:
            total += w * _centre_pad(k, (size, size))
        return total

    # -- serialisation ----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain-JSON description (the content of ``psf.json``)."""
        record = {"format": PSF_FORMAT, "format_version": PSF_FORMAT_VERSION}
        record.update({k: (float(v) if not isinstance(v, dict) else v) for k, v in asdict(self).items()})
        return record


def save_psf(model: PSFModel, path: str | os.PathLike, *, inputs=()) -> Path:
    """Write ``model`` to ``path`` (``psf.json``) atomically.

    Parameters
    ----------
    model : PSFModel
    path : path-like
        Destination; refused when it is one of ``inputs``.
    inputs : iterable of path-like
        Input files of the fit (never overwritten).

    Returns
    -------
    Path
    """
    from ..io.provenance import to_jsonable

    text = json.dumps(to_jsonable(model.to_dict()), indent=2, allow_nan=False) + "\n"
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"), inputs=inputs)


def load_psf(path: str | os.PathLike) -> PSFModel:
    """Read and validate a ``psf.json`` written by :func:`save_psf`.

    Raises
    ------
    InputError
        When the file is missing, not JSON, not a PSF file, or a field is missing, ill-typed or
        out of range (the one-line message names the file and the key).
    """
    from ..io import read_structured_file

    path = Path(path)
    record = read_structured_file(path, what="PSF file", fmt="json")
    if record.get("format") != PSF_FORMAT:
        raise InputError(path, f"not a PSF file (expected \"format\": \"{PSF_FORMAT}\")")
    if record.get("format_version") != PSF_FORMAT_VERSION:
        raise InputError(path, f"unsupported format_version {record.get('format_version')!r} "
                               f"(this version reads {PSF_FORMAT_VERSION})")
    kwargs = {}
    for key in ("pixel_pitch_mm",) + PARAMETER_NAMES + ("shape_power",):
        if key not in record:
            raise InputError(path, f"missing key {key!r}")
        value = record[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(path, f"key {key!r} must be a number, got {value!r}")
        kwargs[key] = float(value)
    for key in ("uncertainty", "fit_report"):
        value = record.get(key, {})
        if not isinstance(value, dict):
            raise InputError(path, f"key {key!r} must be an object, got {type(value).__name__}")
        kwargs[key] = value
    try:
        return PSFModel(**kwargs)
    except ParameterError as exc:
        raise InputError(path, str(exc)) from None
