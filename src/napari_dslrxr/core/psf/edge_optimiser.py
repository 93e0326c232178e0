"""The optimiser of an edge fit: preconditioned L-BFGS-B passes, then the noise model (weights
per level bin) and the outlier masks that the second pass uses."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ..progress import Steps
from ..robust import robust_sigma
from .edge_images import _Prepared
from .edge_objective import _JointProblem


@dataclass
class _OptimiserRun:
    """The optimiser's last result and the bookkeeping of all passes."""

    result: optimize.OptimizeResult
    theta: np.ndarray
    iterations: int
    evaluations: int
    n_rejected: int


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


def _optimise(problem: _JointProblem, prepared: list[_Prepared], theta: np.ndarray, *,
              outlier_sigma: float | None, weight_by_noise: bool, max_iterations: int,
              progress: Callable[[int, int], None] | None) -> _OptimiserRun:
    """A first unweighted fit, then (when asked and when it changes anything) a refit with the
    fitted noise model and the outliers masked."""
    total_iterations, evaluations, n_rejected = 0, 0, 0
    steps = Steps(progress, max_iterations)

    def callback(_xk):
        steps.advance()

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
