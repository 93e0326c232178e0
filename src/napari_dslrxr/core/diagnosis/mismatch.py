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

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError, ParameterError
from ..robust import robust_sigma
from ..simulation.physics_terms import LIBRARY, ChainGrid, PhysicsTerm, get_term
from ..simulation.simulator import ChainModel, Scene, block_mean
from . import noise as noise_mod
from .acceptance import base_span, compare_round, rank, update_reported
from .fitting import BASE_FREE, Layout, Problem
from .locating import checkerboard, multiscale_maps, residual_profiles, signed_edge_distance, \
    smooth_term_delta_bic
from .result import AddedTerm, DiagnosisOptions, DiagnosisResult
from .structure import flagged_regions, out_of_library_alternatives, ripple_phase_profile, structure_tests
from .terms import GENERIC_SIGNATURE, KEYSTONE, REGISTRATION

__all__ = ["AddedTerm", "BASE_FREE", "DiagnosisOptions", "DiagnosisResult", "auto_binning", "diagnose",
           "diagnose_scene", "multiscale_maps", "parse_binning", "residual_profiles"]


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
        raise ParameterError(f"binning must be 'auto' or an integer >= 1, got {text!r}") from None
    if value < 1:
        raise ParameterError(f"binning must be 'auto' or an integer >= 1, got {text!r}")
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
            sigma[b] = max(robust_sigma(h), 1.12 * float(np.std(trimmed)))
    sigma = np.maximum(sigma, max(float(np.max(sigma)) * 1e-3, 1e-12))
    return hp > z_threshold * sigma[which]


