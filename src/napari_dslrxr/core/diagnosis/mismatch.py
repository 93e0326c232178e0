"""Mismatch diagnosis: locate, name, model and refit what the base model leaves out.

Algorithm (``docs/diagnosis.md``; background in ``docs/algorithms/diagnosis.md``), on a single-channel
linear recording:

1. **Base fit.** Offset, gain, effective attenuation, detector blur width and the registration
   (sub-pixel shift, magnification error, small rotation) are fitted by least squares on the
   prewhitened residual; the focal-spot width stays at the scene value (with one object height
   only the combined Gaussian width is identifiable). Impulsive pulses are masked.
2. **Noise.** ``v(mu) = K (mu - b) + s_r^2`` and the noise power spectrum come from the
   repeats when given, else from the residual's variogram over flat pixels
   (:mod:`.noise`); the residual is prewhitened with it, so correlated camera noise
   is not read as physics. The noise model is re-estimated after every accepted term.
3. **Locate.** Normalised residual maps, tiles and profiles along rows, columns, radius, edge
   distance, thickness and intensity.
4. **Rank.** Projected Rao score test of each library term (max over its shape grid).
5. **Compare, then accept.** The best candidates by score are each refitted jointly with every
   parameter, inside the bounds the scene allows (:func:`.terms.physical_bounds`);
   the one with the largest refitted ``ΔBIC = Δχ² - k ln n`` is accepted if ``ΔBIC > 10``, the
   held-out χ² (checkerboard blocks) improves, and a generic smooth surface does not explain
   the same mismatch better. The runner-up is reported; when it is within ``ambiguity_bic``
   the pair is declared ambiguous, with the acquisition that would separate them. Parameters
   at a bound are flagged ("at bound: not an estimate").
6. **Stop** when no candidate is accepted; then the structure tests of
   :mod:`.structure` decide whether anything is left ("unexplained", with signature
   and location).

Large recordings are block-averaged (``binning``; "auto" keeps the blur at least one binned
pixel); the transmission (and part of the blur, against aliasing) is computed on the full grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import InputError, ParameterError
from ..simulation.physics_terms import LIBRARY, ChainGrid, PhysicsTerm, get_term
from ..simulation.simulator import ChainModel, Scene, block_mean
from . import noise as noise_mod
from .structure import flagged_regions, structure_tests
from .terms import GENERIC_COMPETITORS, GENERIC_SIGNATURE, REGISTRATION, physical_bounds, probe_params

BASE_FREE = ("offset_dn", "gain_dn", "mu_per_mm", "detector_sigma_mm")
N_REGISTRATION = len(REGISTRATION)


@dataclass
class DiagnosisOptions:
    """Settings of :func:`diagnose`.

    Parameters
    ----------
    accept_delta_bic : float
        Minimum ΔBIC to accept a term (10 = "very strong", Kass & Raftery).
    max_terms : int
        At most this many terms are added.
    tile_px : int
        Tile size (pixels of the fitted grid) for the locate step.
    heldout_block_px : int
        Checkerboard block size for the held-out check (larger than the correlation length).
    max_fit_size_px : int
        With automatic binning, recordings larger than this along an axis are block-averaged,
        as long as the blur stays at least one binned pixel.
    candidates : tuple of str or None
        Library terms to consider (default: all).
    confusable_correlation : float
        Canonical correlation above which two candidates are flagged as confusable.
    compare_top : int
        Candidates (best by score) refitted and compared per round.
    ambiguity_bic : float
        A runner-up whose refitted ΔBIC is within this of the winner's makes the pair ambiguous.
    max_nfev : int
        Function-evaluation limit per least-squares fit.
    binning : int or None
        Force this block-averaging factor (default: automatic, see :func:`auto_binning`).
    pre_blur_fraction : float
        With a supersampled object or a binned fit, this fraction of the starting blur width is
        applied on the fine grid before block-averaging (avoids aliasing of sharp edges); the
        fitted width cannot go below it.
    fixed_offset_dn : float or None
        Hold the camera offset at this value (from a dark frame: the acquisition that separates
        a uniform glare floor from the black level; docs/algorithms/diagnosis.md, section
        'Identifiability'); default: fitted.
    noise_model_binned : (float, float) or None
        ``(K, c)`` with ``v(mu) = K mu + c`` (absolute DN) for the *binned* recording, e.g. from
        repeated frames (:func:`noise_model_from_repeats`); default: estimated from the residual.
    noise_sample_binned : ndarray or None
        A pure noise field with the binned recording's noise (e.g. the halved even/odd
        difference of repeats, binned): gives the noise power spectrum directly.
    registration : bool
        Fit shift, scale and rotation in the base model.
    """

    accept_delta_bic: float = 10.0
    max_terms: int = field(default=4, metadata={
        "help": "at most this many effects are added to the scene model", "unit": "terms", "min": 1, "max": 10})
    tile_px: int = 32
    heldout_block_px: int = 32
    max_fit_size_px: int = 512
    candidates: tuple[str, ...] | None = None
    confusable_correlation: float = 0.9
    compare_top: int = 3
    ambiguity_bic: float = 6.0
    max_nfev: int = 40
    binning: int | None = None
    noise_model_binned: tuple[float, float] | None = None
    noise_sample_binned: np.ndarray | None = None
    fixed_offset_dn: float | None = None
    pre_blur_fraction: float = 0.6
    registration: bool = True


@dataclass
class AddedTerm:
    """A term the diagnosis accepted."""

    effect: str
    params: dict[str, float]
    uncertainty: dict[str, float]
    delta_bic: float
    chi2_per_dof: float
    score: float
    likelihood_ratio: float
    heldout_gain: float
    confusable_with: list[tuple[str, float]] = field(default_factory=list)
    runner_up: str | None = None
    runner_up_delta_bic: float | None = None
    ambiguous: bool = False
    separating: str = ""
    at_bound: list[str] = field(default_factory=list)


@dataclass
class DiagnosisResult:
    """Everything the diagnosis found; :meth:`to_json` gives the ``diagnosis.json`` content."""

    base_chi2_per_dof: float
    base_bic: float
    regions: list[list[int]]
    added: list[AddedTerm]
    final_chi2_per_dof: float
    unexplained: bool
    unexplained_regions: list[list[int]]
    noise_poisson_gain_dn: float
    noise_read_dn: float
    base_params: dict[str, float]
    final_base_params: dict[str, float]
    z_base: np.ndarray
    z_final: np.ndarray
    mask: np.ndarray
    profiles_base: dict
    profiles_final: dict
    rankings: list[list[dict]]
    binning: int
    n_pixels: int
    smooth_delta_bic: float
    message: str
    registration: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)
    structure: dict = field(default_factory=dict)
    signatures: list[str] = field(default_factory=list)
    comparisons: list[list[dict]] = field(default_factory=list)

    def to_json(self) -> dict:
        """The ``diagnosis.json`` content."""
        def term_json(a: AddedTerm) -> dict:
            out = {"effect": a.effect,
                   "params": {k: round(v, 7) for k, v in a.params.items()},
                   "uncertainty": {k: round(v, 7) for k, v in a.uncertainty.items()},
                   "delta_bic": round(a.delta_bic, 2), "chi2_per_dof": round(a.chi2_per_dof, 5),
                   "runner_up": a.runner_up,
                   "runner_up_delta_bic": None if a.runner_up_delta_bic is None else round(a.runner_up_delta_bic, 2),
                   "ambiguous": a.ambiguous}
            if a.ambiguous:
                out["separating_acquisition"] = a.separating
            if a.at_bound:
                out["at_bound"] = {k: "at bound: not an estimate" for k in a.at_bound}
            return out

        return {
            "base": {"chi2_per_dof": round(self.base_chi2_per_dof, 5), "bic": round(self.base_bic, 2)},
            "registration": {k: round(v, 6) for k, v in self.registration.items()},
            "noise": self.noise,
            "mismatch": {"regions": self.regions},
            "added": [term_json(a) for a in self.added],
            "final": {"chi2_per_dof": round(self.final_chi2_per_dof, 5)},
            "unexplained": bool(self.unexplained),
            "unexplained_signatures": self.signatures,
        }

    def details(self) -> dict:
        """Supporting numbers (noise model, rankings, comparisons, structure tests)."""
        return {
            "noise": {"poisson_gain_dn": self.noise_poisson_gain_dn, "read_noise_dn": self.noise_read_dn,
                      **self.noise},
            "base_params": self.base_params, "final_base_params": self.final_base_params,
            "binning": self.binning, "n_pixels": self.n_pixels,
            "added": [{"effect": a.effect, "score": a.score, "likelihood_ratio": a.likelihood_ratio,
                       "heldout_gain": a.heldout_gain,
                       "confusable_with": [[n, round(c, 4)] for n, c in a.confusable_with]}
                      for a in self.added],
            "rankings": self.rankings, "comparisons": self.comparisons,
            "unexplained_regions": self.unexplained_regions,
            "structure_tests": self.structure.get("tests", {}),
            "smooth_term_delta_bic": self.smooth_delta_bic, "message": self.message,
        }


# --------------------------------------------------------------------------- parameter layout


@dataclass
class _Layout:
    """Free parameters: base names plus (term, param) pairs, with bounds and FD steps.

    ``terms`` starts with the registration terms (part of the base model), then library terms.
    """

    base_fixed: dict[str, float]
    terms: list[PhysicsTerm]
    names: list[tuple[str, str]]
    lower: np.ndarray
    upper: np.ndarray
    steps: np.ndarray
    free_base: tuple[str, ...] = BASE_FREE

    @classmethod
    def build(cls, base: dict[str, float], terms: list[PhysicsTerm], grid: ChainGrid,
              free_base: tuple[str, ...] = BASE_FREE) -> "_Layout":
        names, lo, hi, st = [], [], [], []
        for key in free_base:
            names.append(("base", key))
            value = abs(base[key])
            if key == "offset_dn":
                lo.append(-np.inf), hi.append(np.inf), st.append(0.5)
            elif key == "detector_sigma_mm":
                lo.append(1e-5), hi.append(np.inf), st.append(max(1e-4, 1e-3 * value))
            else:
                lo.append(1e-9), hi.append(np.inf), st.append(max(1e-8, 1e-4 * value))
        for term in terms:
            bounds = physical_bounds(term, grid)
            for spec in term.params:
                names.append((term.name, spec.name))
                low, high = bounds.get(spec.name, spec.prior)
                lo.append(low), hi.append(high), st.append(spec.step)
        layout = cls(dict(base), list(terms), names, np.array(lo, float), np.array(hi, float),
                     np.array(st, float))
        layout.free_base = tuple(free_base)
        return layout

    def unpack(self, x: np.ndarray) -> tuple[dict, list[tuple[PhysicsTerm, dict]]]:
        base = dict(self.base_fixed)
        per_term: dict[str, dict] = {t.name: {} for t in self.terms}
        for (owner, key), value in zip(self.names, x):
            if owner == "base":
                base[key] = float(value)
            else:
                per_term[owner][key] = float(value)
        return base, [(t, per_term[t.name]) for t in self.terms]

    def pack(self, base: dict, term_params: dict[str, dict]) -> np.ndarray:
        return np.array([base[k] if o == "base" else term_params[o][k] for o, k in self.names])

    def index(self, owner: str, key: str) -> int:
        return self.names.index((owner, key))


# --------------------------------------------------------------------------- locate


def _binned_profile(values: np.ndarray, z: np.ndarray, edges: np.ndarray) -> dict:
    which = np.searchsorted(edges, values, side="right") - 1
    centres, means, zscores, counts = [], [], [], []
    for b in range(len(edges) - 1):
        sel = which == b
        n = int(sel.sum())
        if n < 10:
            continue
        centres.append(float(values[sel].mean()))  # where the bin's pixels are (bins may be quantiles)
        means.append(float(z[sel].mean()))
        zscores.append(float(z[sel].sum() / np.sqrt(n)))
        counts.append(n)
    return {"centre": centres, "mean_z": means, "bin_z": zscores, "count": counts}


def _quantile_edges(values: np.ndarray, n_bins: int) -> np.ndarray:
    edges = np.unique(np.quantile(values, np.linspace(0, 1, n_bins + 1)))
    edges[-1] += 1e-9
    return edges


def residual_profiles(z: np.ndarray, mask: np.ndarray, thickness_coarse: np.ndarray,
                      expected_dn: np.ndarray, grid: ChainGrid, px_scale: int = 1) -> dict:
    """Mean normalised residual along the organising covariates of the library.

    Positions (rows, columns, edge distance) are in recording pixels (fitted-grid pixels times
    ``px_scale``, the binning).

    Returns a dict of profiles ``{"rows", "columns", "radius", "edge_distance_px", "thickness_mm",
    "intensity_dn"}`` each with bin centres, mean z, bin z-score (``Σz/√n``) and counts.
    """
    from scipy import ndimage

    h, w = z.shape
    rr, cc = np.broadcast_arrays(np.arange(h)[:, None], np.arange(w)[None, :])
    zm, m = z[mask], mask
    rho = np.sqrt(((grid.x**2 + grid.y**2) / 2.0) * np.ones(z.shape))
    attenuating = thickness_coarse > 0.5 * max(float(thickness_coarse.max()), 1e-12) * 0.1
    inside = ndimage.distance_transform_edt(attenuating)
    outside = ndimage.distance_transform_edt(~attenuating)
    signed = np.where(attenuating, -inside + 0.5, outside - 0.5)
    nbins = 32
    rr, cc, signed = rr * px_scale, cc * px_scale, signed * px_scale
    return {
        "rows": _binned_profile(rr[m], zm, np.linspace(0, h * px_scale, min(nbins, h) + 1)),
        "columns": _binned_profile(cc[m], zm, np.linspace(0, w * px_scale, min(nbins, w) + 1)),
        "radius": _binned_profile(rho[m], zm, np.linspace(0, rho.max() + 1e-9, nbins + 1)),
        "edge_distance_px": _binned_profile(signed[m], zm, np.arange(-30.5, 31.5, max(2.0, px_scale))),
        "thickness_mm": _binned_profile(thickness_coarse[m], zm,
                                        np.linspace(0, thickness_coarse.max() + 1e-9, 17)),
        "intensity_dn": _binned_profile(expected_dn[m], zm, _quantile_edges(expected_dn[m], 16)),
    }


def multiscale_maps(z: np.ndarray, mask: np.ndarray, scales=(1, 4, 16)) -> dict[int, np.ndarray]:
    """Binned residual maps ``Σz/√n`` per ``b × b`` block (unit variance under the null)."""
    out = {}
    zz = np.where(mask, z, 0.0)
    for b in scales:
        h, w = (z.shape[0] // b) * b, (z.shape[1] // b) * b
        s = zz[:h, :w].reshape(h // b, b, w // b, b).sum(axis=(1, 3))
        n = mask[:h, :w].reshape(h // b, b, w // b, b).sum(axis=(1, 3))
        out[b] = (s / np.sqrt(np.maximum(n, 1))).astype(np.float32)
    return out




# --------------------------------------------------------------------------- the fitter


class _Problem:
    """Recording, mask, noise model and chain model of one diagnosis.

    The fitted residual is the prewhitened normalised residual ``W[(y - mu) / sqrt(v)]`` at the
    unmasked pixels (``W`` = identity for white noise).
    """

    def __init__(self, y: np.ndarray, model: ChainModel, mask: np.ndarray):
        self.y = y
        self.model = model
        self.mask = mask
        self.noise: noise_mod.NoiseModel | None = None
        self.wsqrt = np.ones_like(y)
        self.n = int(mask.sum())

    def set_noise(self, noise: noise_mod.NoiseModel, expected: np.ndarray, offset: float) -> None:
        self.noise = noise
        self.wsqrt = 1.0 / np.sqrt(noise.variance(expected, offset))

    @property
    def n_effective(self) -> float:
        """Expected χ² of the true model: unmasked pixels × measured whitened noise variance."""
        return self.n * (self.noise.effective_fraction if self.noise is not None else 1.0)

    def whiten_field(self, field_: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        """Prewhiten a weighted field (zero outside the mask) and take the selected pixels."""
        m = self.mask if sel is None else sel
        u = np.where(self.mask, field_, 0.0)
        if self.noise is not None and not self.noise.is_white:
            u = self.noise.whiten(u)
        return u[m]

    def whitened(self, layout: _Layout, x: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        mu = self.model.expected(*layout.unpack(x))
        return self.whiten_field((self.y - mu) * self.wsqrt, sel)

    def jacobian(self, layout: _Layout, x: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        """Jacobian of the whitened residual: analytic for offset and gain, else forward differences."""
        base, terms = layout.unpack(x)
        mu = self.model.expected(base, terms)
        f0 = self.whiten_field((self.y - mu) * self.wsqrt, sel)
        jac = np.empty((f0.size, x.size))
        for j, (owner, key) in enumerate(layout.names):
            if owner == "base" and key == "offset_dn":
                jac[:, j] = self.whiten_field(-self.wsqrt, sel)
            elif owner == "base" and key == "gain_dn":
                jac[:, j] = self.whiten_field(-(mu - base["offset_dn"]) / base["gain_dn"] * self.wsqrt, sel)
            else:
                h = layout.steps[j] if x[j] + layout.steps[j] <= layout.upper[j] else -layout.steps[j]
                xj = x.copy()
                xj[j] += h
                jac[:, j] = (self.whitened(layout, xj, sel) - f0) / h
        return jac

    def fit(self, layout: _Layout, x0: np.ndarray, sel: np.ndarray | None = None, max_nfev: int = 40):
        """Bounded least squares; returns ``(x, χ², Jacobian at x)``."""
        return _levenberg_marquardt(lambda x: self.whitened(layout, x, sel),
                                    lambda x: self.jacobian(layout, x, sel),
                                    x0, layout.lower, layout.upper, max_nfev)


def _levenberg_marquardt(fun, jac, x0, lower, upper, max_nfev: int, rel_tol: float = 1e-9):
    """Levenberg–Marquardt on the small normal equations, with an active set for the bounds.

    The residual vectors are long (every pixel) and the parameters few (≤ ~30): ``JᵀJ`` is a
    tiny matrix, so each step costs one Jacobian, not an SVD of it. Parameters at a bound whose
    gradient points outward are held for that step. Stops when χ² improves by less than
    ``max(1e-3, rel_tol·χ²)`` (far below what a BIC comparison resolves) or after ``max_nfev``
    residual evaluations.
    """
    x = np.clip(np.asarray(x0, float), lower, upper)
    r = fun(x)
    chi2 = float(r @ r)
    nfev, lam = 1, 1e-3
    j = jac(x)
    while nfev < max_nfev:
        a = j.T @ j
        g = j.T @ r
        at_low = (x <= lower) & (g > 0)
        at_high = (x >= upper) & (g < 0)
        free = ~(at_low | at_high)
        if not free.any():
            break
        af, gf = a[np.ix_(free, free)], g[free]
        diag = np.maximum(np.diag(af), 1e-30)
        accepted = False
        while nfev < max_nfev:
            step = np.zeros_like(x)
            try:
                step[free] = np.linalg.solve(af + lam * np.diag(diag), -gf)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = np.clip(x + step, lower, upper)
            r_new = fun(x_new)
            nfev += 1
            chi2_new = float(r_new @ r_new)
            if np.isfinite(chi2_new) and chi2_new < chi2:
                accepted = True
                break
            lam *= 4.0
            if lam > 1e12:
                break
        if not accepted:
            break
        gain = chi2 - chi2_new
        x, r, chi2 = x_new, r_new, chi2_new
        lam = max(lam / 3.0, 1e-9)
        j = jac(x)
        if gain < max(1e-3, rel_tol * chi2):
            break
    return x, chi2, j


def _covariance(jac: np.ndarray) -> np.ndarray:
    jtj = jac.T @ jac
    try:
        return np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(jtj)


def _orthonormal(columns: np.ndarray, reference_norm: float, rel_tol: float = 1e-4) -> np.ndarray:
    """Orthonormal basis of the column space, dropping directions below ``rel_tol`` of the norm.

    QR of the tall matrix, then an SVD of the small triangular factor (cheap for n >> d).
    """
    if columns.shape[1] == 0:
        return columns
    q, r = np.linalg.qr(columns, mode="reduced")
    u, s, _ = np.linalg.svd(r)
    keep = s > rel_tol * max(reference_norm, 1e-300)
    return q @ u[:, keep]


def _candidate_columns(problem: _Problem, layout: _Layout, x: np.ndarray, term: PhysicsTerm,
                       grid_point: dict) -> np.ndarray:
    """Whitened Jacobian columns of ``term`` (non-grid params) at its probe point."""
    base, terms = layout.unpack(x)
    probe = probe_params(term, problem.model.grid)
    probe.update(grid_point)
    f_probe = problem.model.expected(base, terms + [(term, probe)])
    cols = []
    for spec in term.params:
        if spec.is_grid:
            continue
        plus = dict(probe)
        # forward difference, stepping inside the prior range
        h = spec.step if probe[spec.name] + spec.step <= spec.prior[1] else -spec.step
        plus[spec.name] += h
        f_plus = problem.model.expected(base, terms + [(term, plus)])
        cols.append(problem.whiten_field((f_plus - f_probe) / h * problem.wsqrt))
    return np.stack(cols, axis=1)


def _rank(problem: _Problem, layout: _Layout, x: np.ndarray, jac0: np.ndarray, z: np.ndarray,
          candidates: list[PhysicsTerm]) -> list[dict]:
    """Projected score test for each candidate (max over its shape grid)."""
    q0 = _orthonormal(jac0, np.linalg.norm(jac0, axis=0).max(), 1e-9)
    log_n = np.log(problem.n)
    out = []
    for term in candidates:
        best = None
        for gp in term.grid_points():
            cols = _candidate_columns(problem, layout, x, term, gp)
            perp = cols - q0 @ (q0.T @ cols)
            # S = gᵀ G⁺ g with G = B⊥ᵀB⊥, g = B⊥ᵀz (small d×d problem; directions whose
            # projected norm is below 1e-4 of the raw column norm are not identifiable)
            gram = perp.T @ perp
            grad = perp.T @ z
            evals, evecs = np.linalg.eigh(gram)
            ref = float(np.linalg.norm(cols, axis=0).max())
            keep = evals > (1e-4 * ref) ** 2
            if not keep.any():
                continue
            proj = evecs[:, keep].T @ grad
            score = float(np.sum(proj**2 / evals[keep]))
            if best is None or score > best["score"]:
                coef = evecs[:, keep] @ (proj / evals[keep])
                best = {"effect": term.name, "score": score, "dof": int(keep.sum()),
                        "grid": dict(gp), "one_step": [float(c) for c in coef], "_perp": perp}
        if best is None:
            continue
        k = len(term.params)
        best["delta_bic_est"] = best["score"] - k * log_n
        out.append(best)
    out.sort(key=lambda d: -d["delta_bic_est"])
    return out


def _checkerboard(shape: tuple[int, int], block: int) -> np.ndarray:
    r = (np.arange(shape[0]) // block)[:, None]
    c = (np.arange(shape[1]) // block)[None, :]
    return ((r + c) % 2).astype(bool)


def _smooth_term_delta_bic(z: np.ndarray, mask: np.ndarray, q0: np.ndarray, grid: ChainGrid,
                           degree: int = 4) -> tuple[float, np.ndarray]:
    """ΔBIC of a generic smooth 2-D Legendre surface in the residual (location of leftovers)."""
    from numpy.polynomial import legendre

    xs = np.broadcast_to(grid.x / max(np.abs(grid.x).max(), 1e-9), z.shape)[mask]
    ys = np.broadcast_to(grid.y / max(np.abs(grid.y).max(), 1e-9), z.shape)[mask]
    cols = []
    for i in range(degree + 1):
        for j in range(degree + 1 - i):
            if i == 0 and j == 0:
                continue
            ci = np.zeros(i + 1)
            ci[i] = 1
            cj = np.zeros(j + 1)
            cj[j] = 1
            cols.append(legendre.legval(xs, ci) * legendre.legval(ys, cj))
    basis = np.stack(cols, 1)
    zm = z[mask]
    perp = basis - q0 @ (q0.T @ basis)
    qb = _orthonormal(perp, np.linalg.norm(basis, axis=0).max())
    coef = qb.T @ zm
    score = float(coef @ coef)
    smooth = np.zeros(z.shape)
    smooth[mask] = qb @ coef
    return score - qb.shape[1] * np.log(max(zm.size, 2)), smooth


# --------------------------------------------------------------------------- diagnose, by phase


def auto_binning(shape: tuple[int, int], blur_sigma_px: float, max_fit_size_px: int = 512) -> int:
    """Block-averaging factor: the smallest that brings the fit within ``max_fit_size_px`` per
    side, but never so large that the blur falls below one binned pixel (a binned model of a
    sharper image aliases at edges and invents terms)."""
    by_size = int(np.ceil(max(shape) / max_fit_size_px))
    by_blur = max(1, int(np.floor(blur_sigma_px)))
    return max(1, min(by_size, by_blur))


def parse_binning(text: str | int | None) -> int | None:
    """``"auto"``/None → None (automatic), else an integer >= 1 (one-line error otherwise)."""
    if text is None or (isinstance(text, str) and text.strip().lower() == "auto"):
        return None
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ParameterError(f"--binning must be 'auto' or an integer >= 1, got {text!r}") from None
    if value < 1:
        raise ParameterError(f"--binning must be 'auto' or an integer >= 1, got {text!r}")
    return value


def _blur_sigma_px(base: dict, grid: ChainGrid) -> float:
    return float(np.hypot(base["focal_spot_sigma_mm"] * grid.magnification_minus_one,
                          base["detector_sigma_mm"]) / grid.pitch_mm)


@dataclass
class _Setup:
    y: np.ndarray
    mask: np.ndarray
    grid: ChainGrid
    model: ChainModel
    thickness: np.ndarray
    binning: int
    pre_blur_px: float


def _check_inputs(y_full, thickness_mm, grid, base_start, opts) -> list[PhysicsTerm]:
    if y_full.ndim != 2:
        raise InputError(None, f"diagnosis needs a single-channel 2-D recording, got shape {y_full.shape}")
    if not np.all(np.isfinite(y_full)):
        raise InputError(None, "recording contains NaN or infinite values")
    if tuple(y_full.shape) != tuple(grid.shape):
        raise InputError(None, f"recording shape {y_full.shape} does not match the scene {grid.shape}")
    if tuple(np.shape(thickness_mm)) != (grid.shape[0] * grid.fine_factor, grid.shape[1] * grid.fine_factor):
        raise InputError(None, f"thickness shape {np.shape(thickness_mm)} does not match recording "
                               f"{y_full.shape} × supersample {grid.fine_factor}")
    for key in BASE_FREE + ("focal_spot_sigma_mm",):
        if key not in base_start:
            raise ParameterError(f"base_start is missing {key}")
    if opts.binning is not None and opts.binning < 1:
        raise ParameterError(f"binning must be >= 1, got {opts.binning}")
    return [get_term(n) for n in opts.candidates] if opts.candidates else list(LIBRARY)


def _prepare(y_full, thickness_mm, grid, base_start, opts) -> _Setup:
    """Mask pulses at full resolution, bin, and build the chain model on the fitted grid."""
    from scipy import ndimage

    pulses = ndimage.binary_dilation(_pulses(y_full), iterations=2)

    binning = opts.binning or auto_binning(y_full.shape, _blur_sigma_px(base_start, grid), opts.max_fit_size_px)
    h, w = (y_full.shape[0] // binning) * binning, (y_full.shape[1] // binning) * binning
    s = grid.fine_factor
    y = block_mean(y_full[:h, :w], binning)
    mask = ~(block_mean(pulses[:h, :w].astype(float), binning) > 0)
    fine = np.asarray(thickness_mm, dtype=np.float64)[:h * s, :w * s]
    cgrid = ChainGrid((h // binning, w // binning), s * binning, grid.pitch_mm * binning,
                      grid.magnification_minus_one, grid.source_to_detector_mm)
    # Blur before pixel integration, as physics does: part of the blur on the fine grid. With
    # a supersampled or binned object, blurring only after block-averaging aliases the sharp
    # edges (a 31σ integrated error at 192² with a 2× supersampled phantom).
    pre_blur = opts.pre_blur_fraction * _blur_sigma_px(base_start, cgrid) if s * binning > 1 else 0.0
    return _Setup(y, mask, cgrid, ChainModel(fine, cgrid, pre_blur), block_mean(fine, s * binning),
                  binning, pre_blur)


def _pulses(image: np.ndarray, z_threshold: float = 8.0, n_bins: int = 16) -> np.ndarray:
    """Impulsive pulses: high-pass (minus the 3×3 median) beyond ``z_threshold`` robust sigmas,
    the sigma (MAD) taken per bin of local level — the noise level varies with the signal and
    the read noise dominates dark regions, so one global scale would flag dark noise."""
    from scipy import ndimage

    level = ndimage.median_filter(image, size=3, mode="reflect")
    hp = image - level
    edges = np.unique(np.quantile(level, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, max(len(edges) - 2, 0))
    sigma = np.zeros(len(edges))
    for b in range(max(len(edges) - 1, 1)):
        h = hp[which == b]
        if h.size:
            # MAD, but not below a trimmed standard deviation: on integer DN with little noise
            # most high-pass values are 0 and the MAD collapses (1.12 undoes the 1 % trim)
            lo, hi = np.percentile(h, (1.0, 99.0))
            trimmed = h[(h >= lo) & (h <= hi)]
            sigma[b] = max(1.4826 * np.median(np.abs(h - np.median(h))), 1.12 * float(np.std(trimmed)))
    sigma = np.maximum(sigma, max(float(np.max(sigma)) * 1e-3, 1e-12))
    return hp > z_threshold * sigma[which]


def _noise_model(problem: _Problem, mu: np.ndarray, offset: float, opts: DiagnosisOptions,
                 previous: noise_mod.NoiseModel | None) -> noise_mod.NoiseModel:
    if opts.noise_model_binned is not None:
        slope, intercept = opts.noise_model_binned  # v = slope * level + intercept (absolute DN)
        if opts.noise_sample_binned is not None:
            model = noise_mod.estimate_from_noise_sample(opts.noise_sample_binned, mu, (slope, intercept))
        else:
            model = noise_mod.NoiseModel(float(slope), 0.0, source="repeats")
            model.prepare(mu.shape)
        # as v = K (mu - b) + s_r^2 about the fitted offset
        model.read_variance = max(float(intercept + slope * offset), 1e-6)
        return model
    return noise_mod.estimate_from_residual(problem.y - mu, mu, offset, problem.mask, previous)


def _fit_base(setup: _Setup, base_start: dict, opts: DiagnosisOptions):
    """Linear start, then base + registration fit alternating with the noise estimate."""
    from scipy import ndimage

    model, y, mask, cgrid = setup.model, setup.y, setup.mask, setup.grid
    problem = _Problem(y, model, mask)
    base0 = dict(base_start)
    unit = model.expected({**base0, "offset_dn": 0.0, "gain_dn": 1.0})
    design = np.stack([np.ones(mask.sum()), unit[mask]], 1)
    (b0, g0), *_ = np.linalg.lstsq(design, y[mask], rcond=None)
    if opts.fixed_offset_dn is not None:
        base0["offset_dn"] = float(opts.fixed_offset_dn)
        g0 = float(np.sum(unit[mask] * (y[mask] - base0["offset_dn"])) / np.sum(unit[mask] ** 2))
        base0["gain_dn"] = g0 if g0 > 0 else base0["gain_dn"]
        free_base = tuple(k for k in BASE_FREE if k != "offset_dn")
    else:
        free_base = BASE_FREE
        if g0 > 0:
            base0["offset_dn"], base0["gain_dn"] = float(b0), float(g0)
    registration = list(REGISTRATION) if opts.registration else []
    layout = _Layout.build(base0, registration, cgrid, free_base)
    if setup.pre_blur_px > 0:
        j = layout.index("base", "detector_sigma_mm")
        fs_mm = base0["focal_spot_sigma_mm"] * cgrid.magnification_minus_one
        floor_mm = float(np.sqrt(max((1.02 * setup.pre_blur_px * cgrid.pitch_mm) ** 2 - fs_mm**2, 1e-10)))
        layout.lower[j] = floor_mm
        base0["detector_sigma_mm"] = max(base0["detector_sigma_mm"], 1.05 * floor_mm)
    x = layout.pack(base0, {t.name: t.null_params() for t in registration})
    mu = model.expected(*layout.unpack(x))
    noise = None
    for _ in range(2):
        offset = layout.unpack(x)[0]["offset_dn"]
        noise = _noise_model(problem, mu, offset, opts, noise)
        problem.set_noise(noise, mu, offset)
        x, chi2, jac = problem.fit(layout, x, max_nfev=opts.max_nfev)
        mu = model.expected(*layout.unpack(x))
    offset = layout.unpack(x)[0]["offset_dn"]
    problem.set_noise(_noise_model(problem, mu, offset, opts, noise), mu, offset)
    # Mask positive outliers the full-resolution test missed (clusters of pulses after binning).
    outliers = ndimage.binary_dilation((y - mu) * problem.wsqrt > 6.0, iterations=1)
    if outliers.any():
        problem.mask = setup.mask = mask & ~outliers
        problem.n = int(problem.mask.sum())
    x, chi2, jac = problem.fit(layout, x, max_nfev=opts.max_nfev if outliers.any() else 5)
    return problem, layout, x, chi2, jac


@dataclass
class _Trial:
    term: PhysicsTerm
    layout: _Layout
    x: np.ndarray
    chi2: float
    jac: np.ndarray
    delta_bic: float
    score: float = 0.0
    cand: dict | None = None

    def summary(self) -> dict:
        return {"effect": self.term.name, "delta_bic": round(float(self.delta_bic), 2),
                "score": round(float(self.score), 2)}


def _refit_with(problem: _Problem, layout: _Layout, x: np.ndarray, chi2_now: float, term: PhysicsTerm,
                start: dict, opts: DiagnosisOptions, log_n: float) -> _Trial:
    new_layout = _Layout.build(layout.base_fixed, layout.terms + [term], problem.model.grid, layout.free_base)
    nb = len(layout.free_base)
    new_layout.lower[:nb] = layout.lower[:nb]
    base_cur, current = layout.unpack(x)
    x0 = new_layout.pack(base_cur, {**{t.name: p for t, p in current}, term.name: start})
    x_ext, chi2_ext, jac_ext = problem.fit(new_layout, x0, max_nfev=opts.max_nfev)
    delta_bic = chi2_now - chi2_ext - len(term.params) * log_n
    return _Trial(term, new_layout, x_ext, chi2_ext, jac_ext, float(delta_bic))


def _start_from_candidate(term: PhysicsTerm, cand: dict, grid: ChainGrid) -> dict:
    start = probe_params(term, grid)
    start.update(cand["grid"])
    bounds = physical_bounds(term, grid)
    free = [sp for sp in term.params if not sp.is_grid]
    for spec, value in zip(free, cand["one_step"]):
        lo, hi = bounds.get(spec.name, spec.prior)
        if spec.probe != spec.null and abs(value) > 0.1 * abs(spec.probe) and lo <= value <= hi:
            start[spec.name] = value
    return start


def _heldout_gain(problem: _Problem, layout: _Layout, x: np.ndarray, trial: _Trial,
                  train: np.ndarray, test: np.ndarray) -> float:
    """Fit both models on the training blocks; χ² improvement on the held-out blocks."""
    x_cur_tr, _, _ = problem.fit(layout, x, sel=train, max_nfev=10)
    x_ext_tr, _, _ = problem.fit(trial.layout, trial.x, sel=train, max_nfev=10)
    chi_cur = float(np.sum(problem.whitened(layout, x_cur_tr, test) ** 2))
    chi_ext = float(np.sum(problem.whitened(trial.layout, x_ext_tr, test) ** 2))
    return chi_cur - chi_ext


def _at_bound(trial: _Trial) -> list[str]:
    flagged = []
    for i, (owner, key) in enumerate(trial.layout.names):
        if owner != trial.term.name or trial.term.spec(key).period:
            continue
        lo, hi = trial.layout.lower[i], trial.layout.upper[i]
        tol = 1e-3 * (hi - lo)
        if trial.x[i] - lo < tol or hi - trial.x[i] < tol:
            flagged.append(key)
    return flagged


def _confusable(cand: dict, ranking: list[dict], threshold: float) -> list[tuple[str, float]]:
    out = []
    basis = _orthonormal(cand["_perp"], np.linalg.norm(cand["_perp"], axis=0).max())
    for other in ranking[:6]:
        if other["effect"] == cand["effect"]:
            continue
        other_basis = _orthonormal(other["_perp"], np.linalg.norm(other["_perp"], axis=0).max())
        sv = np.linalg.svd(basis.T @ other_basis, compute_uv=False)
        if sv.size and sv.max() > threshold:
            out.append((other["effect"], float(sv.max())))
    return out


def _compare_round(problem, layout, x, chi2_now, ranking, opts, log_n, train, test, say):
    """Refit the best candidates, accept the best refit (or nothing); returns
    ``(trial or None, AddedTerm or None, comparison list, generic signature or None)``."""
    cgrid = problem.model.grid
    trials: list[_Trial] = []
    for cand in ranking[:opts.compare_top]:
        if cand["delta_bic_est"] <= 0 and trials:
            break
        term = get_term(cand["effect"])
        trial = _refit_with(problem, layout, x, chi2_now, term, _start_from_candidate(term, cand, cgrid),
                            opts, log_n)
        trial.score, trial.cand = cand["score"], cand
        trials.append(trial)
        say(f"{term.name}: refitted ΔBIC {trial.delta_bic:.1f}")
    trials.sort(key=lambda t: -t.delta_bic)
    comparison = [t.summary() for t in trials]
    passing = [t for t in trials if t.delta_bic > opts.accept_delta_bic]
    if not passing:
        return None, None, comparison, None
    # A generic smooth surface that explains the mismatch clearly better than the best library
    # term means the mismatch is not that term (stray light, a smooth out-of-library field).
    generic = [_refit_with(problem, layout, x, chi2_now, g, g.null_params(), opts, log_n)
               for g in GENERIC_COMPETITORS]
    comparison += [{**g.summary(), "generic": True} for g in generic]
    best_generic = max(generic, key=lambda t: t.delta_bic)
    if best_generic.delta_bic > passing[0].delta_bic + opts.accept_delta_bic:
        say(f"{best_generic.term.name} beats {passing[0].term.name} by "
            f"{best_generic.delta_bic - passing[0].delta_bic:.1f}: not a library term")
        return None, None, comparison, GENERIC_SIGNATURE[best_generic.term.name]
    for i, winner in enumerate(passing):
        gain = _heldout_gain(problem, layout, x, winner, train, test)
        if gain <= 0:
            say(f"{winner.term.name}: held-out χ² worse by {-gain:.1f} — not accepted")
            continue
        others = [t for t in trials if t is not winner]
        runner = others[0] if others else None
        cov = _covariance(winner.jac)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        params, unc = {}, {}
        for j, (owner, key) in enumerate(winner.layout.names):
            if owner == winner.term.name:
                params[key], unc[key] = winner.term.spec(key).wrap(float(winner.x[j])), float(se[j])
        ambiguous = bool(runner is not None and runner.delta_bic > opts.accept_delta_bic
                         and winner.delta_bic - runner.delta_bic < opts.ambiguity_bic)
        separating = ""
        if ambiguous:
            separating = (f"{winner.term.name}: {winner.term.separating}; "
                          f"{runner.term.name}: {runner.term.separating}")
        n_dof = problem.n_effective - len(winner.x)
        added = AddedTerm(winner.term.name, params, unc, winner.delta_bic, winner.chi2 / n_dof,
                          winner.score, chi2_now - winner.chi2, float(gain),
                          _confusable(winner.cand, ranking, opts.confusable_correlation),
                          runner.term.name if runner else None,
                          float(runner.delta_bic) if runner else None, ambiguous, separating,
                          _at_bound(winner))
        say(f"added {winner.term.name} ΔBIC {winner.delta_bic:.1f} (runner-up "
            f"{runner.term.name if runner else '—'}) held-out gain {gain:.1f}")
        return winner, added, comparison, None
    return None, None, comparison, None


def _update_reported(added: list[AddedTerm], layout: _Layout, x: np.ndarray, jac: np.ndarray) -> None:
    """Earlier terms were refitted jointly: report their current values and errors."""
    se = np.sqrt(np.clip(np.diag(_covariance(jac)), 0, None))
    for term_result in added:
        term = get_term(term_result.effect)
        for i, (owner, key) in enumerate(layout.names):
            if owner == term.name:
                term_result.params[key] = term.spec(key).wrap(float(x[i]))
                term_result.uncertainty[key] = float(se[i])


def _registration_report(layout: _Layout, x: np.ndarray, binning: int) -> dict:
    out = {}
    for i, (owner, key) in enumerate(layout.names):
        if owner == "registration_shift":
            out[key] = float(x[i]) * binning  # recording pixels
        elif owner == "registration_affine" and key == "scale":
            out["scale"] = float(x[i])
        elif owner == "registration_affine":
            out["rotation_deg"] = float(np.rad2deg(x[i]))
    return out


def _signed_edge_distance(thickness_coarse: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    attenuating = thickness_coarse > 0.05 * max(float(thickness_coarse.max()), 1e-12)
    inside = ndimage.distance_transform_edt(attenuating)
    outside = ndimage.distance_transform_edt(~attenuating)
    return np.where(attenuating, -inside + 0.5, outside - 0.5)


def _compose_message(added, structure, generic_signature, binning, sigma_coarse_px) -> tuple[bool, str]:
    signatures = list(structure["signatures"])
    if generic_signature:
        signatures.insert(0, generic_signature)
    unexplained = bool(signatures)
    named = ", ".join(a.effect + (" (ambiguous with " + a.runner_up + ")" if a.ambiguous else "")
                      for a in added)
    if unexplained:
        head = f"added {named}; " if added else ""
        message = head + "unexplained structure remains: " + "; ".join(signatures) + " (not in the library)"
    elif added:
        message = f"added {named}; no structure left (every residual test passes)"
    else:
        message = "nothing missing: no term added and every residual test passes"
    if binning > 1 and sigma_coarse_px < 1.0:
        message += (f" (caution: blur {sigma_coarse_px:.2f} binned px < 1 — the {binning}× binned model "
                    "may alias at sharp edges; use a smaller binning)")
    return unexplained, message


def diagnose(recording: np.ndarray, thickness_mm: np.ndarray, grid: ChainGrid,
             base_start: dict[str, float], options: DiagnosisOptions | None = None,
             progress: Callable[[str], None] | None = None) -> DiagnosisResult:
    """Diagnose what the base model leaves out of ``recording``.

    Parameters
    ----------
    recording : ndarray, (H, W)
        Single-channel linear recording in DN (any real dtype).
    thickness_mm : ndarray, (H*s, W*s)
        Path length of the object material per fine pixel (mm); ``s = grid.fine_factor`` for the
        unbinned recording.
    grid : ChainGrid
        Chain grid of the unbinned recording (pitch, magnification, SDD).
    base_start : dict
        Starting base parameters (``offset_dn``, ``gain_dn``, ``mu_per_mm``, ``detector_sigma_mm``,
        ``focal_spot_sigma_mm`` — the latter is held fixed).
    options : DiagnosisOptions, optional
    progress : callable, optional
        Called with a short text after each step.
    """
    opts = options or DiagnosisOptions()
    say = progress or (lambda _msg: None)
    y_full = np.asarray(recording, dtype=np.float64)
    candidates = _check_inputs(y_full, thickness_mm, grid, base_start, opts)
    setup = _prepare(y_full, thickness_mm, grid, base_start, opts)
    problem, layout, x, chi2, jac = _fit_base(setup, base_start, opts)
    y, cgrid, model, binning = setup.y, setup.grid, setup.model, setup.binning
    say(f"base fit chi2/dof {chi2 / (problem.n_effective - len(x)):.4f}")

    # Locate.
    n = problem.n
    log_n = np.log(n)
    mask = problem.mask
    base_fit = dict(layout.unpack(x)[0])
    mu = model.expected(*layout.unpack(x))
    z_base = np.zeros(y.shape)
    z_base[mask] = problem.whitened(layout, x)
    base_chi2_dof = chi2 / (problem.n_effective - len(x))
    base_bic = chi2 + len(x) * log_n
    tile = max(8, opts.tile_px)
    regions = flagged_regions(z_base, mask, tile, binning)
    profiles_base = residual_profiles(z_base, mask, setup.thickness, mu, cgrid, binning)
    noise_first = problem.noise.to_json(binning)

    # Search: rank, compare, accept; re-estimate the noise after each accepted term.
    heldout = _checkerboard(y.shape, max(8, opts.heldout_block_px // binning if binning > 1
                                         else opts.heldout_block_px))
    train, test = mask & ~heldout, mask & heldout
    added: list[AddedTerm] = []
    rankings, comparisons = [], []
    remaining = list(candidates)
    generic_signature = None
    while len(added) < opts.max_terms and remaining:
        z = problem.whitened(layout, x)
        ranking = _rank(problem, layout, x, jac, z, remaining)
        rankings.append([{k: v for k, v in r.items() if k != "_perp"} for r in ranking])
        say("ranking: " + ", ".join(f"{r['effect']} S={r['score']:.1f}" for r in ranking[:3]))
        trial, term_result, comparison, generic_signature = _compare_round(
            problem, layout, x, chi2, ranking, opts, log_n, train, test, say)
        comparisons.append(comparison)
        if trial is None:
            break
        added.append(term_result)
        layout, x, chi2, jac = trial.layout, trial.x, trial.chi2, trial.jac
        mu = model.expected(*layout.unpack(x))
        offset = layout.unpack(x)[0]["offset_dn"]
        problem.set_noise(_noise_model(problem, mu, offset, opts, problem.noise), mu, offset)
        x, chi2, jac = problem.fit(layout, x, max_nfev=5)
        _update_reported(added, layout, x, jac)
        remaining = [t for t in remaining if t.name != trial.term.name]

    # Final checks.
    mu = model.expected(*layout.unpack(x))
    z_final = np.zeros(y.shape)
    z_final[mask] = problem.whitened(layout, x)
    final_dof = chi2 / (problem.n_effective - len(x))
    if added:
        added[-1].chi2_per_dof = final_dof
    q0 = _orthonormal(jac, np.linalg.norm(jac, axis=0).max(), 1e-9)
    smooth_dbic, smooth_map = _smooth_term_delta_bic(z_final, mask, q0, cgrid)
    radius = np.sqrt(((cgrid.x**2 + cgrid.y**2) / 2.0) * np.ones(y.shape))
    structure = structure_tests(z_final, mask, chi2, problem.n_effective - len(x), mu,
                                _signed_edge_distance(setup.thickness), radius, tile, binning,
                                noise_samples=problem.noise.n_samples,
                                min_ghost_lag=3 if problem.noise.is_white else noise_mod.SHORT_LAG_PX + 2)
    unexplained_regions = list(structure["tests"]["tiles"]["regions"])
    if (structure["failed"] or generic_signature) and not unexplained_regions:
        sm = np.abs(smooth_map)
        r, c = np.unravel_index(np.argmax(sm), sm.shape)
        unexplained_regions.append([int(max(0, r - tile) * binning), int(max(0, c - tile) * binning),
                                    int(min(sm.shape[0], r + tile) * binning),
                                    int(min(sm.shape[1], c + tile) * binning)])
    final_base = layout.unpack(x)[0]
    unexplained, message = _compose_message(added, structure, generic_signature, binning,
                                            _blur_sigma_px(final_base, cgrid))
    if not unexplained:
        unexplained_regions = []
    noise_json = problem.noise.to_json(binning)
    noise_json["base"] = noise_first
    return DiagnosisResult(
        base_chi2_per_dof=float(base_chi2_dof), base_bic=float(base_bic), regions=regions, added=added,
        final_chi2_per_dof=float(final_dof), unexplained=unexplained,
        unexplained_regions=unexplained_regions,
        noise_poisson_gain_dn=float(problem.noise.poisson_gain * binning**2),
        noise_read_dn=float(np.sqrt(problem.noise.read_variance) * binning),
        base_params=base_fit, final_base_params=dict(final_base),
        z_base=z_base.astype(np.float32), z_final=z_final.astype(np.float32), mask=mask,
        profiles_base=profiles_base,
        profiles_final=residual_profiles(z_final, mask, setup.thickness, mu, cgrid, binning),
        rankings=rankings, binning=binning, n_pixels=n, smooth_delta_bic=float(smooth_dbic),
        message=message, registration=_registration_report(layout, x, binning), noise=noise_json,
        structure=structure, signatures=([generic_signature] if generic_signature else [])
        + structure["signatures"], comparisons=comparisons)


def diagnose_scene(scene: Scene, recording: np.ndarray, options: DiagnosisOptions | None = None,
                   progress: Callable[[str], None] | None = None) -> DiagnosisResult:
    """:func:`diagnose` with geometry, object and starting values from a :class:`Scene`.

    The scene's ``[effects.*]`` tables are not part of the fitted model (they are what
    ``simulate`` injects); the diagnosis starts from the base model and finds them itself.
    """
    if tuple(np.shape(recording)) != scene.shape:
        raise InputError(scene.path or "scene", f"recording shape {np.shape(recording)} does not match "
                                                f"the thickness map {scene.shape}")
    return diagnose(recording, scene.thickness_mm, scene.grid(), scene.base_params(), options, progress)


def clean_repeats(frames: np.ndarray, z_threshold: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean of repeated frames with impulsive spots replaced by the temporal median.

    Parameters
    ----------
    frames : ndarray, (N, H, W)
        Repeated exposures (DN), N >= 3.
    z_threshold : float
        A pixel of a frame is a spot when it exceeds the temporal median by more than this many
        robust (MAD) standard deviations of the frame-minus-median difference.

    Returns
    -------
    mean : ndarray, float64, (H, W)
    spot_fraction : ndarray, float64, (N,)
        Fraction of pixels replaced per frame.
    """
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 3:
        raise InputError(None, f"need at least 3 repeated 2-D frames, got shape {frames.shape}")
    median = np.median(frames, axis=0)
    diff = frames - median
    sigma = 1.4826 * np.median(np.abs(diff), axis=(1, 2), keepdims=True)
    spots = diff > z_threshold * sigma
    cleaned = np.where(spots, median, frames)
    return cleaned.mean(axis=0), spots.mean(axis=(1, 2))


