"""Fit the SABER source + detector blur model to radiographs of straight edges.

Method (``docs/algorithms/psf.md``, sections 'Edge forward model' and 'Fit')
-----------------------------------------------------------------------------
Every edge image ``j`` is normalised (``(raw - dark) / (bright - dark)`` when flat and dark frames
are given), then modelled as

``y_j(pixel) = a_j + (b_j - a_j) * ESF_j(d)``,  ``d = (x - x_c) cos(phi_j) + (y - y_c) sin(phi_j) - c_j``

where ``d`` is the signed distance (pixels) of the pixel centre from the edge line, whose offset
``c_j`` and normal angle ``phi_j`` are fitted (not frozen from a contour), and ``a_j, b_j`` are
the fitted dark- and bright-side transmission levels. Because the ideal object is a half plane,
its blurred and pixel-integrated image depends on ``d`` only, through the edge spread function
of the 2-D kernel projected onto the edge normal. By the Fourier slice theorem that ESF has the
1-D transfer function

``OTF(f) = G(f W_src / k) * [w G(f F_core / k) + (1 - w) G(f F_tail / k)] * sinc(f cos phi) sinc(f sin phi)``

with ``k = 2 ln(2)^(1/p)``, ``G`` the normalised 2-D Fourier transform of ``exp(-r^p)``
(``(1 + (2 pi q)^2)^(-3/2)`` for ``p = 1``, ``exp(-pi^2 q^2)`` for ``p = 2``),
``W_src = (M_j - 1) sqrt((F_x cos phi)^2 + (F_y sin phi)^2)`` the focal spot projected onto the
detector and onto the edge normal, and the two sincs the square pixel aperture projected onto
the normal (exact area integration). The ESF itself is evaluated on a fine 1-D grid (default
1/16 px) by one inverse real FFT, ``ESF(t) = 1/2 + t/L + (1/h) irfft(OTF / (2 pi i f))``, and
linearly interpolated at each pixel's ``d``. The mixture is split, ``ESF = w E_core + (1 - w)
E_tail``: the compact core part lives on the fine grid with a short period, the smooth tail part
(tail FWHM >= 4 px) on a 1/2 px grid whose period covers 8 FWHMs of the widest tail allowed
(default 4 x the largest ROI side). So the **tail is modelled analytically over its whole
extent** and is never cut by the region of interest; the ROI only decides which pixels are
compared.

All edges are fitted jointly by ``scipy.optimize.minimize(method="L-BFGS-B")`` on the mean squared
residual with an **exact gradient**: the derivative of every OTF factor is analytic, the
gradient with respect to the global parameters is the inner product of the back-projected
residual with ``irfft(dOTF / (2 pi i f))`` evaluated in the Fourier domain (Parseval), and the
derivative with respect to ``d`` is the slope of the linear interpolant (so the gradient is the
gradient of the very objective the optimiser sees; ``tests/core/psf/test_edge_fit.py`` checks it
against finite differences). The optimiser works in coordinates scaled by the square root of the
Gauss-Newton Hessian diagonal at the start (unit curvature per coordinate), which halves the
iterations.

Parameters: log FWHMs of the source (``F_x``, ``F_y``, source plane) and detector components
(core, tail), the core weight ``w`` in ``[0.5, 1]``, and per edge ``c_j``, ``phi_j``, ``a_j``,
``b_j`` (the levels enter linearly and are solved in closed form inside every evaluation:
variable projection). With a single source-to-object ratio the source cannot be told from the detector blur:
the source is then fixed to zero and the detector PSF carries the combined blur. With edges of
one orientation only, ``F_y`` is tied to ``F_x``.

Robustness: bright impulses (gamma-ray hits on the camera) are masked before the fit (pixels
more than 8 robust sigmas above a 5x5 median, dilated by one pixel), and after a first fit every
pixel whose residual exceeds ``outlier_sigma`` robust sigmas is masked and the fit is refined.

Noise model: photon noise differs between the dark and bright sides of an edge, so after the
first, unweighted fit the residual sigma is estimated per bin of the fitted level and the fit is
refined by weighted least squares (weights ``1 / sigma^2``).

Uncertainties: Gauss-Newton / Fisher approximation ``cov = sigma^2 (J^T W J)^-1`` with
``sigma^2`` the weighted residual variance, propagated to FWHMs by the delta method. It assumes
uncorrelated noise and a correct model, so it is a lower bound on real data (a blurred
scintillator correlates neighbouring pixels' noise).
"""


