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

import numpy as np

from ..errors import ParameterError
from .edge_config import EdgeConfig, load_edge_config
from .edge_fit_plan import _check_fit_arguments, _FitPlan, _plan_fit, _starting_point
from .edge_fit_result import _fitted_model, _log_sigma, _residual_covariance
from .edge_images import EdgeImage, _Prepared, _prepare, normalise_edge_image
from .edge_model import DEFAULT_ESF_STEP_PX, _dot
from .edge_objective import _JointProblem
from .edge_optimiser import _OptimiserRun, _optimise
from .model import PSFModel

__all__ = ["DETECTOR_CORES", "DEFAULT_ESF_STEP_PX", "EdgeConfig", "EdgeImage", "fit_edges", "load_edge_config",
           "normalise_edge_image"]


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
    cov = _residual_covariance(problem, prepared, theta)[3]
    worst = 0.0
    for name in ("sx", "sy"):
        if name in problem.global_free:
            relative = _log_sigma(cov, problem.global_free.index(name))
            worst = max(worst, relative)    # sigma of log FWHM = relative sigma of the FWHM
    if worst < SOURCE_MAX_RELATIVE_UNCERTAINTY:
        return None
    ratios = ", ".join(f"{r:.3g}" for r in np.unique(np.round(plan.ratios, 4)))
    spread = f"{worst:.0%}" if worst <= 1.0 else "more than 100 %"
    return (f"focal spot not identified by the object distances (ODD/SOD {ratios}): its fitted width was "
            f"uncertain by {spread}; the detector PSF holds the combined blur")
