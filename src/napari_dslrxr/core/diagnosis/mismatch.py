"""Mismatch diagnosis: locate, name, model and refit what the base model leaves out.

Algorithm (``docs/algorithms/diagnosis.md``), on a single-channel linear recording:

1. **Base fit.** Offset, gain, effective attenuation and detector blur width are fitted by
   weighted least squares (``scipy.optimize.least_squares``); the focal-spot width stays at the
   scene value, because with one object height only the combined Gaussian width is identifiable
   (docs/algorithms/diagnosis.md, section 'Identifiability'). Impulsive pulses are masked
   (high-pass robust z > 6, dilated). The noise model
   ``v(mu) = K (mu - b) + s_r^2`` is estimated from the recording itself: robust (MAD) variance of
   the high-passed residual ``r - mean4(r)`` per bin of expected intensity, then a weighted line;
   the high-pass keeps smooth model mismatch out of the noise estimate.
2. **Locate.** Normalised residuals ``z = (y - mu) / sqrt(v(mu))``; maps binned 1×, 4×, 16×;
   tiles with excess mean (``T z̄ ~ N(0,1)``) or excess ``Σ z²`` (Bonferroni over tiles);
   profiles along rows, columns, radius, signed edge distance, thickness and intensity.
3. **Rank.** For each library term and each point of its shape grid, Jacobian columns by central
   differences; projected Rao score ``S = |P_B⊥ z|²`` with the current model's Jacobian projected
   out (``B⊥ = B - Q0 Q0ᵀ B``; the projection is essential, docs/algorithms/diagnosis.md,
   section '3. Rank: projected score test');
   ``ΔBIC_est = S - (d + n_grid) ln n``. Confusability = largest canonical correlation of the
   projected column spaces of the two best candidates (> 0.9 is flagged).
4. **Extend + confirm.** Start from the grid point and the one-step amplitude, refit ALL
   parameters jointly; accept only if ``ΔBIC = χ²_cur - χ²_ext - k ln n > 10`` and the held-out
   χ² on checkerboard blocks (model fitted on the other blocks) improves. Repeat.
5. **Stop.** When no candidate passes. Then the final residual is tested for leftover structure
   (tiles, and a generic smooth 2-D Legendre term of degree 4 with ΔBIC > 10): if present the
   result says ``unexplained`` and where.

Large recordings are block-averaged to at most ``max_fit_size_px`` per side; the transmission
(and a part of the blur, to avoid aliasing of sharp edges) is still computed on the full grid.
With repeated frames and a dark frame (:func:`diagnose_edge_repeats`) the noise model comes from
the frames' even/odd difference (correlated noise) and the offset from the dark frame.
Cost: cached input spectrum and post-PSF image, so most Jacobian columns need one inverse FFT
or none; offset and gain columns are analytic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import InputError, ParameterError
from ..simulation.physics_terms import LIBRARY, ChainGrid, PhysicsTerm, get_term
from ..simulation.simulator import ChainModel, Scene, block_mean

BASE_FREE = ("offset_dn", "gain_dn", "mu_per_mm", "detector_sigma_mm")


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
        Recordings larger than this along an axis are block-averaged (binned) before fitting.
    candidates : tuple of str or None
        Library terms to consider (default: all).
    confusable_correlation : float
        Canonical correlation above which two candidates are flagged as confusable.
    tries_per_round : int
        Candidates refitted per round before giving up.
    max_nfev : int
        Function-evaluation limit per least-squares fit.
    binning : int or None
        Force this block-averaging factor (default: the smallest that fits ``max_fit_size_px``).
        Use it when the noise is spatially correlated (bin until lag-1 correlation is small).
    pre_blur_fraction : float
        For binned fits, this fraction of the starting blur width is applied on the full grid
        before binning (avoids aliasing of sharp edges); the fitted width cannot go below it.
    fixed_offset_dn : float or None
        Hold the camera offset at this value (from a dark frame: the acquisition that separates
        a uniform glare floor from the black level; docs/algorithms/diagnosis.md, section
        'Identifiability'); default: fitted.
    noise_model_binned : (float, float) or None
        ``(K, c)`` with ``v(mu) = K mu + c`` (absolute DN) for the *binned* recording, e.g. from
        repeated frames
        (:func:`noise_model_from_repeats`); default: estimated from the recording itself.
    """

    accept_delta_bic: float = 10.0
    max_terms: int = field(default=4, metadata={
        "help": "at most this many effects are added to the scene model", "unit": "terms", "min": 1, "max": 10})
    tile_px: int = 32
    heldout_block_px: int = 32
    max_fit_size_px: int = 512
    candidates: tuple[str, ...] | None = None
    confusable_correlation: float = 0.9
    tries_per_round: int = 2
    max_nfev: int = 60
    binning: int | None = None
    noise_model_binned: tuple[float, float] | None = None
    fixed_offset_dn: float | None = None
    pre_blur_fraction: float = 0.6


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

    def to_json(self) -> dict:
        """The ``diagnosis.json`` content, in the issue's shape."""
        return {
            "base": {"chi2_per_dof": round(self.base_chi2_per_dof, 5), "bic": round(self.base_bic, 2)},
            "mismatch": {"regions": self.regions},
            "added": [{"effect": a.effect,
                       "params": {k: round(v, 7) for k, v in a.params.items()},
                       "uncertainty": {k: round(v, 7) for k, v in a.uncertainty.items()},
                       "delta_bic": round(a.delta_bic, 2), "chi2_per_dof": round(a.chi2_per_dof, 5)}
                      for a in self.added],
            "final": {"chi2_per_dof": round(self.final_chi2_per_dof, 5)},
            "unexplained": bool(self.unexplained),
        }

    def details(self) -> dict:
        """Supporting numbers (noise model, rankings, confusable pairs, base parameters)."""
        return {
            "noise": {"poisson_gain_dn": self.noise_poisson_gain_dn, "read_noise_dn": self.noise_read_dn},
            "base_params": self.base_params, "final_base_params": self.final_base_params,
            "binning": self.binning, "n_pixels": self.n_pixels,
            "added": [{"effect": a.effect, "score": a.score, "likelihood_ratio": a.likelihood_ratio,
                       "heldout_gain": a.heldout_gain,
                       "confusable_with": [[n, round(c, 4)] for n, c in a.confusable_with]}
                      for a in self.added],
            "rankings": self.rankings, "unexplained_regions": self.unexplained_regions,
            "smooth_term_delta_bic": self.smooth_delta_bic, "message": self.message,
        }