from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ..errors import ParameterError
from ..robust import robust_sigma
from .edge_config import EdgeConfig, load_edge_config
from .edge_images import EdgeImage, _Prepared, _prepare, normalise_edge_image
from .edge_model import DEFAULT_ESF_STEP_PX, _TAIL_FWHM_MIN_PX, _dot
from .edge_objective import _JointProblem
from .model import PSFModel

#: ``s / FWHM`` of a Gaussian written as the MTF ``exp(-(f s)^2)``.
_GAUSSIAN_SCALE_PER_FWHM = math.pi / (2.0 * math.sqrt(math.log(2.0)))

__all__ = ["DETECTOR_CORES", "DEFAULT_ESF_STEP_PX", "EdgeConfig", "EdgeImage", "fit_edges", "load_edge_config",
           "normalise_edge_image"]


def _level_bins(level: np.ndarray, n_bins: int = 8) -> np.ndarray:
    """Bin index of every pixel by its fitted ESF level (quantile bins): noise grows with the signal."""
    cuts = np.quantile(level, np.linspace(0.0, 1.0, n_bins + 1)[1:-1])
    return np.searchsorted(cuts, level)


def _local_sigma(level: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Robust residual sigma per pixel, estimated within bins of the fitted level."""
    bins = _level_bins(level)
    sigma = np.array([robust_sigma(residual[bins == b]) if np.any(bins == b) else np.inf
                      for b in range(bins.max() + 1)])
    return sigma[bins]


def _difference_noise(edge: _Prepared, residual: np.ndarray, level: np.ndarray) -> float:
    """RMS pixel noise from neighbour differences of the residual along the edge.

    Differences along the edge cancel the (smooth) model error; a robust sigma is taken per
    bin of the fitted level, because photon noise differs between the dark and bright sides,
    and the bins are combined as an RMS over pixels. Spatially correlated noise (a blurred
    scintillator) makes this an underestimate.
    """
    h, w = edge.shape
    res_img = np.full(edge.shape, np.nan)
    lev_img = np.full(edge.shape, np.nan)
    rr = np.rint(edge.y_px[edge.keep] + 0.5 * (h - 1)).astype(int)
    cc = np.rint(edge.x_px[edge.keep] + 0.5 * (w - 1)).astype(int)
    res_img[rr, cc] = residual
    lev_img[rr, cc] = level
    along_rows = abs(math.cos(edge.angle_rad)) >= abs(math.sin(edge.angle_rad))  # edge runs along rows
    if along_rows:
        diff, mean_level = res_img[1:, :] - res_img[:-1, :], 0.5 * (lev_img[1:, :] + lev_img[:-1, :])
    else:
        diff, mean_level = res_img[:, 1:] - res_img[:, :-1], 0.5 * (lev_img[:, 1:] + lev_img[:, :-1])
    ok = np.isfinite(diff)
    if ok.sum() < 16:
        return float("nan")
    sigma = _local_sigma(mean_level[ok], diff[ok]) / math.sqrt(2.0)
    return float(np.sqrt(np.mean(sigma ** 2)))


def _profiles(t: dict, values: np.ndarray, bin_px: float = 0.25, half_range_px: float = 48.0) -> dict:
    """Binned measured and fitted ESF (rescaled to 0..1) and their LSFs, for plotting."""
    d, model = t["d"], t["model"]
    low, high = t["low"], t["high"]
    half = min(half_range_px, float(np.abs(d).max()))
    edges = np.arange(-half, half + bin_px, bin_px)
    idx = np.digitize(d, edges) - 1
    ok = (idx >= 0) & (idx < edges.size - 1)
    counts = np.bincount(idx[ok], minlength=edges.size - 1)
    meas = np.bincount(idx[ok], values[ok], minlength=edges.size - 1)
    fit = np.bincount(idx[ok], model[ok], minlength=edges.size - 1)
    have = counts > 0
    centres = 0.5 * (edges[:-1] + edges[1:])[have]
    esf_meas = (meas[have] / counts[have] - low) / (high - low)
    esf_fit = (fit[have] / counts[have] - low) / (high - low)
    lsf_meas = np.gradient(esf_meas, centres) if centres.size > 2 else np.zeros_like(centres)
    lsf_fit = np.gradient(esf_fit, centres) if centres.size > 2 else np.zeros_like(centres)

    def rounded(a):
        return [float(f"{v:.6g}") for v in a]

    return {"distance_px": rounded(centres), "esf_measured": rounded(esf_meas), "esf_fitted": rounded(esf_fit),
            "lsf_measured": rounded(lsf_meas), "lsf_fitted": rounded(lsf_fit)}


#: Detector core families of the fit: the generalised MTF-defined core, or SABER's exponential power.
DETECTOR_CORES = ("generalised", "exponential_power")


def fit_edges(edges: Sequence[EdgeImage], pixel_pitch_mm: float, *, shape_power: float = 1.0,
              detector_core: str = "generalised", detector_tail: bool | None = None,
              fit_source: bool | None = None, tail_fwhm_max_px: float | None = None,
              esf_step_px: float = DEFAULT_ESF_STEP_PX, outlier_sigma: float | None = 5.0,
              weight_by_noise: bool = True, mask_impulses: bool = True, max_iterations: int = 2000,
              progress: Callable[[int, int], None] | None = None) -> PSFModel:
    """Fit the source + detector blur model jointly to several edge radiographs.

    Parameters
    ----------
    edges : sequence of EdgeImage
        One straight edge per image (or per ROI). For source and detector to be separated,
        at least two distinct ``ODD / SOD`` ratios; for both source axes, edges of both
        orientations (horizontal and vertical).
    pixel_pitch_mm : float
        Detector pixel pitch on the scintillator plane, mm (use 1.0 to work in pixels).
    shape_power : {1.0, 2.0}
        Exponential-power ``p`` of the focal spot and the detector tail (1 exponential as in
        SABER, 2 Gaussian), and of the detector core when ``detector_core="exponential_power"``.
    detector_core : {"generalised", "exponential_power"}
        The detector core: defined by its MTF ``(1 + u (f s)^q)^(-1/u)`` with scale, ``q`` and
        ``u`` fitted (stretched-exponential, Lorentzian-like and Gaussian-like detectors), or
        SABER's exponential-power profile of power ``shape_power`` (only its FWHM fitted).
    detector_tail : bool, optional
        Fit a long tail (exponential-power, FWHM >= 4 px) beside the core (weight ``1 - w``);
        False fixes ``w = 1``. Default with the generalised core: fitted without a tail first,
        then a score test (:func:`_tail_score_test`) adds the tail only when the residuals ask
        for one (a tail the data do not identify made the fit 2-4x slower and its weight
        arbitrary); with the exponential-power core: True.
    fit_source : bool, optional
        Fit the focal spot. Default: when the edges span two or more ``ODD / SOD`` ratios.
        When False the source is fixed to zero and the detector PSF holds the combined blur.
    tail_fwhm_max_px : float, optional
        Upper bound of the detector-tail FWHM in pixels (default 4 x the largest ROI side,
        at least 64 px). Sets the length of the analytic ESF grid.
    esf_step_px : float
        Spacing of the fine ESF grid, pixels (default 1/16).
    outlier_sigma : float or None
        After a first fit, mask pixels whose residual exceeds this many robust sigmas (estimated
        per bin of the fitted level) and refit; None disables.
    weight_by_noise : bool
        After a first (unweighted) fit, refit by weighted least squares with weights ``1 / sigma^2``
        from the residual sigma per bin of the fitted level (photon noise is larger on the bright
        side of an edge than under the plate); skipped for an edge whose sigmas differ by < 25 %.
    mask_impulses : bool
        Mask bright impulses (gamma hits) before fitting.
    max_iterations : int
        L-BFGS-B iteration limit per pass.
    progress : callable(done, total), optional
        Called after each optimiser iteration.

    Returns
    -------
    PSFModel
        With ``uncertainty`` (1-sigma, same units as each parameter; ``inf`` when a parameter is
        not identified) and ``fit_report``: ``residual_rms`` (normalised transmission units),
        ``noise_rms_estimate``, cost, iterations, per-edge geometry, levels and binned
        ``profile`` (measured/fitted ESF and LSF against distance in pixels).

    Raises
    ------
    ParameterError, InputError
        Bad parameters or unusable images (one line naming the image or parameter).
    """
    pitch = _check_fit_arguments(edges, pixel_pitch_mm, shape_power, esf_step_px)
    if detector_core not in DETECTOR_CORES:
        raise ParameterError(f"detector_core must be one of {', '.join(DETECTOR_CORES)}, got {detector_core!r}")
    generalised = detector_core == "generalised"
    auto_tail = detector_tail is None and generalised
    with_tail = (not generalised) if detector_tail is None else bool(detector_tail)
    prepared = [_prepare(e, i, mask_impulses) for i, e in enumerate(edges)]
    plan = _plan_fit(prepared, fit_source, tail_fwhm_max_px)
    theta, noise0 = _starting_point(prepared, plan, generalised, with_tail)

    def problem_for(fit_src: bool, tie: bool, tail: bool) -> _JointProblem:
        return _JointProblem(prepared, shape_power, fit_src, tie, plan.tail_fwhm_max_px, esf_step_px, noise0,
                             plan.core_fwhm_max_px, generalised_core=generalised, with_tail=tail)

    def optimise(problem: _JointProblem, start: np.ndarray, before: _OptimiserRun | None) -> _OptimiserRun:
        run = _optimise(problem, prepared, start, outlier_sigma=outlier_sigma, weight_by_noise=weight_by_noise,
                        max_iterations=max_iterations, progress=progress)
        if before is not None:
            run.iterations += before.iterations
            run.evaluations += before.evaluations
            run.n_rejected += before.n_rejected
        return run

    problem = problem_for(plan.fit_source, plan.tie, with_tail)
    run = optimise(problem, theta, None)
    tail_note = None
    if auto_tail:
        # Add the tail only when the data ask for it (score test at w = 1), then refit with it.
        tail_start, score = _tail_score_test(problem, problem_for(plan.fit_source, plan.tie, True), run.theta)
        tail_note = f"tail score {score:.3g} (threshold {_tail_score_threshold(problem):.3g})"
        if tail_start is not None:
            problem = problem_for(plan.fit_source, plan.tie, True)
            run = optimise(problem, tail_start, run)
    source_note = None
    if plan.fit_source and fit_source is None:
        source_note = _unidentified_source(problem, prepared, run.theta, plan)
        if source_note is not None:
            # The distances do not pin the focal spot down: refit without it (warm start), so
            # that the detector PSF holds the combined blur and no made-up spot is reported.
            plan.fit_source, plan.tie = False, False
            start = np.delete(run.theta, range(1 if problem.tie else 2))    # the source widths come first
            problem = problem_for(False, False, problem.with_tail)
            run = optimise(problem, start, run)
    model = _fitted_model(problem, prepared, run, plan, pitch, shape_power, source_note)
    if tail_note is not None:
        model.fit_report["tail_selection"] = tail_note
    return model


#: Candidate tail widths of the score test, as multiples of the core's scale (and >= 4 px).
_TAIL_CANDIDATE_MULTIPLES = (3.0, 6.0, 12.0, 24.0, 48.0)


def _tail_score_threshold(problem: _JointProblem) -> float:
    """Score-test threshold: ``2 ln(N)`` (BIC-like penalty of two more parameters, halved
    because the test is one-sided)."""
    return 2.0 * math.log(max(problem.n_total_pixels, 2))


def _tail_score_test(no_tail: _JointProblem, with_tail: _JointProblem, theta: np.ndarray):
    """Does a tail improve the tail-free fit? Rao score test of ``w = 1`` for a few tail widths.

    At the tail-free optimum the derivative of the weighted cost in ``w`` for a tail of width
    ``T`` is ``g = sum W r c`` with ``c = contrast (E_core - E_tail)``; its Fisher information
    is ``I = sum W c^2 / sigma^2``. ``g^2 / (sigma^2 I)`` is chi-square(1) when no tail is
    present; the tail is added when the best width's statistic exceeds
    :func:`_tail_score_threshold` with the sign of a cost that falls as ``w`` falls. Cheap
    (one ESF per edge and width), so the tail fit runs only when the data ask for it.

    Returns ``(start, score)``: the starting parameters of the tail fit or None, and the largest score.
    """
    fwhm, local = no_tail.unpack(theta)
    lo, hi = with_tail.bounds()[with_tail.global_free.index("tail")]
    best, best_width = 0.0, None
    for multiple in _TAIL_CANDIDATE_MULTIPLES:
        width = float(np.clip(multiple * fwhm["core"], math.exp(lo), math.exp(hi)))
        trial = dict(fwhm, tail=width, w=1.0)
        g = info = rss = 0.0
        n = 0
        for j in range(len(no_tail.edges)):
            t = with_tail._edge_terms(j, trial, local[j], False)
            r = t["values"] - t["model"]
            c = (t["high"] - t["low"]) * (t["parts"]["core"]["esf"] - t["parts"]["tail"]["esf"])
            g += _dot(t["pixel_weight"] * r, c)
            info += _dot(t["pixel_weight"] * c, c)
            rss += _dot(t["pixel_weight"] * r, r)
            n += r.size
        sigma2 = rss / max(n - theta.size, 1)
        # Lowering w moves the model by -c dw: it helps when the residual correlates with -c.
        score = (g * g) / (sigma2 * info) if info > 0 and g < 0 else 0.0
        if score > best:
            best, best_width = score, width
    if best_width is None or best <= _tail_score_threshold(no_tail):
        return None, best
    start = np.concatenate([theta[:no_tail.n_global], [math.log(best_width), 0.97], theta[no_tail.n_global:]])
    return start, best


#: The focal spot counts as identified when every fitted source width is known to better than
#: this fraction of itself (1 sigma, Fisher information).
SOURCE_MAX_RELATIVE_UNCERTAINTY = 0.5


def _unidentified_source(problem: _JointProblem, prepared: list[_Prepared], theta: np.ndarray,
                         plan: _FitPlan) -> str | None:
    """None when the fitted focal spot is identified; otherwise the reason, for the report.

    Identified means every fitted source width has a 1-sigma uncertainty below
    :data:`SOURCE_MAX_RELATIVE_UNCERTAINTY` of its value. Distances too close together (or
    too small a magnification for the pixel size) leave the spot's width free along a valley
    of the cost: the fit then returns some width with an uncertainty as large as itself.
    """
    residuals, jtj, terms = problem.residuals_and_jacobian_normal(theta)
    all_res = np.concatenate(residuals)
    weights = np.concatenate([t["pixel_weight"] for t in terms])
    sigma2 = _dot(weights * all_res, all_res) / max(all_res.size - theta.size - 2 * len(prepared), 1)
    cov = _inverse_fisher(jtj) * sigma2
    worst = 0.0
    for name in ("sx", "sy"):
        if name in problem.global_free:
            k = problem.global_free.index(name)
            relative = math.sqrt(cov[k, k]) if np.isfinite(cov[k, k]) and cov[k, k] >= 0 else float("inf")
            worst = max(worst, relative)    # sigma of log FWHM = relative sigma of the FWHM
    if worst < SOURCE_MAX_RELATIVE_UNCERTAINTY:
        return None
    ratios = ", ".join(f"{r:.3g}" for r in np.unique(np.round(plan.ratios, 4)))
    spread = f"{worst:.0%}" if worst <= 1.0 else "more than 100 %"
    return (f"focal spot not identified by the object distances (ODD/SOD {ratios}): its fitted width was "
            f"uncertain by {spread}; the detector PSF holds the combined blur")


# ---------------------------------------------------------------------------------------------
# Phases of the fit
# ---------------------------------------------------------------------------------------------
@dataclass
class _FitPlan:
    """What the edges allow the fit to identify, and the bounds of the detector widths."""

    fit_source: bool
    tie: bool                   # one source width for both axes (edges of one orientation only)
    ratios: np.ndarray          # ODD / SOD of every edge
    tail_fwhm_max_px: float
    core_fwhm_max_px: float


@dataclass
class _OptimiserRun:
    """The optimiser's last result and the bookkeeping of all passes."""

    result: optimize.OptimizeResult
    theta: np.ndarray
    iterations: int
    evaluations: int
    n_rejected: int


def _check_fit_arguments(edges, pixel_pitch_mm, shape_power, esf_step_px) -> float:
    """Refuse unusable arguments (one line each); return the pixel pitch as a float."""
    if not edges:
        raise ParameterError("fit_edges: no edge images given")
    pitch = float(pixel_pitch_mm)
    if not (math.isfinite(pitch) and pitch > 0):
        raise ParameterError(f"pixel_pitch_mm must be finite and > 0, got {pixel_pitch_mm!r}")
    if shape_power not in (1.0, 2.0):
        raise ParameterError(f"shape_power must be 1 or 2 for edge fitting, got {shape_power!r}")
    if not 1e-3 <= esf_step_px <= 0.5:
        raise ParameterError(f"esf_step_px must be in [0.001, 0.5], got {esf_step_px!r}")
    return pitch


def _plan_fit(prepared: list[_Prepared], fit_source: bool | None, tail_fwhm_max_px: float | None) -> _FitPlan:
    """Whether the source is separable (two or more ODD/SOD ratios), whether its two axes are
    (edges of both orientations), and the largest core and tail widths allowed."""
    ratios = np.array([p.magnification_m1 for p in prepared])
    distinct = np.unique(np.round(ratios, 6))
    if fit_source is None:
        fit_source = distinct.size >= 2 and ratios.max() > 0
    elif fit_source and (distinct.size < 2 or ratios.max() <= 0):
        raise ParameterError("fit_source needs edges at two or more different ODD/SOD ratios (object heights)")
    normals = np.array([[abs(math.cos(p.angle_rad)), abs(math.sin(p.angle_rad))] for p in prepared])
    both_orientations = bool((normals[:, 0] > 0.7).any() and (normals[:, 1] > 0.7).any())
    largest_side = max(max(p.shape) for p in prepared)
    if tail_fwhm_max_px is None:
        tail_fwhm_max_px = max(4.0 * largest_side, 64.0)
    if not tail_fwhm_max_px > 2 * _TAIL_FWHM_MIN_PX:
        raise ParameterError(f"tail_fwhm_max_px must be > {2 * _TAIL_FWHM_MIN_PX:g}, got {tail_fwhm_max_px!r}")
    return _FitPlan(fit_source=bool(fit_source), tie=bool(fit_source and not both_orientations), ratios=ratios,
                    tail_fwhm_max_px=tail_fwhm_max_px,
                    core_fwhm_max_px=min(max(0.125 * largest_side, 16.0), 128.0))


def _starting_point(prepared: list[_Prepared], plan: _FitPlan, generalised: bool = False,
                    with_tail: bool = True) -> tuple[np.ndarray, float]:
    """Initial parameters (blur from the 10-90 % rise of the edges, split between core and
    source) and the initial noise scale."""
    noise0 = np.median([robust_sigma(np.diff(p.values)) / math.sqrt(2) for p in prepared])
    noise0 = float(noise0) if noise0 > 0 else 0.01
    rise = _initial_rise_px(prepared)
    core0 = min(max(0.3, 0.6 * rise), 0.5 * plan.core_fwhm_max_px)
    theta0 = []
    if plan.fit_source:
        src0 = min(max(0.3 * rise, 1e-2), 0.5 * plan.core_fwhm_max_px) / plan.ratios.max()
        theta0 += [math.log(src0)] if plan.tie else [math.log(src0), math.log(src0 * 1.1)]
    if generalised:
        # Scale of a Gaussian MTF exp(-(f s)^2) of this FWHM (s = pi FWHM / (2 sqrt(ln 2))); start
        # half-way between the Gaussian and the Lorentzian (q = 2, u = 0.5).
        theta0 += [math.log(core0 * _GAUSSIAN_SCALE_PER_FWHM), 2.0, 0.5]
    else:
        theta0 += [math.log(core0)]
    if with_tail:
        theta0 += [math.log(min(max(10.0 * core0, 8.0), 0.5 * plan.tail_fwhm_max_px)), 0.95]
    for p in prepared:
        theta0 += [p.offset_px, 0.0]
    return np.asarray(theta0, float), noise0


def _optimise(problem: _JointProblem, prepared: list[_Prepared], theta: np.ndarray, *,
              outlier_sigma: float | None, weight_by_noise: bool, max_iterations: int,
              progress: Callable[[int, int], None] | None) -> _OptimiserRun:
    """A first unweighted fit, then (when asked and when it changes anything) a refit with the
    fitted noise model and the outliers masked."""
    total_iterations, evaluations, n_rejected = 0, 0, 0
    counter = {"it": 0}

    def callback(_xk):
        counter["it"] += 1
        if progress is not None:
            progress(min(counter["it"], max_iterations), max_iterations)

    passes = 2 if (outlier_sigma or weight_by_noise) else 1
    for pass_index in range(passes):
        result = _minimise(problem, prepared, theta, 1e-12, max_iterations, callback)
        theta = result.x
        total_iterations += int(result.nit)
        evaluations += int(result.nfev)
        if pass_index + 1 < passes:
            rejected, changed = _reweight_and_reject(problem, prepared, theta, outlier_sigma, weight_by_noise)
            n_rejected += rejected
            if not changed:
                break
    return _OptimiserRun(result=result, theta=theta, iterations=total_iterations, evaluations=evaluations,
                         n_rejected=n_rejected)


def _minimise(problem: _JointProblem, prepared: list[_Prepared], start: np.ndarray, ftol: float,
              max_iterations: int, callback) -> optimize.OptimizeResult:
    """L-BFGS-B in diagonally preconditioned coordinates ``z = theta * D``.

    ``D`` is the square root of the Gauss-Newton Hessian diagonal at the start, so every
    coordinate has unit curvature; the gradient is rescaled exactly (``dC/dz = dC/dtheta / D``).
    """
    problem.n_total_pixels = sum(int(p.keep.sum()) for p in prepared)
    _, jtj, _ = problem.residuals_and_jacobian_normal(start)
    diag = np.diag(jtj)[:start.size] / (problem.n_total_pixels * problem.noise_scale ** 2)
    scale = np.sqrt(np.where(diag > 0, diag, 1.0))

    def scaled(z):
        cost, grad = problem.cost_and_gradient(z / scale)
        return cost, grad / scale

    bounds = [(None if lo is None else lo * sc, None if hi is None else hi * sc)
              for (lo, hi), sc in zip(problem.bounds(), scale)]
    res = optimize.minimize(scaled, start * scale, jac=True, method="L-BFGS-B", bounds=bounds,
                            callback=callback,
                            options={"maxiter": max_iterations, "ftol": ftol, "gtol": 1e-9, "maxcor": 20})
    res.x = res.x / scale
    return res


def _reweight_and_reject(problem: _JointProblem, prepared: list[_Prepared], theta: np.ndarray,
                         outlier_sigma: float | None, weight_by_noise: bool) -> tuple[int, bool]:
    """Noise model from the first pass (robust residual sigma per bin of the fitted level):
    weights ``1 / sigma^2`` and outlier masks, set on ``prepared`` in place.

    Returns the number of pixels masked and whether anything changed.
    """
    fwhm, local = problem.unpack(theta)
    changed, n_rejected = False, 0
    for j, p in enumerate(prepared):
        t = problem._edge_terms(j, fwhm, local[j], False)
        r = t["model"] - p.values[p.keep]
        sigma = _local_sigma(t["esf"], r)
        # Weight only when the noise really differs across levels (> 25 %): a near-uniform
        # noise model would just cost a second optimisation for nothing.
        if (weight_by_noise and np.all(np.isfinite(sigma)) and np.all(sigma > 0)
                and sigma.max() > 1.25 * sigma.min()):
            weight = 1.0 / sigma ** 2
            p.weight = np.ones(p.values.size)
            p.weight[p.keep] = weight / weight.mean()
            changed = True
        if outlier_sigma:
            full = np.zeros(p.values.size)
            full[p.keep] = np.abs(r) / sigma
            bad = p.keep & (full > outlier_sigma)
            if bad.any():
                p.keep = p.keep & ~bad
                n_rejected += int(bad.sum())
                changed = True
    return n_rejected, changed


def _fitted_model(problem: _JointProblem, prepared: list[_Prepared], run: _OptimiserRun, plan: _FitPlan,
                  pitch: float, shape_power: float, source_note: str | None = None) -> PSFModel:
    """The PSF model at the optimum, with its uncertainties and the fit report."""
    theta = run.theta
    residuals, jtj, terms = problem.residuals_and_jacobian_normal(theta)
    all_res = np.concatenate(residuals)
    all_weights = np.concatenate([t["pixel_weight"] for t in terms])
    n_obs, n_par = all_res.size, theta.size + 2 * len(prepared)
    rss = _dot(all_res, all_res)
    sigma2 = _dot(all_weights * all_res, all_res) / max(n_obs - n_par, 1)   # per unit weight
    cov = _inverse_fisher(jtj) * sigma2
    fwhm, local = problem.unpack(theta)
    uncertainty = _uncertainties(problem, fwhm, cov, pitch, plan.tie)
    edge_reports = [_edge_report(p, r, t, local[j]) for j, (p, r, t) in enumerate(zip(prepared, residuals, terms))]
    result = run.result
    report = {
        "residual_rms": float(np.sqrt(rss / n_obs)),
        "noise_rms_estimate": float(np.median([e["noise_rms_estimate"] for e in edge_reports])),
        "cost": float(result.fun), "iterations": run.iterations, "evaluations": run.evaluations,
        "converged": bool(result.success), "optimizer_message": str(result.message),
        "n_images": len(prepared), "n_pixels": int(n_obs), "n_outliers_masked": run.n_rejected,
        "noise_weighted": bool(any(np.ptp(p.weight) > 0 for p in prepared)),
        "source_fitted": bool(plan.fit_source), "source_axes_tied": bool(plan.tie),
        "shape_power": shape_power, "tail_fwhm_max_px": float(plan.tail_fwhm_max_px),
        "edges": edge_reports,
    }
    if source_note is not None:
        report["note"] = source_note
    elif not plan.fit_source:
        report["note"] = ("single object-to-detector ratio: source blur not separable, "
                          "the detector PSF holds the combined blur")
    core = ({"detector_fwhm_core_mm": 0.0, "detector_core_mtf_scale_mm": fwhm["core"] * pitch,
             "detector_core_mtf_power": fwhm["power"], "detector_core_mtf_linnik": fwhm["linnik"]}
            if problem.generalised else {"detector_fwhm_core_mm": fwhm["core"] * pitch})
    model = PSFModel(pixel_pitch_mm=pitch,
                     source_fwhm_x_mm=fwhm["sx"] * pitch if plan.fit_source else 0.0,
                     source_fwhm_y_mm=fwhm["sy"] * pitch if plan.fit_source else 0.0,
                     detector_fwhm_tail_mm=fwhm["tail"] * pitch if problem.with_tail else 0.0,
                     detector_weight_core=float(fwhm["w"]), shape_power=float(shape_power),
                     source_fitted=bool(plan.fit_source), uncertainty=uncertainty, fit_report=report, **core)
    report["detector_core"] = "generalised" if problem.generalised else "exponential_power"
    report["detector_mtf50_cy_per_mm"] = model.mtf50_cy_per_mm()
    report["detector_lsf_fwhm_mm"] = model.detector_lsf_fwhm_mm()
    return model


def _uncertainties(problem: _JointProblem, fwhm: dict, cov: np.ndarray, pitch: float, tie: bool) -> dict:
    """1-sigma uncertainties of the model's parameters (delta method on the log FWHMs)."""
    def sd(name):
        if name not in problem.global_free:
            return None
        k = problem.global_free.index(name)
        return math.sqrt(cov[k, k]) if np.isfinite(cov[k, k]) and cov[k, k] >= 0 else float("inf")

    uncertainty = {}
    core_key = "detector_core_mtf_scale_mm" if problem.generalised else "detector_fwhm_core_mm"
    for key, short in (("source_fwhm_x_mm", "sx"), ("source_fwhm_y_mm", "sy" if not tie else "sx"),
                       (core_key, "core"), ("detector_fwhm_tail_mm", "tail")):
        s = sd(short)
        if s is not None:
            uncertainty[key] = fwhm[short] * pitch * s   # delta method on log FWHM
    for key, short in (("detector_weight_core", "w"), ("detector_core_mtf_power", "power"),
                       ("detector_core_mtf_linnik", "linnik")):
        if sd(short) is not None:
            uncertainty[key] = sd(short)
    return uncertainty


def _edge_report(p: _Prepared, residual: np.ndarray, t: dict, local: np.ndarray) -> dict:
    """Geometry, levels, residual and noise of one edge, and its binned profiles."""
    return {
        "name": p.name, "source_to_object_mm": p.sod_mm, "source_to_detector_mm": p.sdd_mm,
        "odd_over_sod": p.magnification_m1,
        "edge_normal_angle_deg": math.degrees(t["phi"]),
        "edge_offset_px": float(local[0]), "low_level": float(t["low"]),
        "high_level": float(t["high"]),
        "residual_rms": float(np.sqrt(np.mean(residual ** 2))),
        "noise_rms_estimate": _difference_noise(p, residual, t["esf"]),
        "n_pixels": int(p.keep.sum()), "n_impulses_masked": p.n_impulses_masked,
        "profile": _profiles(t, p.values[p.keep]),
    }


def _inverse_fisher(jtj: np.ndarray) -> np.ndarray:
    """Inverse of ``J^T J`` with unidentified directions reported as infinite variance."""
    diag = np.sqrt(np.clip(np.diag(jtj), 0, None))
    scale = np.where(diag > 0, diag, 1.0)
    normed = jtj / np.outer(scale, scale)
    try:
        eigval, eigvec = np.linalg.eigh(normed)
    except np.linalg.LinAlgError:
        return np.full_like(jtj, np.inf)
    tiny = eigval < 1e-10 * max(eigval.max(), 1e-300)
    inv_eig = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, eigval))
    cov = (eigvec * inv_eig) @ eigvec.T / np.outer(scale, scale)
    if tiny.any():
        # Parameters loading on a null direction are not identified.
        loads = np.abs(eigvec[:, tiny]).max(axis=1) > 1e-3
        cov[loads, loads] = np.inf
    cov[diag == 0, diag == 0] = np.inf
    return cov


def _initial_rise_px(prepared: list[_Prepared]) -> float:
    """Median 10-90 % rise distance of the binned edge profiles (pixels)."""
    rises = []
    for p in prepared:
        d = p.x_px * math.cos(p.angle_rad) + p.y_px * math.sin(p.angle_rad) - p.offset_px
        near = np.abs(d) < 40
        if near.sum() < 32:
            continue
        order = np.argsort(d[near])
        dd, vv = d[near][order], p.values[near][order]
        bins = np.arange(-40, 40.5, 0.5)
        idx = np.digitize(dd, bins)
        prof = np.array([np.median(vv[idx == k]) if np.any(idx == k) else np.nan for k in range(1, bins.size)])
        centres = bins[:-1] + 0.25
        ok = np.isfinite(prof)
        if ok.sum() < 8:
            continue
        level = (prof[ok] - p.low) / (p.high - p.low)
        level = np.maximum.accumulate(np.clip(level, 0, 1))
        x10 = np.interp(0.1, level, centres[ok])
        x90 = np.interp(0.9, level, centres[ok])
        rises.append(max(x90 - x10, 0.5))
    return float(np.median(rises)) if rises else 2.0