def noise_model_from_repeats(frames: np.ndarray, binning: int, n_bins: int = 24) -> tuple[float, float]:
    """``(K, c)``, ``var = K · level + c`` (DN², absolute level), of the mean of ``frames``
    block-averaged ``binning``×, from the repeats themselves.

    The difference of the means of the even and odd frames, halved, has the noise variance of
    the mean of all frames — including its spatially correlated part, which a high-pass
    estimate on one image misses (scintillator light spread makes the noise correlated). Each
    half's global gain/offset difference (source output drift) and a very smooth drift map are
    removed first; then a robust (MAD) variance per bin of block level and a straight line.
    Spots must already be replaced (:func:`clean_repeats`).
    """
    from scipy import ndimage

    frames = np.asarray(frames, dtype=np.float64)
    n = frames.shape[0]
    if frames.ndim != 3 or n < 4:
        raise InputError(None, f"need at least 4 repeated 2-D frames for the noise model, got {frames.shape}")
    mean = frames.mean(axis=0)
    diff = 0.5 * (frames[0::2].mean(axis=0) - frames[1::2].mean(axis=0))
    # equal weights: var(diff) = var(mean) exactly only for equal halves
    diff *= np.sqrt((n // 2 + (n - n // 2)) ** 2 / (4 * (n // 2) * (n - n // 2))) if n % 2 else 1.0
    h, w = mean.shape
    hb, wb = (h // binning) * binning, (w // binning) * binning
    level = block_mean(mean[:hb, :wb], binning)
    d = block_mean(diff[:hb, :wb], binning)
    design = np.stack([np.ones(level.size), level.ravel()], 1)
    coef, *_ = np.linalg.lstsq(design, d.ravel(), rcond=None)
    d = d - (design @ coef).reshape(d.shape)
    d = d - ndimage.gaussian_filter(d, max(2.0, 32.0 / binning), mode="reflect")
    edges = np.unique(np.quantile(level, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, level.ravel(), side="right") - 1, 0, len(edges) - 2)
    xs, vs = [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() >= 20:
            dd = d.ravel()[sel]
            xs.append(level.ravel()[sel].mean())
            vs.append((1.4826 * np.median(np.abs(dd - np.median(dd)))) ** 2)
    if len(xs) < 2:
        raise InputError(None, "too few pixels to estimate the noise model from the repeats")
    slope, intercept = np.polyfit(np.array(xs), np.array(vs), 1)
    return float(slope), float(intercept)


def _halved_difference(frames: np.ndarray, binning: int) -> np.ndarray:
    """Half the difference of the even and odd frames' means, block-averaged: a pure noise
    field with the noise (variance and correlation) of the binned mean of all frames."""
    n = frames.shape[0]
    diff = 0.5 * (frames[0::2].mean(axis=0) - frames[1::2].mean(axis=0))
    if n % 2:
        diff *= np.sqrt(n**2 / (4 * (n // 2) * (n - n // 2)))
    h, w = diff.shape
    crop = (slice(0, (h // binning) * binning), slice(0, (w // binning) * binning))
    d = block_mean(diff[crop], binning)
    level = block_mean(frames.mean(axis=0)[crop], binning)
    # the halves' global gain/offset difference (source output drift) is not noise
    design = np.stack([np.ones(level.size), level.ravel()], 1)
    coef, *_ = np.linalg.lstsq(design, d.ravel(), rcond=None)
    return d - (design @ coef).reshape(d.shape)


def edge_object_from_image(image: np.ndarray, supersample: int = 2, smooth_px: float = 1.0) -> np.ndarray:
    """Ideal (unblurred) opaque-object map from a recording of a plate edge, sub-pixel.

    The image is smoothed (Gaussian ``smooth_px``), upsampled ``supersample``× (bilinear) and
    thresholded half-way between the open level (95th percentile) and the plate level (5th
    percentile). For a symmetric PSF the 50 % contour of a blurred straight edge lies on the
    edge itself, so the map is the plate as it would be imaged without blur (corners are
    slightly rounded).

    Returns
    -------
    ndarray, float64, (H*s, W*s)
        1.0 where the plate is, 0.0 in the open field (a "thickness" in mm of a unit material
        whose attenuation the base fit estimates).
    """
    from scipy import ndimage

    img = ndimage.gaussian_filter(np.asarray(image, dtype=np.float64), smooth_px)
    lo, hi = np.percentile(img, 5), np.percentile(img, 95)
    fine = ndimage.zoom(img, supersample, order=1, mode="nearest", grid_mode=True)
    return (fine < 0.5 * (lo + hi)).astype(np.float64)


def diagnose_edge_repeats(frames: np.ndarray, *, dark_frame: np.ndarray | None = None,
                          flat_frame: np.ndarray | None = None, pixel_pitch_mm: float = 0.1,
                          binning: int = 2, supersample: int = 2,
                          options: DiagnosisOptions | None = None,
                          progress: Callable[[str], None] | None = None) -> DiagnosisResult:
    """Diagnose repeated recordings of an opaque plate edge (no thickness map available).

    Steps: flat-field correction with the smoothed open-beam frame (if given; median 5×5 then
    Gaussian sigma 3 px, normalised to median 1); spots replaced by the temporal median and the
    frames averaged (:func:`clean_repeats`); the ideal edge map derived from the mean image
    (:func:`edge_object_from_image`, a unit-thickness "material" whose attenuation is fitted);
    the noise model of the binned mean from the even/odd half difference
    (:func:`noise_model_from_repeats`); the offset held at the dark frame's median (it separates
    a uniform glare floor from the black level). Geometry: the object lies against the screen
    (``M - 1 ≈ 0``), so only the detector blur is fitted.

    Parameters
    ----------
    frames : ndarray, (N, H, W)
        Repeated exposures (DN), N >= 4.
    dark_frame, flat_frame : ndarray, (H, W), optional
    pixel_pitch_mm : float
        Pixel pitch on the screen (ranges are reported in mm with it).
    binning : int
        Block-averaging factor of the fit (the noise is spatially correlated).
    """
    from scipy import ndimage

    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 4:
        raise InputError(None, f"need at least 4 repeated 2-D frames, got shape {frames.shape}")
    dark = float(np.median(dark_frame)) if dark_frame is not None else float(np.percentile(frames, 0.1))
    if flat_frame is not None:
        flat = ndimage.gaussian_filter(ndimage.median_filter(np.asarray(flat_frame, float), 5), 3) - dark
        if np.any(flat <= 0):
            raise InputError(None, "flat frame is not brighter than the dark level everywhere")
        flat /= np.median(flat)
        frames = (frames - dark) / flat + dark
    median = np.median(frames, axis=0)
    diff = frames - median
    sigma = 1.4826 * np.median(np.abs(diff), axis=(1, 2), keepdims=True)
    cleaned = np.where(diff > 6.0 * sigma, median, frames)
    recording = cleaned.mean(axis=0)
    h, w = recording.shape
    h, w = (h // binning) * binning, (w // binning) * binning
    recording, cleaned = recording[:h, :w], cleaned[:, :h, :w]
    obj = edge_object_from_image(recording, supersample)
    slope, intercept = noise_model_from_repeats(cleaned, binning)
    noise_sample = _halved_difference(cleaned, binning)
    grid = ChainGrid(recording.shape, supersample, pixel_pitch_mm, 0.0, 1.0e4)
    open_level = float(np.percentile(recording, 95))
    plate_level = float(np.percentile(recording, 5))
    start = {"offset_dn": dark, "gain_dn": open_level - dark,
             "mu_per_mm": float(np.log((open_level - dark) / max(plate_level - dark, 1.0))),
             "detector_sigma_mm": 2.0 * pixel_pitch_mm, "focal_spot_sigma_mm": 0.0}
    opts = options or DiagnosisOptions()
    from dataclasses import replace

    opts = replace(opts, binning=binning, fixed_offset_dn=dark, noise_model_binned=(slope, intercept),
                   noise_sample_binned=noise_sample)
    return diagnose(recording, obj, grid, start, opts, progress)
