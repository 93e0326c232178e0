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
* the core is either the exponential-power profile above (``detector_core_mtf_scale_mm == 0``,
  files of format version 1) or, as fitted since format version 2, defined by its radial MTF
  ``(1 + u (f s)^q)^(-1/u)`` (:func:`generalised_mtf`: scale ``s``, power ``q``, "Linnik"
  parameter ``u``; ``u = 0`` is the stretched exponential ``exp(-(f s)^q)``, ``q = 2, u = 1``
  the Lorentzian ``1 / (1 + (f s)^2)``, ``q = 2, u = 0`` a Gaussian and ``q = 2, u = 2/3``
  SABER's exponential ``exp(-r)``), which real scintillators follow more closely;
* the focal spot is only part of the model when the edges identified it (``source_fitted``);
  otherwise its widths are 0 and the detector PSF holds the combined blur at the fitted
  geometry;
* the blur kernel of a radiograph is ``source PSF (at its magnification) * detector PSF``.

The kernels are sampled by :mod:`.kernel_sampling`, the radial shapes are in :mod:`.mtf_shapes`
and the file ``psf.json`` is read and written by :mod:`.psf_file`.

All lengths in this module are millimetres unless the name ends in ``_px`` (detector pixels).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import ParameterError
from .kernel_sampling import (_MAX_SUPERSAMPLING, DELTA_FWHM_PX, _centre_crop, _centre_pad, _check_cap, _delta,
                              _finish, _radius_px, sample_exponential_power)
from .mtf_shapes import _mtf_cutoff, exponential_power_mtf, generalised_mtf

PSF_FORMAT = "napari-dslrxr psf"
#: Format version written by :meth:`PSFModel.to_dict` (readable versions: :mod:`.psf_file`).
PSF_FORMAT_VERSION = 2
PARAMETER_NAMES = ("source_fwhm_x_mm", "source_fwhm_y_mm", "detector_fwhm_core_mm",
                   "detector_fwhm_tail_mm", "detector_weight_core")
#: Fraction of the generalised core kernel's sum kept by its crop (the rest, beyond the smallest
#: centred square holding this fraction, is dropped and the kernel renormalised). Dropping a
#: part of sum e changes the MTF by at most 2 e / (1 - e) at any frequency: 0.002 here. Measured
#: on the NIQA left-edge kernel (q 1.39, scale 7.2 px): 413 -> 235 px a side, MTF change
#: 0.0012; 99.5 % would give about 80 px and 0.0058, beyond the 0.005 allowed.
CORE_KERNEL_ENERGY = 0.999
#: Parameters of the MTF-defined detector core (format version 2).
CORE_MTF_NAMES = ("detector_core_mtf_scale_mm", "detector_core_mtf_power", "detector_core_mtf_linnik")


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


def _with_sd(value: float, sd: float | None, unit: str = "") -> str:
    """``value ± sd unit``, or "not determined" when the uncertainty exceeds the value."""
    if sd is not None and np.isfinite(sd) and sd > abs(value):
        return f"not determined by these edges ({value:.3g} ± {sd:.2g}{unit})"
    return f"{value:.3g}" + (f" ± {sd:.2g}" if sd is not None and np.isfinite(sd) else "") + unit


def _plus_minus(value: float, sd: float | None) -> str:
    """``value ± sd`` of a shape parameter (0 is a valid value of ``u``, so no "not determined")."""
    return f"{value:.3g}" + (f" ± {sd:.2g}" if sd is not None and np.isfinite(sd) else "")


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
        Exponential-power ``p`` of every spatially defined component, in ``(0, 2]`` (1
        exponential, 2 Gaussian).
    detector_core_mtf_scale_mm, detector_core_mtf_power, detector_core_mtf_linnik : float
        The detector core defined by its MTF ``(1 + u (f s)^q)^(-1/u)`` (:func:`generalised_mtf`):
        scale ``s`` (mm, > 0 selects this core; 0 keeps the exponential-power core of FWHM
        ``detector_fwhm_core_mm``), power ``q`` in ``(0, 2]``, Linnik parameter ``u >= 0``. With
        this core, ``detector_fwhm_core_mm`` is unused (0; ``null`` in ``psf.json``).
    source_fitted : bool
        False when the edges could not identify the focal spot (one object distance, or
        distances too close): the source widths are then 0 and ``psf.json`` says "not fitted".
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
    detector_core_mtf_scale_mm: float = 0.0
    detector_core_mtf_power: float = 2.0
    detector_core_mtf_linnik: float = 0.0
    source_fitted: bool = True
    uncertainty: dict = field(default_factory=dict)
    fit_report: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.source_fitted, (bool, np.bool_)):
            raise ParameterError(f"PSF parameter source_fitted must be true or false, got {self.source_fitted!r}")
        for name in ("pixel_pitch_mm",) + PARAMETER_NAMES + ("shape_power",) + CORE_MTF_NAMES:
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
        if not 0 < self.detector_core_mtf_power <= 2:
            raise ParameterError(f"PSF parameter detector_core_mtf_power must be in (0, 2], "
                                 f"got {self.detector_core_mtf_power!r}")
        if not self.source_fitted and (self.source_fwhm_x_mm or self.source_fwhm_y_mm):
            raise ParameterError("PSF source widths must be 0 when the source is not fitted")
        if not isinstance(self.uncertainty, dict) or not isinstance(self.fit_report, dict):
            raise ParameterError("PSF uncertainty and fit_report must be dictionaries")

    # -- widths on the detector ---------------------------------------------------------------
    def source_fwhm_on_detector_px(self, source_to_object_mm: float,
                                   source_to_detector_mm: float) -> tuple[float, float]:
        """Focal-spot FWHM projected onto the detector, ``(columns, rows)`` in pixels."""
        factor = magnification_factor(source_to_object_mm, source_to_detector_mm)
        return (self.source_fwhm_x_mm * factor / self.pixel_pitch_mm,
                self.source_fwhm_y_mm * factor / self.pixel_pitch_mm)

    @property
    def core_from_mtf(self) -> bool:
        """True when the detector core is defined by its generalised MTF (format version 2)."""
        return self.detector_core_mtf_scale_mm > 0

    # -- transfer functions -----------------------------------------------------------------------
    def detector_mtf(self, frequency_cy_per_mm) -> np.ndarray:
        """Radial MTF of the detector PSF (core + tail, before the pixel aperture)."""
        f = np.abs(np.asarray(frequency_cy_per_mm, dtype=np.float64))
        w = float(self.detector_weight_core)
        if self.core_from_mtf:
            core = generalised_mtf(f * self.detector_core_mtf_scale_mm, self.detector_core_mtf_power,
                                   self.detector_core_mtf_linnik)
        else:
            core = self._component_mtf(f, self.detector_fwhm_core_mm)
        if w >= 1.0:
            return core
        return w * core + (1.0 - w) * self._component_mtf(f, self.detector_fwhm_tail_mm)

    def mtf50_cy_per_mm(self) -> float:
        """Frequency at which the detector MTF falls to 0.5 (cycles/mm; inf when it never does)."""
        hi = 1.0 / self.pixel_pitch_mm
        while self.detector_mtf(hi) > 0.5:
            hi *= 2.0
            if hi > 1e6 / self.pixel_pitch_mm:
                return float("inf")
        lo = 0.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.detector_mtf(mid) > 0.5 else (lo, mid)
        return 0.5 * (lo + hi)

    def detector_lsf_fwhm_mm(self) -> float:
        """FWHM of the detector's line spread function (before the pixel aperture), mm.

        From the radial MTF by a 1-D cosine transform on a grid 400 steps per MTF50 period;
        finite for every shape of the family (the 2-D PSF of a Lorentzian-like core has a
        logarithmic peak, so its own FWHM is not a useful width).
        """
        f50 = self.mtf50_cy_per_mm()
        if not math.isfinite(f50):
            return 0.0
        step = 1.0 / (400.0 * f50)
        n = 2 ** 18
        lsf = np.fft.irfft(self.detector_mtf(np.fft.rfftfreq(n, d=step)), n)
        lsf = np.concatenate([lsf[n // 2:], lsf[:n // 2]])     # t = 0 at index n // 2
        above = np.nonzero(lsf >= 0.5 * lsf[n // 2])[0]
        return float((above[-1] - above[0] + 1) * step)

    def _component_mtf(self, f: np.ndarray, fwhm_mm: float) -> np.ndarray:
        kappa = 2.0 * math.log(2.0) ** (1.0 / self.shape_power)
        return exponential_power_mtf(f * fwhm_mm / kappa, self.shape_power)

    def presampling_mtf(self, frequency_cy_per_mm, source_to_object_mm: float, source_to_detector_mm: float,
                        normal_angle_rad: float = 0.0) -> np.ndarray:
        """MTF along one direction of the blur at this geometry including the pixel aperture:
        what a slanted-edge measurement of an edge with this normal gives (focal spot projected
        with the magnification x detector x square pixel aperture)."""
        f = np.abs(np.asarray(frequency_cy_per_mm, dtype=np.float64))
        c, s = math.cos(normal_angle_rad), math.sin(normal_angle_rad)
        factor = magnification_factor(source_to_object_mm, source_to_detector_mm)
        source_width = factor * math.hypot(self.source_fwhm_x_mm * c, self.source_fwhm_y_mm * s)
        pitch = self.pixel_pitch_mm
        return (self._component_mtf(f, source_width) * self.detector_mtf(f)
                * np.abs(np.sinc(f * pitch * c) * np.sinc(f * pitch * s)))

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
        spatial = [(self.detector_fwhm_tail_mm, 1.0 - weight)]
        if self.core_from_mtf:
            if weight > 0:
                components.append((weight, self._mtf_core_kernel_f64(cap)))
        else:
            spatial.insert(0, (self.detector_fwhm_core_mm, weight))
        for fwhm_mm, w in spatial:
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

    def _mtf_core_kernel_f64(self, cap: int) -> np.ndarray:
        """Pixel-area-integrated kernel of the MTF-defined core, by Fourier synthesis.

        The radial MTF times the pixel aperture ``sinc(f_x) sinc(f_y)`` is sampled on a grid
        ``n`` times finer than the pixels (``n`` odd, so that frequencies up to ``n / 2``
        cycles/pixel, where the MTF has fallen below 1e-5, are kept; at most 41 and at most
        2047 samples a side), inverse transformed, and read at the pixel centres. The support
        reaches 30 scales (the heavy tail of a stretched exponential with ``q`` near 1 keeps
        about 0.3 % of its line spread beyond it) and at least 8 pixels; it is then cropped to
        the smallest centred square holding :data:`CORE_KERNEL_ENERGY` of the kernel's sum and
        renormalised (see that constant for the bound on the MTF).
        """
        scale_px = self.detector_core_mtf_scale_mm / self.pixel_pitch_mm
        q, u = self.detector_core_mtf_power, self.detector_core_mtf_linnik
        radius = int(min(max(math.ceil(30.0 * scale_px), 8), cap))
        size = 2 * radius + 1
        cutoff = _mtf_cutoff(scale_px, q, u)
        n = int(min(max(math.ceil(2.0 * cutoff), 1), _MAX_SUPERSAMPLING, max(2047 // size, 1)))
        n += 1 - n % 2
        fine = size * n
        fy = np.fft.fftfreq(fine, d=1.0 / n)[:, None]
        fx = np.fft.rfftfreq(fine, d=1.0 / n)[None, :]
        spectrum = generalised_mtf(np.hypot(fx, fy) * scale_px, q, u) * np.sinc(fx) * np.sinc(fy)
        psf = np.fft.fftshift(np.fft.irfft2(spectrum, s=(fine, fine))[::n, ::n])
        psf /= psf.sum()
        # Sum inside the centred square of each radius: the smallest radius holding the energy sets the crop.
        ring = np.maximum.outer(np.abs(np.arange(-radius, radius + 1)), np.abs(np.arange(-radius, radius + 1)))
        inside = np.cumsum(np.bincount(ring.ravel(), weights=psf.ravel(), minlength=radius + 1))
        keep = int(np.argmax(inside >= CORE_KERNEL_ENERGY)) if inside[-1] >= CORE_KERNEL_ENERGY else radius
        return _centre_crop(psf, max(keep, 1))

    # -- read-out ---------------------------------------------------------------------------------
    def describe(self) -> list[str]:
        """Lines stating what was fitted, with 1-sigma uncertainties, and what was not (CLI, GUI)."""
        unc, report = self.uncertainty, self.fit_report
        lines = []
        if self.source_fitted:
            lines.append(f"focal spot FWHM x, y: {_with_sd(self.source_fwhm_x_mm, unc.get('source_fwhm_x_mm'))}, "
                         f"{_with_sd(self.source_fwhm_y_mm, unc.get('source_fwhm_y_mm'), ' mm')}")
            detector = "detector"
        else:
            lines.append("focal spot: not fitted (" + report.get(
                "note", "the object distances cannot separate it from the detector blur").removeprefix(
                "focal spot ") + ")")
            detector = "combined blur (focal spot + detector)"
        if self.core_from_mtf:
            lines.append(f"{detector} core MTF (1 + u (f s)^q)^(-1/u): "
                         f"s {_with_sd(self.detector_core_mtf_scale_mm, unc.get('detector_core_mtf_scale_mm'), ' mm')}, "
                         f"q {_plus_minus(self.detector_core_mtf_power, unc.get('detector_core_mtf_power'))}, "
                         f"u {_plus_minus(self.detector_core_mtf_linnik, unc.get('detector_core_mtf_linnik'))}")
        else:
            lines.append(f"{detector} core FWHM: "
                         f"{_with_sd(self.detector_fwhm_core_mm, unc.get('detector_fwhm_core_mm'), ' mm')}")
        if self.detector_weight_core < 1.0:
            lines.append(f"{detector} tail FWHM: "
                         f"{_with_sd(self.detector_fwhm_tail_mm, unc.get('detector_fwhm_tail_mm'), ' mm')}")
            lines.append(f"core weight: {_with_sd(self.detector_weight_core, unc.get('detector_weight_core'))}")
        else:
            lines.append("tail: none (core weight 1)")
        lines.append(f"{detector} MTF50 {self.mtf50_cy_per_mm():.3g} cycles/mm, "
                     f"line spread FWHM {self.detector_lsf_fwhm_mm():.3g} mm (before the pixel aperture)")
        return lines

    # -- serialisation ----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain-JSON description (the content of ``psf.json``).

        The source widths are ``null`` (with ``"source": "not fitted"``) when the edges did not
        identify the focal spot.
        """
        record = {"format": PSF_FORMAT, "format_version": PSF_FORMAT_VERSION}
        for k, v in asdict(self).items():
            record[k] = v if isinstance(v, (dict, bool)) else float(v)
        if not self.source_fitted:
            record["source_fwhm_x_mm"] = record["source_fwhm_y_mm"] = None
            record["source"] = "not fitted"
        if self.core_from_mtf:
            record["detector_fwhm_core_mm"] = None   # the core is given by its MTF
        return record
