"""One entry point: MTF, NNPS and DQE of a detector from flats, darks and slanted edges."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError, ParameterError
from .conversion import ConversionFunction, conversion_function
from .edge import fill_masked, slanted_edge_mtf, spot_mask
from .nnps import NNPSResult, analysis_layout, mean_dark, nnps_from_flats
from .params import SNR2_IN_PER_UGY, QcParams


def photon_fluence_per_mm2(beam: str, air_kerma_ugy: float) -> float:
    """q = K * SNR²_in per µGy of the beam quality (IEC 62220-1-1:2015)."""
    if beam not in SNR2_IN_PER_UGY:
        raise ParameterError(f"qc.beam: must be one of {', '.join(SNR2_IN_PER_UGY)}, got {beam!r}")
    return float(air_kerma_ugy) * SNR2_IN_PER_UGY[beam]


def dqe(mtf: np.ndarray, nnps_mm2: np.ndarray, q_photons_per_mm2: float, *,
        mtf_uncertainty: np.ndarray | None = None, nnps_uncertainty_mm2: np.ndarray | None = None):
    """DQE(f) = MTF(f)² / (q · NNPS(f)) and its standard uncertainty (first-order propagation of
    the MTF and NNPS uncertainties, taken as independent; q is taken as exact).

    Returns
    -------
    (dqe, dqe_uncertainty) : ndarrays
    """
    mtf = np.asarray(mtf, dtype=float)
    nnps = np.asarray(nnps_mm2, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        value = mtf ** 2 / (q_photons_per_mm2 * nnps)
        rel2 = np.zeros_like(value)
        if mtf_uncertainty is not None:
            rel2 = rel2 + (2.0 * np.asarray(mtf_uncertainty) / mtf) ** 2
        if nnps_uncertainty_mm2 is not None:
            rel2 = rel2 + (np.asarray(nnps_uncertainty_mm2) / nnps) ** 2
        unc = np.abs(value) * np.sqrt(rel2)
    return value, unc


@dataclass
class DirectionResult:
    """The three curves in one direction, on the common frequency grid."""

    mtf: np.ndarray
    mtf_uncertainty: np.ndarray
    nnps_mm2: np.ndarray
    nnps_uncertainty_mm2: np.ndarray
    dqe: np.ndarray
    dqe_uncertainty: np.ndarray


_CURVES = tuple(f.name for f in dataclasses.fields(DirectionResult))


@dataclass
class DetectorQuality:
    """MTF, NNPS and DQE of a detector (IEC 62220-1-1), with what they were measured from.

    The main curves (``mtf``, ``nnps_mm2``, ``dqe``) are those of ``direction``: the direction
    of the first edge. ``per_direction`` holds every measured direction (``"horizontal"``:
    frequency along the image rows; ``"vertical"``: along the columns).

    Attributes
    ----------
    frequency_cy_per_mm : ndarray
    mtf, mtf_uncertainty, nnps_mm2, nnps_uncertainty_mm2, dqe, dqe_uncertainty : ndarray
        Read-only, of the main direction (``per_direction[direction]``); same length as
        ``frequency_cy_per_mm``; uncertainties are standard (1 sigma).
    q_photons_per_mm2 : float
        Photon fluence of the flats: air kerma x SNR²_in per µGy of the beam.
    direction : str
    per_direction : dict of str to DirectionResult
    edges : list of EdgeMTF
    edge_rois : list
        ``(r0, c0, r1, c1)`` of each edge's analysis region in its image (None = whole frame).
    nnps : NNPSResult
        Also holds the NNPS ROI positions and the analysis area.
    conversion : ConversionFunction
    pixel_pitch_mm, air_kerma_ugy : float
    beam : str
    warnings : list of str
    settings : dict
        Every [qc] parameter used.
    edge_images : list of ndarray
        The analysed (dark-subtracted, flat-fielded, cropped) edge images, float32, for the
        report's pictures (not in ``to_json``).
    flat_image : ndarray or None
        The first flat minus the mean dark, float32 (report picture of the NNPS ROIs).
    """

    frequency_cy_per_mm: np.ndarray
    q_photons_per_mm2: float
    direction: str
    per_direction: dict
    edges: list
    edge_rois: list
    nnps: NNPSResult
    conversion: ConversionFunction
    pixel_pitch_mm: float
    air_kerma_ugy: float
    beam: str
    warnings: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    edge_images: list = field(default_factory=list, repr=False)
    flat_image: np.ndarray | None = field(default=None, repr=False)

    def __getattr__(self, name: str):
        # mtf, nnps_mm2, dqe and their uncertainties: those of the main direction
        if name in _CURVES and "per_direction" in self.__dict__:
            return getattr(self.per_direction[self.direction], name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def nyquist_cy_per_mm(self) -> float:
        return 0.5 / self.pixel_pitch_mm

    def index_at(self, nyquist_fraction: float) -> int:
        """Index of the frequency sample nearest ``nyquist_fraction`` × Nyquist."""
        target = nyquist_fraction * self.nyquist_cy_per_mm
        return int(np.abs(self.frequency_cy_per_mm - target).argmin())

    def to_json(self) -> dict:
        """The numbers of ``qc.json``: plain lists and floats (non-finite values become None)."""
        from ..io.provenance import to_jsonable

        return to_jsonable({
            "frequency_cy_per_mm": self.frequency_cy_per_mm,
            "mtf": self.mtf, "nnps_mm2": self.nnps_mm2, "dqe": self.dqe,
            "uncertainties": {"mtf": self.mtf_uncertainty, "nnps_mm2": self.nnps_uncertainty_mm2,
                              "dqe": self.dqe_uncertainty,
                              "method": "standard uncertainty (1 sigma): MTF from the spread of independent "
                                        "bands along the edge, NNPS from the spread of the ROIs over the square "
                                        "root of the independent area, DQE propagated from both"},
            "direction": self.direction,
            "per_direction": {k: dataclasses.asdict(v) for k, v in self.per_direction.items()},
            "q_photons_per_mm2": self.q_photons_per_mm2,
            "beam": self.beam, "snr2_in_per_ugy": SNR2_IN_PER_UGY[self.beam],
            "air_kerma_ugy": self.air_kerma_ugy, "pixel_pitch_mm": self.pixel_pitch_mm,
            "nyquist_cy_per_mm": self.nyquist_cy_per_mm,
            "edges": [{"direction": e.direction, "angle_deg": e.angle_deg,
                       "edge_line_rc": _in_frame(e.edge_line, roi),
                       "roi": roi, "n_segments": e.n_segments, "n_outliers": e.n_outliers,
                       "lsf_half_width_px": e.lsf_half_width_px, "oversampling": self.settings.get("edge_oversampling")}
                      for e, roi in zip(self.edges, self.edge_rois)],
            "nnps_rois": {"size_px": self.settings.get("roi_size_px"), "origins_rc": self.nnps.roi_origins,
                          "analysis_area": self.nnps.analysis_area, "n_rois": self.nnps.n_rois,
                          "n_independent": self.nnps.n_independent, "mean_signal": self.nnps.mean_signal,
                          "n_outliers": self.nnps.n_outliers},
            "conversion_function": dataclasses.asdict(self.conversion),
            "warnings": self.warnings,
            "settings": self.settings,
        })


def _in_frame(line, roi) -> list[float]:
    """An edge line ``(row0, col0, row1, col1)`` measured in a region, in whole-frame pixels."""
    r0, c0 = (roi[0], roi[1]) if roi is not None else (0, 0)
    return [line[0] + r0, line[1] + c0, line[2] + r0, line[3] + c0]


def _as_list(frames) -> list[np.ndarray]:
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        return [frames]
    return [np.asarray(f) for f in (frames or [])]


def _check_shape(frame: np.ndarray, shape, name: str) -> np.ndarray:
    frame = np.asarray(frame, dtype=np.float64)
    if frame.ndim != 2:
        raise InputError(name, f"expected a single-channel 2-D frame, got shape {frame.shape}")
    if frame.shape != shape:
        raise InputError(name, f"frame of shape {frame.shape} differs from the first flat's {shape}")
    if not np.isfinite(frame).all():
        raise InputError(name, "NaN or infinite values")
    return frame


def measure_detector_quality(flats: Sequence[np.ndarray], darks: Sequence[np.ndarray] | None,
                             edge, *, pixel_pitch_mm: float | None = None,
                             air_kerma_ugy: float | Sequence[float] | None = None, beam: str | None = None,
                             params: QcParams | None = None, edge_rois: Sequence | None = None,
                             names: dict | None = None,
                             progress: Callable[[int, int], object] | None = None) -> DetectorQuality:
    """Measure MTF, NNPS and DQE per IEC 62220-1-1 from linear frames.

    Parameters
    ----------
    flats : sequence of 2-D arrays
        Open-beam frames (linear, same shape). The NNPS uses the flats at the first flat's air
        kerma; all flats enter the conversion function.
    darks : sequence of 2-D arrays or None
        Dark frames; their mean is subtracted from flats and edges.
    edge : 2-D array or sequence of 2-D arrays
        One slanted-edge image per orientation, same shape as the flats.
    pixel_pitch_mm, air_kerma_ugy, beam :
        Override the values in ``params``. ``air_kerma_ugy`` is one value for every flat or
        one per flat.
    params : QcParams
    edge_rois : sequence of (r0, c0, r1, c1) or None, optional
        Region of each edge image to analyse (end exclusive); None = the whole frame.
    names : dict, optional
        ``{"flats": [...], "darks": [...], "edges": [...]}`` file names for messages.
    progress : callable(done, total), optional

    Raises
    ------
    InputError
        Bad frames, no edge found, or a response not linear in air kerma.
    ParameterError
        Pixel pitch or air kerma not set.
    """
    params = params or QcParams()
    overrides = {k: v for k, v in (("pixel_pitch_mm", pixel_pitch_mm), ("beam", beam)) if v is not None}
    # One value for every flat, or one per flat (the first flat's is the NNPS reference level).
    kermas_given = None if air_kerma_ugy is None else [float(k) for k in np.atleast_1d(air_kerma_ugy)]
    if kermas_given:
        overrides["air_kerma_ugy"] = kermas_given[0]
    params = dataclasses.replace(params, **overrides) if overrides else params
    if not params.pixel_pitch_mm > 0:
        raise ParameterError("qc.pixel_pitch_mm: the pixel pitch is required (--pixel-pitch-mm)")
    if not params.air_kerma_ugy > 0:
        raise ParameterError("qc.air_kerma_ugy: the air kerma at the detector is required (--air-kerma-ugy)")
    names = names or {}
    flats = _as_list(flats)
    darks = _as_list(darks)
    edges = _as_list(edge)
    flat_names = list(names.get("flats") or [f"flat {i + 1}" for i in range(len(flats))])
    dark_names = list(names.get("darks") or [f"dark {i + 1}" for i in range(len(darks))])
    edge_names = list(names.get("edges") or [f"edge {i + 1}" for i in range(len(edges))])
    if not flats:
        raise InputError(None, "no flat frames given")
    if not edges:
        raise InputError(None, "no edge image given")
    shape = np.asarray(flats[0]).shape
    flats = [_check_shape(f, shape, n) for f, n in zip(flats, flat_names)]
    darks = [_check_shape(d, shape, n) for d, n in zip(darks, dark_names)]
    edges = [_check_shape(e, shape, n) for e, n in zip(edges, edge_names)]
    if kermas_given is None or np.ndim(air_kerma_ugy) == 0:
        kermas = [params.air_kerma_ugy] * len(flats)
    else:
        kermas = kermas_given
        if len(kermas) != len(flats):
            raise ParameterError(f"--air-kerma-ugy: give one value for all flats or one per flat "
                                 f"({len(flats)}), got {len(kermas)}")
    total_steps = len(flats) + len(edges) + 1
    done = 0

    def step():
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total_steps)

    dark = mean_dark(darks, shape)
    dark = fill_masked(dark, spot_mask(dark, params.outlier_sigma))  # direct hits on the sensor
    # Conversion function from every flat's NNPS analysis area (the whole central square when
    # the frame is too small for one ROI: the NNPS then refuses with its own message).
    area, _ = analysis_layout(shape, params.roi_size_px, params.nnps_area_fraction)
    if area is None:
        side = int(params.nnps_area_fraction * min(shape))
        r0, c0 = (shape[0] - side) // 2, (shape[1] - side) // 2
        area = (r0, c0, r0 + side, c0 + side)
    means = [float((f - dark)[area[0]:area[2], area[1]:area[3]].mean()) for f in flats]
    for m, n in zip(means, flat_names):
        if not m > 0:
            raise InputError(n, "no signal above the dark frame in the central area")
    conv = conversion_function(means, kermas, tolerance_percent=params.linearity_tolerance_percent,
                               names=flat_names)
    reference = [i for i, k in enumerate(kermas) if k == kermas[0]]
    nnps = nnps_from_flats([flats[i] for i in reference], darks, params.pixel_pitch_mm,
                           roi_size_px=params.roi_size_px, area_fraction=params.nnps_area_fraction,
                           cut_half_width=params.nnps_cut_half_width, frequency_bin=params.frequency_bin,
                           outlier_sigma=params.outlier_sigma, names=[flat_names[i] for i in reference],
                           progress=lambda d, t: step(), dark=dark)
    gain_map = None
    dead = np.zeros(shape, bool)
    if params.flat_field_edge:
        mean_flat = np.mean([flats[i] - dark for i in reference], axis=0)
        mean_flat = fill_masked(mean_flat, spot_mask(mean_flat, params.outlier_sigma))
        gain_map = mean_flat / float(mean_flat.mean())
        dead = ~(gain_map > 0.05)
        if dead.mean() > 0.05:
            raise InputError(flat_names[0], f"{100 * dead.mean():.1f} % of the pixels have almost no signal above "
                                            "the dark; cannot flat-field the edge (fix the flat, or set "
                                            "qc.flat_field_edge = false)")
        gain_map = np.where(dead, 1.0, gain_map)
    edge_results, rois, analysed = [], [], []
    rois_in = list(edge_rois) if edge_rois is not None else [None] * len(edges)
    if len(rois_in) != len(edges):
        raise ParameterError(f"--edge-roi: give one region per edge ({len(edges)}), got {len(rois_in)}")
    for e, n, roi in zip(edges, edge_names, rois_in):
        corrected = e - dark
        valid = ~dead
        if gain_map is not None:
            corrected = corrected / gain_map
        if roi is not None:
            a, b, c, d = (int(v) for v in roi)
            if not (0 <= a < c <= shape[0] and 0 <= b < d <= shape[1]):
                raise ParameterError(f"--edge-roi: {list(roi)} is outside the {shape[0]}x{shape[1]} frame of {n}")
            corrected = corrected[a:c, b:d]
            valid = valid[a:c, b:d]
        edge_results.append(slanted_edge_mtf(corrected, params.pixel_pitch_mm, oversampling=params.edge_oversampling,
                                             lsf_half_width_px=params.lsf_half_width_px,
                                             outlier_sigma=params.outlier_sigma, valid=valid, name=n))
        rois.append(list(roi) if roi is not None else None)
        analysed.append(corrected.astype(np.float32))
        step()
    q = photon_fluence_per_mm2(params.beam, params.air_kerma_ugy)
    freq = nnps.frequency_cy_per_mm
    per_direction = {}
    for res in edge_results:
        if res.direction in per_direction:
            continue  # a second edge of the same orientation: the first one is reported
        mtf = np.interp(freq, res.frequency_cy_per_mm, res.mtf)
        mtf_unc = np.interp(freq, res.frequency_cy_per_mm, res.mtf_uncertainty)
        if res.direction == "horizontal":
            n_val, n_unc = nnps.nnps_horizontal_mm2, nnps.uncertainty_horizontal_mm2
        else:
            n_val, n_unc = nnps.nnps_vertical_mm2, nnps.uncertainty_vertical_mm2
        d_val, d_unc = dqe(mtf, n_val, q, mtf_uncertainty=mtf_unc, nnps_uncertainty_mm2=n_unc)
        per_direction[res.direction] = DirectionResult(mtf, mtf_unc, n_val, n_unc, d_val, d_unc)
    warnings = list(conv.warnings) + list(nnps.warnings) + [w for r in edge_results for w in r.warnings]
    if len(edge_results) > len(per_direction):
        warnings.append("two edges of the same orientation: only the first is reported")
    step()
    return DetectorQuality(
        frequency_cy_per_mm=freq, q_photons_per_mm2=q, direction=edge_results[0].direction, per_direction=per_direction, edges=edge_results,
        edge_rois=rois, nnps=nnps, conversion=conv, pixel_pitch_mm=params.pixel_pitch_mm,
        air_kerma_ugy=params.air_kerma_ugy, beam=params.beam, warnings=warnings,
        settings=dataclasses.asdict(params), edge_images=analysed,
        flat_image=(flats[reference[0]] - dark).astype(np.float32))