# --------------------------------------------------------------------------- parameter layout


@dataclass
class _Layout:
    """Free parameters: base names plus (term, param) pairs, with bounds and FD steps."""

    base_fixed: dict[str, float]
    terms: list[PhysicsTerm]
    names: list[tuple[str, str]]
    lower: np.ndarray
    upper: np.ndarray
    steps: np.ndarray
    free_base: tuple[str, ...] = BASE_FREE

    @classmethod
    def build(cls, base: dict[str, float], terms: list[PhysicsTerm],
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
            for spec in term.params:
                names.append((term.name, spec.name))
                lo.append(spec.prior[0]), hi.append(spec.prior[1]), st.append(spec.step)
        layout = cls(dict(base), list(terms), names, np.array(lo), np.array(hi), np.array(st))
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


# --------------------------------------------------------------------------- noise model


def _mean4(image: np.ndarray) -> np.ndarray:
    p = np.pad(image, 1, mode="reflect")
    return 0.25 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])


def estimate_noise_model(residual_dn: np.ndarray, expected_dn: np.ndarray, offset_dn: float,
                         mask: np.ndarray, n_bins: int = 32) -> tuple[float, float]:
    """Fit ``v(mu) = K (mu - b) + s_r^2`` to the high-passed residual.

    Parameters
    ----------
    residual_dn : ndarray
        ``y - mu_hat`` (DN); smooth mismatch is removed by the 4-neighbour high-pass.
    expected_dn : ndarray
        ``mu_hat`` (DN).
    offset_dn : float
        Fitted offset ``b``.
    mask : ndarray of bool
        Pixels to use.

    Returns
    -------
    poisson_gain_dn, read_variance_dn2 : float
        ``K`` (DN per DN of signal) and ``s_r^2`` (DN²).
    """
    high = residual_dn - _mean4(residual_dn)
    use = mask & (_mean4(mask.astype(float)) > 0.99)  # all four neighbours valid too
    signal = (expected_dn - offset_dn)[use]
    hp = high[use]
    if hp.size < 100:
        raise InputError(None, "too few valid pixels to estimate the noise model")
    edges = np.unique(np.quantile(signal, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, signal, side="right") - 1, 0, len(edges) - 2)
    xs, vs, ws = [], [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() < 30:
            continue
        h = hp[sel]
        sigma_robust = 1.4826 * np.median(np.abs(h - np.median(h)))
        # Mean square after clipping far outliers (pulses, edge mismatch): linear in the variance,
        # so a bin that mixes two signal levels still gives their mean variance (a MAD would not).
        kept = h[np.abs(h) < 6.0 * sigma_robust]
        # white noise: var(r - mean4 r) = 1.25 var(r)
        vs.append(float(np.mean(kept**2)) / 1.25)
        xs.append(signal[sel].mean())
        ws.append(sel.sum())
    xs, vs, ws = np.array(xs), np.array(vs), np.array(ws, dtype=float)
    if len(xs) >= 2 and np.ptp(xs) > 0:
        design = np.stack([xs, np.ones_like(xs)], 1)
        # weights ∝ n / v² (variance of a variance estimate)
        wt = np.sqrt(ws) / vs
        coef, *_ = np.linalg.lstsq(design * wt[:, None], vs * wt, rcond=None)
        k, s2 = float(coef[0]), float(coef[1])
    else:
        k, s2 = 0.0, float(np.mean(vs))
    if k < 0:
        k, s2 = 0.0, float(np.average(vs, weights=ws))
    if s2 <= 0:
        s2 = max(1e-6 * float(np.mean(vs)), float(np.min(vs)) * 0.01)
    return k, s2


# --------------------------------------------------------------------------- locate


def _tiles(z: np.ndarray, mask: np.ndarray, tile: int, scale: float = 1.0):
    h, w = z.shape
    out = []
    for r0 in range(0, h - tile // 2, tile):
        for c0 in range(0, w - tile // 2, tile):
            r1, c1 = min(h, r0 + tile), min(w, c0 + tile)
            m = mask[r0:r1, c0:c1]
            n = int(m.sum())
            if n < 16:
                continue
            zz = z[r0:r1, c0:c1][m]
            mean_stat = zz.sum() / np.sqrt(n)
            chi_stat = (np.sum(zz**2) / scale - n) / np.sqrt(2 * n)
            out.append((r0, c0, r1, c1, mean_stat, chi_stat))
    return out


def _flagged_regions(z: np.ndarray, mask: np.ndarray, tile: int, binning: int, alpha: float = 0.01,
                     scale: float = 1.0) -> list[list[int]]:
    """Bounding boxes (recording pixels, end exclusive) of connected tiles with excess residual."""
    from scipy import ndimage, stats

    tiles = _tiles(z, mask, tile, scale)
    if not tiles:
        return []
    threshold = stats.norm.isf(alpha / (2 * len(tiles)))
    h, w = z.shape
    grid = np.zeros((int(np.ceil(h / tile)), int(np.ceil(w / tile))), dtype=bool)
    for r0, c0, r1, c1, m, c in tiles:
        if abs(m) > threshold or c > threshold:
            grid[r0 // tile, c0 // tile] = True
    labels, n = ndimage.label(grid)
    regions = []
    for sl in ndimage.find_objects(labels):
        r0, c0 = sl[0].start * tile, sl[1].start * tile
        r1, c1 = min(h, sl[0].stop * tile), min(w, sl[1].stop * tile)
        regions.append([int(r0 * binning), int(c0 * binning), int(r1 * binning), int(c1 * binning)])
    return regions


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
    """Recording, mask, noise weights and chain model of one diagnosis."""

    def __init__(self, y: np.ndarray, model: ChainModel, mask: np.ndarray):
        self.y = y
        self.model = model
        self.mask = mask
        self.k = 1.0
        self.s2 = 1.0
        self.wsqrt = np.ones_like(y)
        self.n = int(mask.sum())

    def set_weights(self, expected: np.ndarray, offset: float) -> None:
        v = self.k * np.clip(expected - offset, 0.0, None) + self.s2
        self.wsqrt = 1.0 / np.sqrt(v)

    def whitened(self, layout: _Layout, x: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        base, terms = layout.unpack(x)
        mu = self.model.expected(base, terms)
        m = self.mask if sel is None else sel
        return ((self.y - mu) * self.wsqrt)[m]

    def jacobian(self, layout: _Layout, x: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        """Jacobian of the whitened residual: analytic for offset and gain, else forward differences."""
        m = self.mask if sel is None else sel
        base, terms = layout.unpack(x)
        mu = self.model.expected(base, terms)
        f0 = ((self.y - mu) * self.wsqrt)[m]
        jac = np.empty((f0.size, x.size))
        for j, (owner, key) in enumerate(layout.names):
            if owner == "base" and key == "offset_dn":
                jac[:, j] = -self.wsqrt[m]
            elif owner == "base" and key == "gain_dn":
                jac[:, j] = -((mu - base["offset_dn"]) / base["gain_dn"] * self.wsqrt)[m]
            else:
                h = layout.steps[j] if x[j] + layout.steps[j] <= layout.upper[j] else -layout.steps[j]
                xj = x.copy()
                xj[j] += h
                jac[:, j] = (self.whitened(layout, xj, sel) - f0) / h
        return jac

    def fit(self, layout: _Layout, x0: np.ndarray, sel: np.ndarray | None = None, max_nfev: int = 60):
        from scipy.optimize import least_squares

        x0 = np.clip(x0, layout.lower, layout.upper)

        def fun(x):
            return self.whitened(layout, x, sel)

        def jac(x):
            return self.jacobian(layout, x, sel)

        res = least_squares(fun, x0, jac=jac, bounds=(layout.lower, layout.upper), x_scale="jac",
                            method="trf", max_nfev=max_nfev, xtol=1e-8, ftol=1e-9, gtol=1e-8)
        return res.x, float(np.sum(res.fun**2)), res.jac


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
    probe = term.probe_params()
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
        cols.append(((f_plus - f_probe) / h * problem.wsqrt)[problem.mask])
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
    """ΔBIC of a generic smooth 2-D Legendre surface (the 'unexplained' discrepancy term)."""
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
        Chain grid of the unbinned recording (pitch, magnification).
    base_start : dict
        Starting base parameters (``offset_dn``, ``gain_dn``, ``mu_per_mm``, ``detector_sigma_mm``,
        ``focal_spot_sigma_mm`` — the latter is held fixed).
    options : DiagnosisOptions, optional
    progress : callable, optional
        Called with a short text after each step.

    Returns
    -------
    DiagnosisResult
    """
    from scipy import ndimage

    opts = options or DiagnosisOptions()
    say = progress or (lambda _msg: None)
    y_full = np.asarray(recording, dtype=np.float64)
    if y_full.ndim != 2:
        raise InputError(None, f"diagnosis needs a single-channel 2-D recording, got shape {y_full.shape}")
    if not np.all(np.isfinite(y_full)):
        raise InputError(None, "recording contains NaN or infinite values")
    if tuple(y_full.shape) != tuple(grid.shape):
        raise InputError(None, f"recording shape {y_full.shape} does not match the scene {grid.shape}")
    if tuple(np.shape(thickness_mm)) != (grid.shape[0] * grid.fine_factor, grid.shape[1] * grid.fine_factor):
        raise InputError(None, f"thickness shape {np.shape(thickness_mm)} does not match recording "
                               f"{y_full.shape} × supersample {grid.fine_factor}")
    candidates = [get_term(n) for n in opts.candidates] if opts.candidates else list(LIBRARY)
    for key in BASE_FREE + ("focal_spot_sigma_mm",):
        if key not in base_start:
            raise ParameterError(f"base_start is missing {key}")

    # Pulses: high-pass robust z at full resolution (the camera noise is white there).
    hp = y_full - ndimage.median_filter(y_full, size=3, mode="reflect")
    level = ndimage.median_filter(y_full, size=3, mode="reflect")
    rough_var = np.maximum(np.abs(level - np.percentile(level, 0.5)), 1.0)
    scale_est = np.median(np.abs(hp) / np.sqrt(rough_var)) * 1.4826 + 1e-12
    pulses = hp / np.sqrt(rough_var) > 8.0 * scale_est
    pulses = ndimage.binary_dilation(pulses, iterations=2)

    binning = opts.binning or int(np.ceil(max(y_full.shape) / opts.max_fit_size_px))
    h, w = (y_full.shape[0] // binning) * binning, (y_full.shape[1] // binning) * binning
    s = grid.fine_factor
    y = block_mean(y_full[:h, :w], binning)
    mask = ~(block_mean(pulses[:h, :w].astype(float), binning) > 0)
    fine = np.asarray(thickness_mm, dtype=np.float64)[:h * s, :w * s]
    cgrid = ChainGrid((h // binning, w // binning), s * binning, grid.pitch_mm * binning,
                      grid.magnification_minus_one, grid.source_to_detector_mm)
    pre_blur = 0.0
    if binning > 1:
        start_sigma_px = np.hypot(base_start["focal_spot_sigma_mm"] * cgrid.magnification_minus_one,
                                  base_start["detector_sigma_mm"]) / cgrid.pitch_mm
        pre_blur = opts.pre_blur_fraction * start_sigma_px
    model = ChainModel(fine, cgrid, pre_blur)
    problem = _Problem(y, model, mask)
    thickness_coarse = block_mean(fine, s * binning)

    # Linear start for offset and gain on the scene's transmission.
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

    layout = _Layout.build(base0, [], free_base)
    if pre_blur > 0:
        j = layout.names.index(("base", "detector_sigma_mm"))
        fs_mm = base0["focal_spot_sigma_mm"] * cgrid.magnification_minus_one
        floor_mm = float(np.sqrt(max((1.02 * pre_blur * cgrid.pitch_mm) ** 2 - fs_mm**2, 1e-10)))
        layout.lower[j] = floor_mm
        base0["detector_sigma_mm"] = max(base0["detector_sigma_mm"], 1.05 * floor_mm)
    x = layout.pack(base0, {})
    # Rough noise for the first fit, then the model-based estimate, then refit (IRLS).
    mu = model.expected(*layout.unpack(x))

    def noise(mu_now, offset_now):
        if opts.noise_model_binned is not None:
            slope, intercept = opts.noise_model_binned  # v = slope * mu + intercept (absolute DN)
            return float(slope), max(float(intercept + slope * offset_now), 1e-6)
        return estimate_noise_model(y - mu_now, mu_now, offset_now, mask)

    problem.k, problem.s2 = noise(mu, base0["offset_dn"])
    for _ in range(2):
        problem.set_weights(mu, layout.unpack(x)[0]["offset_dn"])
        x, chi2, jac = problem.fit(layout, x, max_nfev=opts.max_nfev)
        mu = model.expected(*layout.unpack(x))
        problem.k, problem.s2 = noise(mu, layout.unpack(x)[0]["offset_dn"])
    problem.set_weights(mu, layout.unpack(x)[0]["offset_dn"])
    resid = (y - mu) * problem.wsqrt
    # Mask positive outliers the full-resolution test missed (clusters of pulses after binning).
    outliers = ndimage.binary_dilation(resid > 6.0, iterations=1)
    if outliers.any():
        problem.mask = mask = mask & ~outliers
        problem.n = int(mask.sum())
    x, chi2, jac = problem.fit(layout, x, max_nfev=opts.max_nfev if outliers.any() else 5)
    say(f"base fit chi2/dof {chi2 / (problem.n - len(x)):.4f}")

    n = problem.n
    log_n = np.log(n)
    base_fit = dict(layout.unpack(x)[0])
    mu = model.expected(*layout.unpack(x))
    z_base = np.where(mask, (y - mu) * problem.wsqrt, 0.0)
    base_chi2 = chi2
    base_chi2_dof = chi2 / (n - len(x))
    base_bic = chi2 + len(x) * log_n
    tile = max(8, opts.tile_px)
    regions = _flagged_regions(z_base, mask, tile, binning, scale=base_chi2_dof)
    profiles_base = residual_profiles(z_base, mask, thickness_coarse, mu, cgrid, binning)

    heldout = _checkerboard(y.shape, max(8, opts.heldout_block_px // binning if binning > 1
                                         else opts.heldout_block_px))
    train, test = mask & ~heldout, mask & heldout

    added: list[AddedTerm] = []
    rankings: list[list[dict]] = []
    terms_now: list[PhysicsTerm] = []
    term_values: dict[str, dict] = {}
    chi2_now = chi2
    jac_now = jac
    remaining = list(candidates)
    while len(added) < opts.max_terms and remaining:
        z = ((y - model.expected(*layout.unpack(x))) * problem.wsqrt)[mask]
        ranking = _rank(problem, layout, x, jac_now, z, remaining)
        rankings.append([{k: v for k, v in r.items() if k != "_perp"} for r in ranking])
        say("ranking: " + ", ".join(f"{r['effect']} S={r['score']:.1f}" for r in ranking[:3]))
        accepted = False
        for cand in ranking[:opts.tries_per_round]:
            if cand["delta_bic_est"] <= opts.accept_delta_bic:
                break
            term = get_term(cand["effect"])
            start = term.probe_params()
            start.update(cand["grid"])
            free = [sp for sp in term.params if not sp.is_grid]
            for spec, value in zip(free, cand["one_step"]):
                lo, hi = spec.prior
                if spec.probe != spec.null and abs(value) > 0.1 * abs(spec.probe) and lo <= value <= hi:
                    start[spec.name] = value
            new_layout = _Layout.build(layout.base_fixed, terms_now + [term], free_base)
            new_layout.lower[:len(free_base)] = layout.lower[:len(free_base)]
            base_cur, _ = layout.unpack(x)
            x0 = new_layout.pack(base_cur, {**term_values, term.name: start})
            x_ext, chi2_ext, jac_ext = problem.fit(new_layout, x0, max_nfev=opts.max_nfev)
            k_term = len(term.params)
            lr = chi2_now - chi2_ext
            delta_bic = lr - k_term * log_n
            if delta_bic <= opts.accept_delta_bic:
                say(f"{term.name}: ΔBIC {delta_bic:.1f} — not accepted")
                continue
            # Held-out blocks: fit both models on the training blocks, compare on the others.
            x_cur_tr, _, _ = problem.fit(layout, x, sel=train, max_nfev=10)
            x_ext_tr, _, _ = problem.fit(new_layout, x_ext, sel=train, max_nfev=10)
            chi_cur_te = float(np.sum(problem.whitened(layout, x_cur_tr, test) ** 2))
            chi_ext_te = float(np.sum(problem.whitened(new_layout, x_ext_tr, test) ** 2))
            gain = chi_cur_te - chi_ext_te
            if gain <= 0:
                say(f"{term.name}: held-out χ² worse by {-gain:.1f} — not accepted")
                continue
            cov = _covariance(jac_ext)
            se = np.sqrt(np.clip(np.diag(cov), 0, None))
            params, unc = {}, {}
            for i, (owner, key) in enumerate(new_layout.names):
                if owner == term.name:
                    params[key], unc[key] = term.spec(key).wrap(float(x_ext[i])), float(se[i])
            confusable = []
            basis = _orthonormal(cand["_perp"], np.linalg.norm(cand["_perp"], axis=0).max())
            for other in ranking[:6]:
                if other["effect"] == term.name:
                    continue
                other_basis = _orthonormal(other["_perp"], np.linalg.norm(other["_perp"], axis=0).max())
                sv = np.linalg.svd(basis.T @ other_basis, compute_uv=False)
                if sv.size and sv.max() > opts.confusable_correlation:
                    confusable.append((other["effect"], float(sv.max())))
            added.append(AddedTerm(term.name, params, unc, float(delta_bic),
                                   chi2_ext / (n - len(x_ext)), cand["score"], float(lr), float(gain),
                                   confusable))
            say(f"added {term.name} ΔBIC {delta_bic:.1f} held-out gain {gain:.1f}")
            layout, x, chi2_now, jac_now = new_layout, x_ext, chi2_ext, jac_ext
            # Earlier terms were refitted jointly: report their current values and errors.
            for earlier in added[:-1]:
                earlier_term = get_term(earlier.effect)
                for i, (owner, key) in enumerate(new_layout.names):
                    if owner == earlier.effect:
                        earlier.params[key] = earlier_term.spec(key).wrap(float(x_ext[i]))
                        earlier.uncertainty[key] = float(se[i])
            terms_now.append(term)
            term_values = {t.name: p for t, p in layout.unpack(x)[1]}
            remaining = [t for t in remaining if t.name != term.name]
            accepted = True
            break
        if not accepted:
            break

    mu = model.expected(*layout.unpack(x))
    z_final = np.where(mask, (y - mu) * problem.wsqrt, 0.0)
    final_dof = chi2_now / (n - len(x))
    q0 = _orthonormal(jac_now, np.linalg.norm(jac_now, axis=0).max(), 1e-9)
    smooth_dbic, smooth_map = _smooth_term_delta_bic(z_final, mask, q0, cgrid)
    leftover = _flagged_regions(z_final, mask, tile, binning, alpha=0.001, scale=final_dof)
    unexplained = bool(leftover) or smooth_dbic > opts.accept_delta_bic
    unexplained_regions = list(leftover)
    if smooth_dbic > opts.accept_delta_bic and not leftover:
        sm = np.abs(smooth_map)
        r, c = np.unravel_index(np.argmax(sm), sm.shape)
        half = tile
        unexplained_regions.append([int(max(0, r - half) * binning), int(max(0, c - half) * binning),
                                    int(min(sm.shape[0], r + half) * binning),
                                    int(min(sm.shape[1], c + half) * binning)])
    if not added and not unexplained:
        message = "nothing missing: residuals are consistent with noise; no term added"
    elif unexplained:
        message = (f"unexplained structure remains at {unexplained_regions} (smooth-term ΔBIC "
                   f"{smooth_dbic:.1f}); not in the library")
    else:
        message = "added " + ", ".join(a.effect for a in added) + "; residuals consistent with noise"
    final_base = layout.unpack(x)[0]
    sigma_coarse_px = np.hypot(final_base["focal_spot_sigma_mm"] * cgrid.magnification_minus_one,
                               final_base["detector_sigma_mm"]) / cgrid.pitch_mm
    if binning > 1 and sigma_coarse_px < 1.0:
        message += (f" (caution: blur {sigma_coarse_px:.2f} binned px < 1 — the {binning}× binned model "
                    "may alias at sharp edges; use a smaller binning)")
    return DiagnosisResult(
        base_chi2_per_dof=float(base_chi2_dof), base_bic=float(base_bic), regions=regions, added=added,
        final_chi2_per_dof=float(final_dof), unexplained=unexplained,
        unexplained_regions=unexplained_regions,
        noise_poisson_gain_dn=float(problem.k * binning**2),
        noise_read_dn=float(np.sqrt(problem.s2) * binning),
        base_params=base_fit, final_base_params=dict(layout.unpack(x)[0]),
        z_base=z_base.astype(np.float32), z_final=z_final.astype(np.float32), mask=mask,
        profiles_base=profiles_base,
        profiles_final=residual_profiles(z_final, mask, thickness_coarse, mu, cgrid, binning),
        rankings=rankings, binning=binning, n_pixels=n, smooth_delta_bic=float(smooth_dbic),
        message=message)


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


def noise_model_from_repeats(frames: np.ndarray, binning: int, n_bins: int = 24) -> tuple[float, float]:
    """``(K, c)``, ``var = K · level + c`` (DN², absolute level), of the mean of ``frames``
    block-averaged ``binning``×, from the repeats themselves.

    The difference of the means of the even and odd frames, halved, has the noise variance of
    the mean of all frames — including its spatially correlated part, which a high-pass
    estimate on one image misses (scintillator light spread makes the noise correlated). Each
    half's global gain/offset difference (source output drift) and a very smooth drift map are
    removed first; then a robust (MAD) variance per bin of block level and a straight line.
    Spots must already be replaced (by the temporal median, as :func:`diagnose_edge_repeats` does).
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
    Gaussian sigma 3 px, normalised to median 1); spots (more than 6 robust sigmas above the
    temporal median) replaced by that median and the frames averaged; the ideal edge map derived from the mean image
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
    grid = ChainGrid(recording.shape, supersample, pixel_pitch_mm, 0.0, 1.0e4)
    open_level = float(np.percentile(recording, 95))
    plate_level = float(np.percentile(recording, 5))
    start = {"offset_dn": dark, "gain_dn": open_level - dark,
             "mu_per_mm": float(np.log((open_level - dark) / max(plate_level - dark, 1.0))),
             "detector_sigma_mm": 2.0 * pixel_pitch_mm, "focal_spot_sigma_mm": 0.0}
    opts = options or DiagnosisOptions()
    from dataclasses import replace

    opts = replace(opts, binning=binning, fixed_offset_dn=dark, noise_model_binned=(slope, intercept))
    return diagnose(recording, obj, grid, start, opts, progress)
