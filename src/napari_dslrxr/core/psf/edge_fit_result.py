"""The result of an edge fit: the PSF model at the optimum, its uncertainties (inverse Fisher
information, delta method) and the fit report (per-edge noise, levels and binned profiles)."""

from __future__ import annotations

import math

import numpy as np

from .edge_fit_plan import _FitPlan
from .edge_images import _Prepared
from .edge_model import _dot
from .edge_objective import _JointProblem
from .edge_optimiser import _local_sigma, _OptimiserRun
from .model import PSFModel


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


def _residual_covariance(problem: _JointProblem, prepared: list[_Prepared], theta: np.ndarray):
    """Residuals, per-edge terms, all residuals joined, and ``cov = sigma^2 (J^T W J)^-1`` at ``theta``.

    ``sigma^2`` is the weighted residual variance per unit weight; each edge's two levels count
    as fitted parameters.
    """
    residuals, jtj, terms = problem.residuals_and_jacobian_normal(theta)
    all_res = np.concatenate(residuals)
    all_weights = np.concatenate([t["pixel_weight"] for t in terms])
    n_par = theta.size + 2 * len(prepared)
    sigma2 = _dot(all_weights * all_res, all_res) / max(all_res.size - n_par, 1)
    return residuals, terms, all_res, _inverse_fisher(jtj) * sigma2


def _log_sigma(cov: np.ndarray, k: int) -> float:
    """1-sigma of free parameter ``k`` (of its log for a FWHM); inf when not determined."""
    return math.sqrt(cov[k, k]) if np.isfinite(cov[k, k]) and cov[k, k] >= 0 else float("inf")


def _fitted_model(problem: _JointProblem, prepared: list[_Prepared], run: _OptimiserRun, plan: _FitPlan,
                  pitch: float, shape_power: float, source_note: str | None = None) -> PSFModel:
    """The PSF model at the optimum, with its uncertainties and the fit report."""
    theta = run.theta
    residuals, terms, all_res, cov = _residual_covariance(problem, prepared, theta)
    n_obs = all_res.size
    rss = _dot(all_res, all_res)
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
        return _log_sigma(cov, problem.global_free.index(name))

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
