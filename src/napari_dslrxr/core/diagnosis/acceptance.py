"""Rank, compare, then accept: the projected score test ranks the library, the best candidates
are refitted jointly, and the best refit is accepted if it beats the threshold, the held-out
blocks and explain more than a generic smooth additive light field; runner-up, ambiguity, confusable pairs and
parameters at a bound are reported."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..simulation.physics_terms import STAGES, ChainGrid, PhysicsTerm, get_term
from .fitting import Layout, Problem, covariance, orthonormal, resolved, tall_product
from .result import AddedTerm, DiagnosisOptions
from .terms import GENERIC_SIGNATURE, GHOST_COPY, KEYSTONE, SMOOTH_ADDITIVE, SMOOTH_WARP, additive_twin, \
    physical_bounds, probe_params


def _affine_in_free_params(term: PhysicsTerm, probe: dict, active: list[PhysicsTerm]) -> bool:
    """Whether the model image is affine in ``term``'s non-grid parameters: the term is affine
    in them (none probed at its null) and every active term that acts on the light after it
    passes the light on by an affine map."""
    free = [spec for spec in term.params if not spec.is_grid]
    if not free or any(spec.name not in term.linear_params or probe[spec.name] == spec.null for spec in free):
        return False
    stage = STAGES.index(term.stage)
    # the same stage or later: a term of the same stage may be applied after it
    return all(t.passes_light_linearly() for t in active if STAGES.index(t.stage) >= stage)


def _candidate_columns(problem: Problem, layout: Layout, x: np.ndarray, term: PhysicsTerm,
                       grid_point: dict) -> np.ndarray:
    """Whitened Jacobian columns of ``term`` (non-grid params) at its probe point.

    Where the model is affine in them (:func:`_affine_in_free_params`: an amplitude times a
    pattern, seen through affine maps) a column is the change from the current model (the
    term at its null, already evaluated) to the term at its probe value alone, divided by that
    value: the forward difference at the probe point is the same column, at one model
    evaluation more per column set (the mirror ghost's 24 shape-grid points were a third of
    the ranking's time)."""
    base, terms = layout.unpack(x)
    probe = probe_params(term, problem.model.grid)
    probe.update(grid_point)
    if _affine_in_free_params(term, probe, [t for t, _ in terms]):
        f_null = problem.expected(layout, x)
        cols = []
        for spec in term.params:
            if spec.is_grid:
                continue
            alone = {**probe, **{other.name: other.null for other in term.params
                                 if not other.is_grid and other.name != spec.name}}
            f_alone = problem.model.expected(base, terms + [(term, alone)])
            h = probe[spec.name] - spec.null
            cols.append(problem.whiten_field((f_alone - f_null) / h * problem.wsqrt))
        return np.stack(cols, axis=1)
    return forward_difference_columns(problem, base, terms, term, probe)


def forward_difference_columns(problem: Problem, base: dict, terms: list, term: PhysicsTerm,
                               probe: dict) -> np.ndarray:
    """Whitened forward-difference columns of ``term``'s non-grid params at ``probe`` (each
    stepping inside its prior range)."""
    f_probe = problem.model.expected(base, terms + [(term, probe)])
    cols = []
    for spec in term.params:
        if spec.is_grid:
            continue
        plus = dict(probe)
        h = spec.step if probe[spec.name] + spec.step <= spec.prior[1] else -spec.step
        plus[spec.name] += h
        f_plus = problem.model.expected(base, terms + [(term, plus)])
        cols.append(problem.whiten_field((f_plus - f_probe) / h * problem.wsqrt))
    return np.stack(cols, axis=1)


def rank(problem: Problem, layout: Layout, x: np.ndarray, jac0: np.ndarray, z: np.ndarray,
          candidates: list[PhysicsTerm], q0: np.ndarray | None = None) -> list[dict]:
    """Projected score test for each candidate (max over its shape grid). ``q0``:
    :func:`base_span` of ``jac0``, if already computed."""
    if q0 is None:
        q0 = base_span(jac0)
    log_n = np.log(problem.n)
    q0_z = q0.T @ z
    out = []
    for term in candidates:
        best = None
        for gp in term.grid_points():
            cols = _candidate_columns(problem, layout, x, term, gp)
            # S = gᵀ G⁺ g with G = B⊥ᵀB⊥, g = B⊥ᵀz, B⊥ = (1 - q0 q0ᵀ) B: from the small products
            # BᵀB, q0ᵀB and Bᵀz (the long projected columns are formed only for each term's
            # best grid point; the subtraction loses ~1e-16 of |B|², far below the 1e-8 of it
            # under which a direction is not identifiable: projected norm below 1e-4 of the raw)
            q0_cols = q0.T @ cols
            cross = cols.T @ cols
            gram = cross - q0_cols.T @ q0_cols
            grad = cols.T @ z - q0_cols.T @ q0_z
            evals, evecs = np.linalg.eigh(gram)
            ref = float(np.sqrt(np.max(np.diag(cross))))
            keep = evals > (1e-4 * ref) ** 2
            if not keep.any():
                continue
            proj = evecs[:, keep].T @ grad
            score = float(np.sum(proj**2 / evals[keep]))
            if best is None or score > best["score"]:
                coef = evecs[:, keep] @ (proj / evals[keep])
                best = {"effect": term.name, "score": score, "dof": int(keep.sum()),
                        "grid": dict(gp), "one_step": [float(c) for c in coef], "_cols": (cols, q0_cols)}
        if best is None:
            continue
        cols, q0_cols = best.pop("_cols")
        best["_perp"] = cols - tall_product(q0, q0_cols)
        k = len(term.params)
        best["delta_bic_est"] = best["score"] - k * log_n
        out.append(best)
    out.sort(key=lambda d: -d["delta_bic_est"])
    return out


def base_span(jac0: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the current model's Jacobian columns (what the score test projects out)."""
    jac0 = resolved(jac0)
    return orthonormal(jac0, np.linalg.norm(jac0, axis=0).max(), 1e-9)


@dataclass
class _Trial:
    term: PhysicsTerm
    layout: Layout
    x: np.ndarray
    chi2: float
    jac: np.ndarray
    delta_bic: float
    score: float = 0.0
    cand: dict | None = None

    def summary(self) -> dict:
        return {"effect": self.term.name, "delta_bic": round(float(self.delta_bic), 2),
                "score": round(float(self.score), 2)}


#: Fractions of the start value of a term's main amplitude tried before the local refit.
_LINE_SEARCH_FRACTIONS = (1.0, 0.5, 0.25, 0.12, 0.06, 0.03)


def _line_search_main(problem: Problem, layout: Layout, x0: np.ndarray, term: PhysicsTerm) -> np.ndarray:
    """Start the refit from the best of a few fractions of the main amplitude's start value.
    Where the effect is even in its amplitude (two focal-spot lobes at ±a) the gradient vanishes
    at the null and a start far above the true value lets the local fit run into the null and
    stay there; the one-step estimate only fixes the start of terms linear in their amplitude.
    For such a term (``even_in_main``) the fractions are tried at every point of its shape grid:
    the score test chose its grid point by a linearisation at the probe amplitude, which says
    little about an even effect (held-out 2's lobes along x, SNR 32, ranked at the 90°
    axis: the refit from there ran into the null, ΔBIC −19, where a start on the 0° axis
    gains 1105)."""
    i = next((j for j, (owner, key) in enumerate(layout.names) if owner == term.name and key == term.main), None)
    null = term.spec(term.main).null
    if i is None or x0[i] == null:
        return x0
    starts = [x0]
    if term.even_in_main:
        index = {key: j for j, (owner, key) in enumerate(layout.names) if owner == term.name}
        for point in term.grid_points():
            x = x0.copy()
            for key, value in point.items():
                x[index[key]] = value
            if not np.array_equal(x, x0):
                starts.append(x)
    best, best_chi2 = _with_linear_refit(problem, layout, x0)
    for k, start in enumerate(starts):
        for fraction in _LINE_SEARCH_FRACTIONS[0 if k else 1:]:
            x = start.copy()
            x[i] = null + fraction * (start[i] - null)
            x, chi2 = _with_linear_refit(problem, layout, x)
            if chi2 < best_chi2:
                best, best_chi2 = x, chi2
    return best


def _with_linear_refit(problem: Problem, layout: Layout, x: np.ndarray) -> tuple[np.ndarray, float]:
    """``x`` with its offset and gain solved for (linear least squares, exact: the expected image
    is ``offset + gain · light``), and its χ² then."""
    r = problem.whitened(layout, x)
    linear = [j for j, name in enumerate(layout.names) if name in (("base", "offset_dn"), ("base", "gain_dn"))]
    if not linear:
        return x, float(r @ r)
    cols = problem.jacobian(layout, x, f0=r, columns=linear)
    # the 2×2 normal equations (a constant and the model's light: far from collinear)
    step = np.linalg.solve(cols.T @ cols, -(cols.T @ r))
    x = x.copy()
    x[linear] += step
    r = r + cols @ step  # the residual at the new x (exactly linear in these two)
    return x, float(r @ r)


def _refit_with(problem: Problem, layout: Layout, x: np.ndarray, chi2_now: float, term: PhysicsTerm,
                start: dict, opts: DiagnosisOptions, log_n: float) -> _Trial:
    new_layout = Layout.build(layout.base_fixed, layout.terms + [term], problem.model.grid, layout.free_base)
    nb = len(layout.free_base)
    new_layout.lower[:nb] = layout.lower[:nb]
    base_cur, current = layout.unpack(x)
    x0 = new_layout.pack(base_cur, {**{t.name: p for t, p in current}, term.name: start})
    x0 = _line_search_main(problem, new_layout, x0, term)
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


#: Terms that are smooth fields over the whole image, which stray light or haze could mimic;
#: the others (PSF, path, camera, geometry, and scatter, which follows the object) have
#: signatures a smooth field does not produce (a smooth field does absorb a wide scatter in a
#: small field, so scatter is not held to this test).
SMOOTH_FIELD_TERMS = frozenset({"heel_effect", "inverse_square", "vignetting"})
#: Terms that are a smooth displacement of the image, which a keystone (tilted sensor or
#: screen) could mimic: accepted only if their refit beats, by BIC, both the keystone (the
#: lowest-order projective distortion, 2 parameters) and a generic warp (14 parameters).
GEOMETRIC_TERMS = frozenset({"lens_distortion"})
#: Terms a defocused, inverted copy of the image (a lens ghost) partly mimics: the smooth fields
#: (its low frequencies), scatter (a blurred copy of the object), the mirror ghost (a copy) and
#: the terms that follow the local intensity or path (beam hardening, camera gamma: the ghost's
#: light matters most where the object is dark): accepted only if their refit beats the generic
#: ghost copy by BIC. Not the edge-profile terms (glare, focal-spot lobes, lens distortion),
#: which change the shape of edges, as a defocused copy does not.
GHOST_MIMICS = SMOOTH_FIELD_TERMS | {"scatter", "mirror_ghost", "beam_hardening", "detector_gamma"}


def _delta_bic_beyond(problem: Problem, trial: _Trial, additive: _Trial, opts: DiagnosisOptions,
                      log_n: float) -> float:
    """ΔBIC of ``trial``'s term fitted on top of the smooth additive field ``additive``."""
    layout = Layout.build(additive.layout.base_fixed, additive.layout.terms + [trial.term],
                          problem.model.grid, additive.layout.free_base)
    nb = len(additive.layout.free_base)
    layout.lower[:nb] = additive.layout.lower[:nb]
    base, current = additive.layout.unpack(additive.x)
    term_values = {t.name: p for t, p in current}
    term_values[trial.term.name] = {t.name: p for t, p in trial.layout.unpack(trial.x)[1]}[trial.term.name]
    x0 = layout.pack(base, term_values)
    _, chi2_both, _ = problem.fit(layout, x0, max_nfev=opts.max_nfev)
    return float(additive.chi2 - chi2_both - len(trial.term.params) * log_n)


def _additive_twin_trial(problem: Problem, layout: Layout, x: np.ndarray, chi2_now: float, winner: _Trial,
                         opts: DiagnosisOptions, log_n: float) -> _Trial:
    """Refit of the winner's field as additive light (:func:`.terms.additive_twin`), from the
    winner's fitted parameters, with as many evaluations as the winner's final refit."""
    twin = additive_twin(winner.term)
    start = {t.name: p for t, p in winner.layout.unpack(winner.x)[1]}[winner.term.name]
    return _refit_with(problem, layout, x, chi2_now, twin, start,
                       replace(opts, max_nfev=3 * opts.max_nfev), log_n)


def _heldout_gain(problem: Problem, layout: Layout, x: np.ndarray, trial: _Trial,
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
    basis = orthonormal(cand["_perp"], np.linalg.norm(cand["_perp"], axis=0).max())
    for other in ranking[:6]:
        if other["effect"] == cand["effect"]:
            continue
        other_basis = orthonormal(other["_perp"], np.linalg.norm(other["_perp"], axis=0).max())
        sv = np.linalg.svd(basis.T @ other_basis, compute_uv=False)
        if sv.size and sv.max() > threshold:
            out.append((other["effect"], float(sv.max())))
    return out


def compare_round(problem, layout, x, chi2_now, ranking, opts, log_n, train, test, say,
                  out_of_library=lambda: []):
    """Refit the best candidates, accept the best refit (or nothing); returns
    ``(trial or None, AddedTerm or None, comparison list, generic signature or None, the generic
    alternative that explained most of what it rejected or None)``.

    ``out_of_library``: called once a candidate passes, the out-of-library alternatives of the
    current residual (:func:`.structure.out_of_library_alternatives`): a candidate one of them
    explains clearly more than (by the acceptance threshold) only absorbs a part of it."""
    trials = _refit_candidates(problem, layout, x, chi2_now, ranking, opts, log_n, say)
    comparison = [t.summary() for t in trials]
    passing = [t for t in trials if t.delta_bic > opts.accept_delta_bic]
    if not passing:
        return None, None, comparison, None, None
    structural = out_of_library()
    comparison.extend({"effect": a.name, "delta_bic": round(float(a.delta_bic), 2), "generic": True}
                      for a in structural)
    structural_signatures: dict[str, str] = {}  # name -> text, for the alternatives that rejected
    # A smooth-field library term must, fitted on top of a generic smooth additive light field,
    # still gain ΔBIC > threshold. Stray light or haze (outside
    # the library) is then reported unexplained instead of being credited to heel, vignetting
    # or inverse square; a multiplicative term (heel, vignetting) still differs from additive
    # light in the attenuated regions, and a second effect in the same round does not hide it.
    additive = None
    if any(t.term.name in SMOOTH_FIELD_TERMS for t in passing):
        additive = _refit_with(problem, layout, x, chi2_now, SMOOTH_ADDITIVE, SMOOTH_ADDITIVE.null_params(),
                               opts, log_n)
        comparison.append({**additive.summary(), "generic": True})
    geometric: list[_Trial] = []
    if any(t.term.name in GEOMETRIC_TERMS for t in passing):
        for alternative in (KEYSTONE, SMOOTH_WARP):
            geometric.append(_refit_with(problem, layout, x, chi2_now, alternative, alternative.null_params(),
                                         opts, log_n))
            comparison.append({**geometric[-1].summary(), "generic": True})
    ghost: list[_Trial] = []  # fitted once, when a candidate it mimics passes
    # the generic alternatives that rejected a candidate (their signature is reported)
    rejected_by: list[str] = []
    # generic fields that explained more than an earlier candidate: a later (weaker) candidate
    # must still gain ΔBIC > threshold on top of them, or it is only absorbing a part of the
    # out-of-library structure
    rejecting: list[_Trial] = []
    for i, winner in enumerate(passing):
        alternatives = list(geometric) if winner.term.name in GEOMETRIC_TERMS else []
        if winner.term.name in GHOST_MIMICS:
            if not ghost:
                ghost.append(_refit_with(problem, layout, x, chi2_now, GHOST_COPY, probe_params(GHOST_COPY,
                                                                                               problem.model.grid),
                                         opts, log_n))
                comparison.append({**ghost[0].summary(), "generic": True})
            alternatives += ghost
        # an out-of-library alternative that explains clearly more (by the acceptance threshold,
        # as any term against the model without it): the candidate only absorbs a part of it
        better = [g for g in alternatives if g.delta_bic > winner.delta_bic + opts.accept_delta_bic]
        if better:
            g = max(better, key=lambda t: t.delta_bic)
            say(f"{winner.term.name}: the generic {g.term.name} explains more (ΔBIC {g.delta_bic:.1f} against "
                f"{winner.delta_bic:.1f}) — not accepted")
            rejected_by.append(g.term.name)
            _append_once(rejecting, g)
            continue
        clearer = [a for a in structural if a.delta_bic > winner.delta_bic + opts.accept_delta_bic]
        if clearer:
            a = max(clearer, key=lambda t: t.delta_bic)
            say(f"{winner.term.name}: an out-of-library {a.signature} explains more (ΔBIC {a.delta_bic:.1f} "
                f"against {winner.delta_bic:.1f}) — not accepted")
            structural_signatures.setdefault(a.name, f"{a.signature}, explaining more than the library's best "
                                                     f"term ({winner.term.name}: ΔBIC {winner.delta_bic:.0f} "
                                                     f"against {a.delta_bic:.0f}), not matching any library term")
            continue
        # each joint refit of the winner on top of a generic field is done once (the additive
        # field can both have rejected an earlier candidate and be this one's smooth-light test)
        beyond_of: dict[int, float] = {}

        def beyond_generic_field(g: _Trial) -> float:
            if id(g) not in beyond_of:
                beyond_of[id(g)] = _delta_bic_beyond(problem, winner, g, opts, log_n)
            return beyond_of[id(g)]

        beyond_generic = [(g, beyond_generic_field(g)) for g in rejecting]
        if any(b <= opts.accept_delta_bic for _, b in beyond_generic):
            g, b = min(beyond_generic, key=lambda gb: gb[1])
            say(f"{winner.term.name}: ΔBIC {b:.1f} beyond the generic {g.term.name}, which explains "
                f"more — not accepted")
            continue
        beyond = (beyond_generic_field(additive) if winner.term.name in SMOOTH_FIELD_TERMS else float("inf"))
        if np.isfinite(beyond):
            comparison.append({"effect": winner.term.name, "delta_bic_beyond_smooth_light": round(beyond, 2)})
        like_smooth_light = False
        if beyond <= opts.accept_delta_bic:
            if winner.delta_bic < additive.delta_bic - opts.accept_delta_bic:
                say(f"{winner.term.name}: ΔBIC {beyond:.1f} beyond a smooth additive light field, which "
                    f"explains more — not accepted")
                rejected_by.append(SMOOTH_ADDITIVE.name)
                _append_once(rejecting, additive)
                continue
            # as good as the 14-parameter generic field and simpler: named, but not separable
            # from additive light in this recording
            like_smooth_light = True
        # refine the candidate's refit before it is judged further (the comparison refits stop
        # at max_nfev; nonlinear shape parameters need more)
        winner.x, winner.chi2, winner.jac = problem.fit(winner.layout, winner.x, max_nfev=3 * opts.max_nfev,
                                                        jac0=winner.jac)
        winner.delta_bic = float(chi2_now - winner.chi2 - len(winner.term.params) * log_n)
        if like_smooth_light:
            twin = _additive_twin_trial(problem, layout, x, chi2_now, winner, opts, log_n)
            comparison.append({**twin.summary(), "generic": True})
            # the twin has the winner's parameters, so its ΔBIC against the winner is the χ²
            # difference; like any term against the model without it, the multiplying field is
            # credited only if it gains more than the acceptance threshold over the adding one
            if twin.chi2 - winner.chi2 <= opts.accept_delta_bic:
                say(f"{winner.term.name}: its field added to the light fits about as well as multiplying "
                    f"it (χ² {twin.chi2:.1f} against {winner.chi2:.1f}, ΔBIC ≤ {opts.accept_delta_bic:g}) "
                    f"— additive light, not accepted")
                rejected_by.append(SMOOTH_ADDITIVE.name)
                _append_once(rejecting, twin)
                continue
        gain = _heldout_gain(problem, layout, x, winner, train, test)
        if gain <= 0:
            say(f"{winner.term.name}: held-out χ² worse by {-gain:.1f} — not accepted")
            continue
        added = _added_term(problem, winner, trials, additive if like_smooth_light else None, chi2_now, gain,
                            ranking, opts)
        say(f"added {winner.term.name} ΔBIC {winner.delta_bic:.1f} (runner-up "
            f"{added.runner_up or '—'}) held-out gain {gain:.1f}")
        return winner, added, comparison, None, None
    signature = "; ".join([GENERIC_SIGNATURE[name] for name in dict.fromkeys(rejected_by)]
                          + list(structural_signatures.values())) or None
    best_generic = max(rejecting, key=lambda t: t.delta_bic) if rejecting else None
    return None, None, comparison, signature, best_generic


def _append_once(trials: list[_Trial], trial: _Trial) -> None:
    if not any(t is trial for t in trials):
        trials.append(trial)


def _refit_candidates(problem, layout, x, chi2_now, ranking, opts, log_n, say) -> list[_Trial]:
    """Refit the best-ranked candidates (at most ``opts.compare_top``; after the first, only those
    the estimate says gain), best refitted ΔBIC first."""
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
    return trials


def _added_term(problem, winner: _Trial, trials: list[_Trial], smooth_light: _Trial | None, chi2_now: float,
                gain: float, ranking, opts) -> AddedTerm:
    """The accepted term's record: its parameters and errors, its runner-up and whether the two
    are ambiguous. ``smooth_light`` (the generic additive field) is the runner-up when the
    winner does no better than it: named, but not separable from additive light."""
    others = [t for t in trials if t is not winner]
    runner = others[0] if others else None
    cov = covariance(winner.jac)
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
    if smooth_light is not None:
        ambiguous, runner = True, smooth_light
        separating = (f"{winner.term.name}: {winner.term.separating}; smooth additive light (stray "
                      "light, haze): a frame with the object moved or removed (a fluence or lens field "
                      "scales with the transmission, additive light does not)")
    n_dof = problem.n_effective - len(winner.x)
    return AddedTerm(winner.term.name, params, unc, winner.delta_bic, winner.chi2 / n_dof,
                     winner.score, chi2_now - winner.chi2, float(gain),
                     _confusable(winner.cand, ranking, opts.confusable_correlation),
                     runner.term.name if runner else None,
                     float(runner.delta_bic) if runner else None, ambiguous, separating,
                     _at_bound(winner))


def update_reported(added: list[AddedTerm], layout: Layout, x: np.ndarray, jac: np.ndarray) -> None:
    """Earlier terms were refitted jointly: report their current values and errors."""
    se = np.sqrt(np.clip(np.diag(covariance(jac)), 0, None))
    for term_result in added:
        term = get_term(term_result.effect)
        for i, (owner, key) in enumerate(layout.names):
            if owner == term.name:
                term_result.params[key] = term.spec(key).wrap(float(x[i]))
                term_result.uncertainty[key] = float(se[i])