def _noise_model(problem: Problem, mu: np.ndarray, offset: float, opts: DiagnosisOptions,
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
    problem = Problem(y, model, mask)
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
    layout = Layout.build(base0, registration, cgrid, free_base)
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


def _registration_report(layout: Layout, x: np.ndarray, binning: int) -> dict:
    out = {}
    for i, (owner, key) in enumerate(layout.names):
        if owner == "registration_shift":
            out[key] = float(x[i]) * binning  # recording pixels
        elif owner == "registration_affine" and key == "scale":
            out["scale"] = float(x[i])
        elif owner == "registration_affine":
            out["rotation_deg"] = float(np.rad2deg(x[i]))
    return out


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


@dataclass
class _Fit:
    """The current model: parameter layout, values, χ² and Jacobian."""

    layout: Layout
    x: np.ndarray
    chi2: float
    jac: np.ndarray
    _span: np.ndarray | None = None

    def span(self) -> np.ndarray:
        """:func:`.acceptance.base_span` of the Jacobian, computed once (the last ranking and the
        final checks project out the same model)."""
        if self._span is None:
            self._span = base_span(self.jac)
        return self._span


@dataclass
class _Search:
    fit: _Fit
    added: list[AddedTerm]
    rankings: list
    comparisons: list
    generic_signature: str | None
    #: the generic alternative that rejected the last round's candidates (never part of the
    #: model; the banding re-test discounts what it explains)
    generic_fit: _Fit | None = None


def _banding(setup: _Setup, problem: Problem, fit: _Fit) -> tuple[np.ndarray, list[tuple[str, int, float, int]]]:
    """Row and column banding (per-line offsets of the camera read-out) in the residual of
    ``fit``: the non-smooth part of the per-line mean residual (minus a Gaussian smoothing over 8
    lines, so a smooth gradient such as heel or vignetting is kept) is tested (χ² over lines at
    ``α/9``). Returns the recording with the failing axes' line offsets subtracted and, per
    failing axis, ``(name, strongest line in recording pixels, χ², lines)``."""
    from scipy import ndimage, special

    mu = setup.model.expected(*fit.layout.unpack(fit.x))
    # Lines are judged on flat pixels only: read-out banding runs through the whole line, while
    # an edge-profile mismatch along a long straight edge of the object (a focal-spot lobe,
    # glare) also concentrates on a few lines
    offset = fit.layout.unpack(fit.x)[0]["offset_dn"]
    flat = noise_mod.flat_pixels(mu, problem.noise.variance(mu, offset), problem.mask,
                                 tolerance_sigma=3.0, size=5)
    y_in = problem.y
    y = y_in.copy()
    found = []
    for axis, name in ((1, "row"), (0, "column")):
        # the residual without the lines already removed: weighted row offsets would
        # otherwise show up in the column means wherever the weights follow the object
        problem.y = y
        try:
            z = np.zeros(setup.y.shape)
            z[problem.mask] = problem.whitened(fit.layout, fit.x)
        finally:
            problem.y = y_in
        z[~flat] = 0.0
        counts = flat.sum(axis=axis)
        use = counts > 10
        line_z = np.where(use, z.sum(axis=axis) / np.sqrt(np.maximum(counts, 1)), 0.0)
        high = line_z - ndimage.gaussian_filter1d(line_z, 8.0, mode="reflect")
        kept = 1.0 - 1.0 / (2.0 * np.sqrt(np.pi) * 8.0)  # variance a white sequence keeps
        stat = float(np.sum(high[use] ** 2) / kept)
        if special.chdtrc(int(use.sum()), stat) >= 1e-3 / 9:  # χ² survival function
            continue
        # The offsets subtracted come from every unmasked pixel of the line, not only the flat
        # ones the test judged: read-out banding offsets the whole line, and the flat set
        # changes from line to line with the object, so over it alone a smooth mismatch (a
        # heel) gives line means that jump at the object's edges (offsets 3× further from the
        # true ones with a heel, and 1.3× from pixel noise alone, in the 128² sample scene).
        resid = np.where(problem.mask, y - mu, 0.0)
        line_dn = resid.sum(axis=axis) / np.maximum(problem.mask.sum(axis=axis), 1)
        offsets = line_dn - ndimage.gaussian_filter1d(line_dn, 8.0, mode="reflect")
        y = y - (offsets[:, None] if axis == 1 else offsets[None, :])
        found.append((name, int(np.argmax(np.abs(high))) * setup.binning, stat, int(use.sum())))
    return y, found


def _renew_noise(problem: Problem, setup: _Setup, layout: Layout, x: np.ndarray, opts: DiagnosisOptions) -> None:
    """Re-estimate the noise model from the residual of the model ``x``."""
    mu = setup.model.expected(*layout.unpack(x))
    offset = layout.unpack(x)[0]["offset_dn"]
    problem.set_noise(_noise_model(problem, mu, offset, opts, problem.noise), mu, offset)


def _remove_banding(setup: _Setup, problem: Problem, fit: _Fit, opts: DiagnosisOptions, say) -> tuple[_Fit, bool]:
    """Banding is outside the library and, left in, is absorbed by line-like terms (a ghost
    shifted along the other axis): if the base residual shows it, it is subtracted before the
    search. Only provisionally: :func:`_retest_banding` decides after the search."""
    y, found = _banding(setup, problem, fit)
    if not found:
        return fit, False
    for name, _, stat, lines in found:
        say(f"{name} banding removed before the search (χ² {stat:.0f} over {lines} {name}s)")
    problem.y = setup.y = y
    _renew_noise(problem, setup, fit.layout, fit.x, opts)  # banding inflates the variogram
    x, chi2, jac = problem.fit(fit.layout, fit.x, max_nfev=10)
    return _Fit(fit.layout, x, chi2, jac), True


def _retest_banding(setup: _Setup, problem: Problem, search: _Search, y_recorded: np.ndarray,
                    say) -> list[str]:
    """Re-test the banding removed before the search, on the recording as recorded and the final
    model. The base residual's line test also fails on structure with sharp line-to-line
    changes along the object's edges that a library term explains (veiling glare, a ghost):
    banding the found terms explain is dropped, and only what still fails is subtracted and
    reported."""
    problem.y = setup.y = y_recorded
    fit = search.fit
    # judged against the generic alternative that rejected candidates, when there is one: line
    # structure an out-of-library copy or field explains (a lens ghost's sharp inverted edges)
    # is not read-out banding
    y, found = _banding(setup, problem, search.generic_fit or fit)
    if not found:
        say("banding seen before the search is explained by the added terms or the generic alternative")
    problem.y = setup.y = y
    x, chi2, jac = problem.fit(fit.layout, fit.x, max_nfev=10)
    fit = search.fit = _Fit(fit.layout, x, chi2, jac)
    update_reported(search.added, fit.layout, fit.x, fit.jac)
    return [f"{name} banding (strongest at {name} {where}; per-line offsets subtracted)"
            for name, where, _, _ in found]


def _locate(setup: _Setup, problem: Problem, fit: _Fit, opts: DiagnosisOptions) -> dict:
    """Base-model residual: map, flagged regions, profiles, χ²/dof and BIC."""
    mu = setup.model.expected(*fit.layout.unpack(fit.x))
    z_base = np.zeros(setup.y.shape)
    z_base[problem.mask] = problem.whitened(fit.layout, fit.x)
    return {"z": z_base, "base_params": dict(fit.layout.unpack(fit.x)[0]),
            "chi2_per_dof": fit.chi2 / (problem.n_effective - len(fit.x)),
            "bic": fit.chi2 + len(fit.x) * np.log(problem.n),
            "regions": flagged_regions(z_base, problem.mask, max(8, opts.tile_px), setup.binning),
            "profiles": residual_profiles(z_base, problem.mask, setup.thickness, mu, setup.grid, setup.binning),
            "noise": problem.noise.to_json(setup.binning)}


def _search(setup: _Setup, problem: Problem, fit: _Fit, candidates: list[PhysicsTerm],
            opts: DiagnosisOptions, say) -> _Search:
    """Rank, compare, accept — until no candidate is accepted; the noise model is re-estimated
    after each accepted term (its weights then describe the better model's residual)."""
    binning, mask = setup.binning, problem.mask
    heldout = checkerboard(setup.y.shape, max(8, opts.heldout_block_px // binning if binning > 1
                                              else opts.heldout_block_px))
    train, test = mask & ~heldout, mask & heldout
    log_n = np.log(problem.n)
    result = _Search(fit, [], [], [], None)
    remaining = list(candidates)
    while len(result.added) < opts.max_terms and remaining:
        layout, x = fit.layout, fit.x
        ranking = rank(problem, layout, x, fit.jac, problem.whitened(layout, x), remaining, fit.span())
        result.rankings.append([{k: v for k, v in r.items() if k != "_perp"} for r in ranking])
        say("ranking: " + ", ".join(f"{r['effect']} S={r['score']:.1f}" for r in ranking[:3]))
        trial, term_result, comparison, result.generic_signature, generic = compare_round(
            problem, layout, x, fit.chi2, ranking, opts, log_n, train, test, say,
            lambda: _out_of_library(setup, problem, layout, x, log_n, opts))
        if generic is not None:
            result.generic_fit = _Fit(generic.layout, generic.x, generic.chi2, generic.jac)
        result.comparisons.append(comparison)
        if trial is None:
            break
        result.added.append(term_result)
        _renew_noise(problem, setup, trial.layout, trial.x, opts)
        x, chi2, jac = problem.fit(trial.layout, trial.x, max_nfev=5)
        fit = result.fit = _Fit(trial.layout, x, chi2, jac)
        update_reported(result.added, fit.layout, fit.x, fit.jac)
        remaining = [t for t in remaining if t.name != trial.term.name]
    return result


def _out_of_library(setup: _Setup, problem: Problem, layout: Layout, x: np.ndarray, log_n: float,
                    opts: DiagnosisOptions) -> list:
    """The out-of-library alternatives (ripple, spots) of the residual of the model ``x``."""
    mu = problem.expected(layout, x)  # the cached image the ranking's residual came from
    z = np.zeros(setup.y.shape)
    z[problem.mask] = problem.whitened(layout, x)
    noise_sd = np.sqrt(problem.noise.variance(mu, layout.unpack(x)[0]["offset_dn"]))
    return out_of_library_alternatives(z, problem.mask, mu, noise_sd, setup.binning, log_n, opts.accept_delta_bic)


def _final_checks(setup: _Setup, problem: Problem, search: _Search, located: dict,
                  opts: DiagnosisOptions) -> DiagnosisResult:
    """Structure tests of the final residual, the message, and the result."""
    fit, mask, binning, cgrid = search.fit, problem.mask, setup.binning, setup.grid
    tile = max(8, opts.tile_px)
    mu = setup.model.expected(*fit.layout.unpack(fit.x))
    z_final = np.zeros(setup.y.shape)
    z_final[mask] = problem.whitened(fit.layout, fit.x)
    final_dof = fit.chi2 / (problem.n_effective - len(fit.x))
    if search.added:
        search.added[-1].chi2_per_dof = final_dof
    q0 = fit.span()
    smooth_dbic, smooth_map = smooth_term_delta_bic(z_final, mask, q0, cgrid)
    radius = np.sqrt(((cgrid.x**2 + cgrid.y**2) / 2.0) * np.ones(setup.y.shape))
    noise_sd = np.sqrt(problem.noise.variance(mu, fit.layout.unpack(fit.x)[0]["offset_dn"]))
    structure = structure_tests(z_final, mask, fit.chi2, problem.n_effective - len(fit.x), mu,
                                signed_edge_distance(setup.thickness), radius, tile, binning,
                                noise_samples=problem.noise.n_samples,
                                min_ghost_lag=3 if problem.noise.is_white else noise_mod.SHORT_LAG_PX + 2,
                                noise_sd_dn=noise_sd)
    # A keystone (tilted camera or screen) is too weak for lens distortion to pass before the
    # generic warps judge it, yet clear in a 2-parameter test: its projected score on the final
    # residual (exact for its linear parameters) against the acceptance criterion of a term
    keystone_rank = rank(problem, fit.layout, fit.x, fit.jac, z_final[mask], [KEYSTONE], q0)
    keystone_dbic = keystone_rank[0]["delta_bic_est"] if keystone_rank else float("-inf")
    structure["tests"]["keystone"] = {"delta_bic_est": float(keystone_dbic),
                                      "signature": GENERIC_SIGNATURE["keystone"]}
    # (not beside a generic alternative that rejected candidates: a large unexplained residual
    # projects on the keystone too)
    if keystone_dbic > opts.accept_delta_bic and search.generic_signature is None:
        structure["failed"].append("keystone")
        structure["signatures"].insert(0, GENERIC_SIGNATURE["keystone"])
    unexplained_regions = list(structure["tests"]["tiles"]["regions"])
    if (structure["failed"] or search.generic_signature) and not unexplained_regions:
        sm = np.abs(smooth_map)
        r, c = np.unravel_index(np.argmax(sm), sm.shape)
        unexplained_regions.append([int(max(0, r - tile) * binning), int(max(0, c - tile) * binning),
                                    int(min(sm.shape[0], r + tile) * binning),
                                    int(min(sm.shape[1], c + tile) * binning)])
    profiles_final = residual_profiles(z_final, mask, setup.thickness, mu, cgrid, binning)
    profiles_base = located["profiles"]
    if "intensity_ripple" in structure["failed"]:  # its evidence, before and after, for the report
        period = structure["tests"]["intensity_ripple"]["period_dn"]
        profiles_base = {**profiles_base, "ripple_phase": ripple_phase_profile(
            located["z"][mask], mu[mask], noise_sd[mask], binning, period)}
        profiles_final["ripple_phase"] = ripple_phase_profile(z_final[mask], mu[mask], noise_sd[mask],
                                                              binning, period)
    final_base = fit.layout.unpack(fit.x)[0]
    unexplained, message = _compose_message(search.added, structure, search.generic_signature, binning,
                                            _blur_sigma_px(final_base, cgrid))
    noise_json = problem.noise.to_json(binning)
    noise_json["base"] = located["noise"]
    return DiagnosisResult(
        base_chi2_per_dof=float(located["chi2_per_dof"]), base_bic=float(located["bic"]),
        regions=located["regions"], added=search.added, final_chi2_per_dof=float(final_dof),
        unexplained=unexplained, unexplained_regions=unexplained_regions if unexplained else [],
        noise_poisson_gain_dn=float(problem.noise.poisson_gain * binning**2),
        noise_read_dn=float(np.sqrt(problem.noise.read_variance) * binning),
        base_params=located["base_params"], final_base_params=dict(final_base),
        z_base=located["z"].astype(np.float32), z_final=z_final.astype(np.float32), mask=mask,
        profiles_base=profiles_base, profiles_final=profiles_final,
        rankings=search.rankings, binning=binning, n_pixels=problem.n, smooth_delta_bic=float(smooth_dbic),
        message=message, registration=_registration_report(fit.layout, fit.x, binning), noise=noise_json,
        structure=structure, signatures=([search.generic_signature] if search.generic_signature else [])
        + structure["signatures"], comparisons=search.comparisons)


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

    Notes
    -----
    Runs with the BLAS limited to one thread (``threadpoolctl``, for the whole process while it
    runs): its thousands of small products gain nothing from more, and OpenBLAS's idle workers
    spin between them (at 512², 29-31 s of CPU for 17-19 s of wall time, against 18 s for 18 s
    on one thread), taking a core from a GUI or another job.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(recording, thickness_mm, grid, base_start, options, progress)


def _diagnose(recording, thickness_mm, grid, base_start, options, progress) -> DiagnosisResult:
    opts = options or DiagnosisOptions()
    say = progress or (lambda _msg: None)
    y_full = np.asarray(recording, dtype=np.float64)
    candidates = _check_inputs(y_full, thickness_mm, grid, base_start, opts)
    setup = _prepare(y_full, thickness_mm, grid, base_start, opts)
    problem, layout, x, chi2, jac = _fit_base(setup, base_start, opts)
    fit = _Fit(layout, x, chi2, jac)
    say(f"base fit chi2/dof {chi2 / (problem.n_effective - len(x)):.4f}")
    located = _locate(setup, problem, fit, opts)
    y_recorded = problem.y
    fit, banding_removed = _remove_banding(setup, problem, fit, opts, say)
    search = _search(setup, problem, fit, candidates, opts, say)
    banding = _retest_banding(setup, problem, search, y_recorded, say) if banding_removed else []
    result = _final_checks(setup, problem, search, located, opts)
    if banding:
        _add_signatures(result, banding)
    return result


def _add_signatures(result: DiagnosisResult, signatures: list[str]) -> None:
    result.signatures = signatures + result.signatures
    result.unexplained = True
    if not result.unexplained_regions:
        h, w = result.z_final.shape
        result.unexplained_regions = [[0, 0, h * result.binning, w * result.binning]]
    named = ", ".join(a.effect for a in result.added)
    result.message = ((f"added {named}; " if named else "") + "unexplained structure remains: "
                      + "; ".join(result.signatures) + " (not in the library)")


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
