"""Least squares on the prewhitened residual: the parameter layout (base, registration and
term parameters with their bounds), the problem (recording, mask, noise model, chain model)
and a Levenberg–Marquardt solver on the small normal equations."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..simulation.physics_terms import ChainGrid, PhysicsTerm
from ..simulation.simulator import ChainModel
from . import noise as noise_mod
from .terms import physical_bounds

BASE_FREE = ("offset_dn", "gain_dn", "mu_per_mm", "detector_sigma_mm")
#: Memory for the expected images a problem keeps (a Jacobian's worth at 512² fitted pixels).
EXPECTED_CACHE_BYTES = 32 * 2**20


@dataclass
class Layout:
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
              free_base: tuple[str, ...] = BASE_FREE) -> "Layout":
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


class Problem:
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
        # Expected images of the last points evaluated, most recent last. The Jacobian at the
        # point the optimiser just evaluated needs it again (for the gain column), and a refit
        # from the same point after the noise model changed (new weights, same model) needs the
        # images of its whole Jacobian again.
        self._expected_cache: OrderedDict = OrderedDict()

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
        if self.noise is None or self.noise.is_white:
            # selections lie inside the mask: the zeroing outside it does not change them
            return field_[m]
        return self.noise.whiten(np.where(self.mask, field_, 0.0))[m]

    def expected(self, layout: Layout, x: np.ndarray) -> np.ndarray:
        """The model's expected image at ``x`` (read-only: kept for later calls at the same point)."""
        base, terms = layout.unpack(x)
        key = (tuple(base.items()), tuple((t.name, tuple(p.items())) for t, p in terms))
        cache = self._expected_cache
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
        mu = self.model.expected(base, terms)
        mu.flags.writeable = False
        cache[key] = mu
        while len(cache) > max(1, EXPECTED_CACHE_BYTES // mu.nbytes):
            cache.popitem(last=False)
        return mu

    def whitened(self, layout: Layout, x: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        return self.whiten_field((self.y - self.expected(layout, x)) * self.wsqrt, sel)

    def jacobian(self, layout: Layout, x: np.ndarray, sel: np.ndarray | None = None,
                 f0: np.ndarray | None = None, columns=None) -> np.ndarray:
        """Jacobian of the whitened residual: analytic for offset and gain, else forward differences.
        ``f0``: the whitened residual at ``x``, if already computed; ``columns``: the indices of
        the parameters to differentiate (all if None)."""
        base = layout.unpack(x)[0]
        mu = self.expected(layout, x)
        if f0 is None:
            f0 = self.whiten_field((self.y - mu) * self.wsqrt, sel)
        columns = range(x.size) if columns is None else list(columns)
        # columns written as contiguous rows of the transpose, then one transposing copy (the
        # same numbers; writing each long column with a stride took twice as long)
        jac_t = np.empty((len(columns), f0.size))
        for row, j in enumerate(columns):
            self._jacobian_row(layout, x, sel, f0, base, mu, j, jac_t[row])
        return np.ascontiguousarray(jac_t.T)

    def _jacobian_row(self, layout, x, sel, f0, base, mu, j, out) -> None:
        """Column ``j`` of :meth:`jacobian`, written into ``out``."""
        owner, key = layout.names[j]
        if owner == "base" and key == "offset_dn":
            out[:] = self.whiten_field(-self.wsqrt, sel)
        elif owner == "base" and key == "gain_dn":
            out[:] = self.whiten_field(-(mu - base["offset_dn"]) / base["gain_dn"] * self.wsqrt, sel)
        else:
            h = layout.steps[j] if x[j] + layout.steps[j] <= layout.upper[j] else -layout.steps[j]
            xj = x.copy()
            xj[j] += h
            np.subtract(self.whitened(layout, xj, sel), f0, out=out)
            out /= h

    def fit(self, layout: Layout, x0: np.ndarray, sel: np.ndarray | None = None, max_nfev: int = 40,
            jac0=None):
        """Bounded least squares; returns ``(x, χ², Jacobian at x)``, the Jacobian possibly a
        :class:`DeferredJacobian` (read it with :func:`resolved`). ``jac0``: the Jacobian at
        ``x0`` of an earlier fit of the same problem ending there, if there is one."""
        x, chi2, jac = levenberg_marquardt(lambda x: self.whitened(layout, x, sel),
                                           lambda x, r: self.jacobian(layout, x, sel, r),
                                           x0, layout.lower, layout.upper, max_nfev, jac0=jac0)
        if isinstance(jac, DeferredJacobian):
            jac.require_unchanged(self, ("y", "wsqrt", "noise", "mask"))
        return x, chi2, jac


class DeferredJacobian:
    """The Jacobian at a fit's final point, computed when first read. Most fits' last one is
    never read (a refit that loses the comparison, a held-out fit, a fit after which the noise
    model is renewed), and each costs a model evaluation per parameter (docs/diagnosis.md,
    "The fits' arithmetic").

    The Jacobian depends on the problem's state (recording, weights, noise model, mask): reading
    it after that state changed raises instead of silently computing another one."""

    def __init__(self, compute):
        self._compute = compute
        self._value: np.ndarray | None = None
        self._state: tuple = ()

    def require_unchanged(self, owner, attributes: tuple[str, ...]) -> None:
        self._state = (owner, attributes, tuple(getattr(owner, a) for a in attributes))

    def __call__(self) -> np.ndarray:
        if self._value is None:
            if self._state:
                owner, attributes, values = self._state
                changed = [a for a, v in zip(attributes, values) if getattr(owner, a) is not v]
                if changed:
                    raise RuntimeError(f"deferred Jacobian read after the problem's {', '.join(changed)} changed")
            self._value, self._compute, self._state = self._compute(), None, ()
        return self._value


def resolved(jac) -> np.ndarray:
    """The Jacobian array of a fit's result (computing it if it was deferred)."""
    return jac() if isinstance(jac, DeferredJacobian) else jac


def levenberg_marquardt(fun, jac, x0, lower, upper, max_nfev: int, rel_tol: float = 1e-9, jac0=None):
    """Levenberg–Marquardt on the small normal equations, with an active set for the bounds.

    ``jac(x, r)`` gets the residual ``r = fun(x)`` already computed; ``jac0``, if given, is
    the Jacobian at ``x0`` (within the bounds). The residual vectors are
    long (every pixel) and the parameters few (≤ ~30): ``JᵀJ`` is a
    tiny matrix, so each step costs one Jacobian, not an SVD of it. Parameters at a bound whose
    gradient points outward are held for that step, and so are those the step would carry past
    a bound (held there, the step of the others solved again: :func:`_bounded_step`). Stops when χ² improves by less than
    ``tol = max(1e-3, rel_tol·χ²)`` (far below what a BIC comparison resolves), when the
    Gauss–Newton step's predicted improvement ``gᵀ(JᵀJ)⁻¹g`` (the most any step can gain under
    the linearised model) is below ``tol``, or after ``max_nfev`` residual evaluations.

    The damping λ is divided by 10 after a step whose gain was at least 3/4 of the quadratic
    model's prediction (the model is good: take longer steps), by 3 after other accepted steps,
    and multiplied by 4 after a rejected one.
    """
    x = np.clip(np.asarray(x0, float), lower, upper)
    r = fun(x)
    chi2 = float(r @ r)
    nfev, lam = 1, 1e-3
    j = jac(x, r) if jac0 is None else resolved(jac0)
    while nfev < max_nfev:
        a = j.T @ j
        g = j.T @ r
        free, predicted_gn = _gauss_newton_gain(a, g, x, lower, upper)
        # converged: no step can gain more than the Gauss-Newton step's prediction (the trial
        # steps at such a point only fail on rounding, each costing a model evaluation)
        if not free.any() or 0.0 <= predicted_gn < max(1e-3, rel_tol * chi2):
            break
        accepted = False
        while nfev < max_nfev:
            try:
                step = _bounded_step(a, g, x, lower, upper, free, lam, np.maximum(np.diag(a), 1e-30))
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
        predicted = -float(2.0 * g @ step + step @ a @ step)
        x, r, chi2 = x_new, r_new, chi2_new
        lam = max(lam / (10.0 if gain >= 0.75 * predicted else 3.0), 1e-9)
        tol = max(1e-3, rel_tol * chi2)
        if gain < tol or nfev >= max_nfev or _converged_on(j, r, x, lower, upper, 0.1 * tol):
            # the Jacobian at the final point only if a caller reads it
            return x, chi2, DeferredJacobian(lambda x=x, r=r: jac(x, r))
        j = jac(x, r)
    return x, chi2, j


def _gauss_newton_gain(a, g, x, lower, upper) -> tuple[np.ndarray, float]:
    """The free parameters (not at a bound their gradient points past) and the Gauss–Newton
    step's predicted gain ``gᵀ(JᵀJ)⁻¹g`` over them (inf if singular), from ``a = JᵀJ`` and
    ``g = Jᵀr``."""
    free = ~(((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0)))
    if not free.any():
        return free, 0.0
    af, gf = a[np.ix_(free, free)], g[free]
    try:
        return free, float(gf @ np.linalg.solve(af + 1e-12 * np.diag(np.maximum(np.diag(af), 1e-30)), gf))
    except np.linalg.LinAlgError:
        return free, np.inf


def _converged_on(j, r, x, lower, upper, tol: float) -> bool:
    """The convergence test of :func:`levenberg_marquardt` (no step can gain ``tol``) at the new
    point ``x`` with residual ``r``, on the previous point's Jacobian ``j``: a step that close to
    the minimum barely changes it, and the test then spares a Jacobian the fit would only
    compute to find it has converged (with a tenth of the tolerance, for the approximation)."""
    free, predicted = _gauss_newton_gain(j.T @ j, j.T @ r, x, lower, upper)
    return not free.any() or 0.0 <= predicted < tol


def _bounded_step(a, g, x, lower, upper, free, lam, diag, max_rounds: int = 4) -> np.ndarray:
    """The damped Gauss–Newton step of the parameters ``free``, solved again with the
    parameters its last solution pushed past a bound held at that bound: a clipped step is no
    longer the minimiser of the linearised problem, and the others must take up what the
    clipped ones cannot do (a term's amplitude run into its null at the start of a refit
    otherwise costs several rejected trials)."""
    step = np.zeros_like(x)
    free = free.copy()
    for _ in range(max_rounds):
        fixed = ~free
        rhs = -(g[free] + a[np.ix_(free, fixed)] @ step[fixed])
        step[free] = np.linalg.solve(a[np.ix_(free, free)] + lam * np.diag(diag[free]), rhs)
        out = free & ((x + step < lower) | (x + step > upper))
        if not out.any():
            break
        step[out] = np.clip(x + step, lower, upper)[out] - x[out]
        free &= ~out
        if not free.any():
            break
    return step


def covariance(jac) -> np.ndarray:
    jac = resolved(jac)
    jtj = jac.T @ jac
    try:
        return np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(jtj)


#: rows per block of :func:`tall_product` (small enough that the BLAS runs each block on one thread)
_TALL_PRODUCT_ROWS = 8192


def tall_product(tall: np.ndarray, small: np.ndarray) -> np.ndarray:
    """``tall @ small`` for a tall ``(n, k)`` and a small ``(k, d)`` matrix, block of rows by block.

    The same numbers to the bit (each output element is the same length-``k`` dot product,
    whichever block computes it), without the BLAS's threads: for so thin a product, their
    hand-offs cost a core's time for nothing and up to 50× the wall time when the cores are busy.
    """
    out = np.empty((tall.shape[0], small.shape[1]), dtype=np.result_type(tall, small))
    for start in range(0, tall.shape[0], _TALL_PRODUCT_ROWS):
        np.matmul(tall[start:start + _TALL_PRODUCT_ROWS], small, out=out[start:start + _TALL_PRODUCT_ROWS])
    return out


def orthonormal(columns: np.ndarray, reference_norm: float, rel_tol: float = 1e-4) -> np.ndarray:
    """Orthonormal basis of the column space, dropping directions below ``rel_tol`` of the norm.

    QR of the tall matrix, then an SVD of the small triangular factor (cheap for n >> d).
    """
    if columns.shape[1] == 0:
        return columns
    q, r = np.linalg.qr(columns, mode="reduced")
    u, s, _ = np.linalg.svd(r)
    keep = s > rel_tol * max(reference_norm, 1e-300)
    return q @ u[:, keep]
