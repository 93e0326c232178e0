"""Terms the diagnosis fits besides the physics library, and the scene's physical bounds.

* **Registration** (always in the base model): a sub-pixel shift of the object on the detector
  (exact, a phase ramp in the transfer function) and a small scale (magnification error) and
  rotation about the image centre (first order: ``O = L - ∇L · δ(q)``; the displacements these
  describe are a fraction of a pixel, where the first-order form is accurate). Without them a
  0.1 px shift or a 0.05 % magnification error leaves edge dipoles that library terms absorb.
* **Out-of-library competitors** (never named as physics): a multiplicative and an additive
  2-D Legendre surface of degree 4, a displacement field of degree 2-3, a keystone (the
  first-order projective distortion of a tilted camera or screen) and a lens ghost (a
  defocused copy of the image inverted about the optical axis). A library term is only
  credited with a mismatch if it explains it better (by BIC) than these do; otherwise the
  mismatch is reported unexplained.
* **Physical bounds** of library terms from the scene (SDD, field size, plausible lenses and
  physical magnitudes), tighter than the library's generic prior ranges.
"""

from __future__ import annotations

import numpy as np

from ..simulation.physics_terms import ChainGrid, ChainState, ParamSpec, PhysicsTerm

P = ParamSpec


def _apply_shift(state: ChainState, p: dict) -> None:
    g = state.grid
    sx, sy = p["shift_x_px"], p["shift_y_px"]
    if sx == 0.0 and sy == 0.0:
        return
    ramp = g.cached(("registration_shift", sx, sy), lambda: (
        np.exp(-2j * np.pi * sy * g.fy) * np.exp(-2j * np.pi * sx * g.fx)))
    state.transfer = state.transfer * ramp


def _apply_affine(state: ChainState, p: dict) -> None:
    scale, rot = p["scale"], p["rotation_rad"]
    if scale == 0.0 and rot == 0.0:
        return
    g = state.grid
    xs = g.x * g.half_size_px  # pixels from the image centre
    ys = g.y * g.half_size_px
    _displace(state, scale * xs - rot * ys, scale * ys + rot * xs)


def _displace(state: ChainState, dx: np.ndarray, dy: np.ndarray) -> None:
    """Move the light by a displacement field of a fraction of a pixel, to first order:
    ``light - (∇light · δ)``, computed in place in ``dx`` and ``dy`` (new arrays the caller
    gives up; this runs at every model evaluation)."""
    gy, gx = state.light_gradient()
    np.multiply(gx, dx, out=dx)
    np.multiply(gy, dy, out=dy)
    np.add(dx, dy, out=dx)
    state.light = np.subtract(state.light, dx, out=dx)


REGISTRATION_SHIFT = PhysicsTerm(
    "registration_shift", "psf",
    (P("shift_x_px", 0.0, (-3.0, 3.0), 0.0, 0.01, unit="px"),
     P("shift_y_px", 0.0, (-3.0, 3.0), 0.0, 0.01, unit="px")),
    "shift_x_px", _apply_shift,
    physics="Sub-pixel shift of the object on the detector (registration, fitted-grid pixels).")
REGISTRATION_AFFINE = PhysicsTerm(
    "registration_affine", "optics",
    (P("scale", 0.0, (-0.01, 0.01), 0.0, 1e-5), P("rotation_rad", 0.0, (-0.02, 0.02), 0.0, 1e-5)),
    "scale", _apply_affine,
    physics="Magnification error and small rotation about the image centre (registration).",
    linear_params=("scale", "rotation_rad"), linear_in_light=True)
REGISTRATION = (REGISTRATION_SHIFT, REGISTRATION_AFFINE)


def _legendre_basis(grid: ChainGrid, degree: int = 4) -> np.ndarray:
    def make():
        from numpy.polynomial import legendre

        xs = grid.x / max(float(np.abs(grid.x).max()), 1e-9)
        ys = grid.y / max(float(np.abs(grid.y).max()), 1e-9)
        cols = []
        for i in range(degree + 1):
            for j in range(degree + 1 - i):
                if i == 0 and j == 0:
                    continue
                ci, cj = np.zeros(i + 1), np.zeros(j + 1)
                ci[i], cj[j] = 1.0, 1.0
                cols.append(legendre.legval(ys, ci) * legendre.legval(xs, cj))
        return np.stack([np.broadcast_to(c, grid.shape) for c in cols])
    return grid.cached(("legendre", degree), make)


def _surface(state: ChainState, p: dict) -> np.ndarray:
    basis = _legendre_basis(state.grid)
    coef = np.array([p[f"c{i:02d}"] for i in range(basis.shape[0])])
    return np.tensordot(coef, basis, axes=1)


def _apply_smooth_gain(state: ChainState, p: dict) -> None:
    state.light = state.light * (1.0 + _surface(state, p))


def _apply_smooth_additive(state: ChainState, p: dict) -> None:
    state.light = state.light + _surface(state, p)


_N_SMOOTH = 14  # Legendre products of total degree 1..4
_COEFS = tuple(P(f"c{i:02d}", 0.0, (-1.0, 1.0), 0.0, 1e-3) for i in range(_N_SMOOTH))
_LINEAR_COEFS = dict(linear_params=tuple(c.name for c in _COEFS), linear_in_light=True)
SMOOTH_GAIN = PhysicsTerm("smooth_gain", "optics", _COEFS, "c00", _apply_smooth_gain,
                          physics="Generic smooth multiplicative field (not physics: a competitor).",
                          **_LINEAR_COEFS)
SMOOTH_ADDITIVE = PhysicsTerm("smooth_additive", "camera", _COEFS, "c00", _apply_smooth_additive,
                              physics="Generic smooth additive light (not physics: a competitor).",
                              **_LINEAR_COEFS)

#: Monomials x^i y^j of the generic warp: total degree 2 and 3 (degree 0 and 1 are the
#: registration's shift, scale and rotation).
_WARP_POWERS = tuple((i, d - i) for d in (2, 3) for i in range(d + 1))


def _apply_smooth_warp(state: ChainState, p: dict) -> None:
    g = state.grid
    gy, gx = state.light_gradient()
    dx = sum(p[f"x{k:02d}"] * g.x**i * g.y**j for k, (i, j) in enumerate(_WARP_POWERS))
    dy = sum(p[f"y{k:02d}"] * g.x**i * g.y**j for k, (i, j) in enumerate(_WARP_POWERS))
    state.light = state.light - (gx * dx + gy * dy)  # first order, displacements in pixels


SMOOTH_WARP = PhysicsTerm(
    "smooth_warp", "optics",
    tuple(P(f"{axis}{k:02d}", 0.0, (-3.0, 3.0), 0.0, 1e-3, unit="px")
          for axis in "xy" for k in range(len(_WARP_POWERS))),
    "x00", _apply_smooth_warp,
    physics="Generic smooth geometric distortion, displacements of degree 2-3 (not physics: a "
            "competitor of lens distortion).",
    linear_params=tuple(f"{axis}{k:02d}" for axis in "xy" for k in range(len(_WARP_POWERS))),
    linear_in_light=True)


def _apply_keystone(state: ChainState, p: dict) -> None:
    tx, ty = p["tilt_x"], p["tilt_y"]
    if tx == 0.0 and ty == 0.0:
        return
    g = state.grid
    # the first-order projective map of a plane seen at a small tilt: the local scale changes
    # linearly across the field, δ(q) = (tx·x + ty·y)·q (x, y in half-field units, q in px)
    local_scale = tx * g.x + ty * g.y
    _displace(state, local_scale * (g.x * g.half_size_px), local_scale * (g.y * g.half_size_px))


KEYSTONE = PhysicsTerm(
    "keystone", "optics",
    (P("tilt_x", 0.0, (-0.02, 0.02), 0.0, 1e-5), P("tilt_y", 0.0, (-0.02, 0.02), 0.0, 1e-5)),
    "tilt_x", _apply_keystone,
    physics="Keystone of a camera or screen tilted against the other (the first-order projective "
            "distortion, 2 parameters; not in the library: a competitor of lens distortion).",
    linear_params=("tilt_x", "tilt_y"), linear_in_light=True)


def _apply_ghost_copy(state: ChainState, p: dict) -> None:
    eps = p["epsilon"]
    if eps == 0.0:
        return
    g = state.grid
    sigma = p["sigma_px"]
    # point inversion about the optical axis at (centre_x, centre_y) half-field units from the
    # image centre: L(2c - q) is the flipped image shifted by 2c
    sx, sy = 2.0 * p["centre_x"] * g.half_size_px, 2.0 * p["centre_y"] * g.half_size_px
    flipped = state.light[::-1, ::-1]
    pad = int(np.ceil(4.0 * sigma + 2.0 * max(abs(sx), abs(sy)))) + 2
    padded = np.pad(flipped, pad, mode="reflect")
    fy = np.fft.fftfreq(padded.shape[0])[:, None]
    fx = np.fft.rfftfreq(padded.shape[1])[None, :]
    transfer = np.exp(-2.0 * np.pi**2 * sigma**2 * (fx**2 + fy**2) - 2j * np.pi * (fy * sy + fx * sx))
    ghost = np.fft.irfft2(np.fft.rfft2(padded) * transfer, s=padded.shape)[pad:-pad, pad:-pad]
    state.light = state.light + eps * ghost


GHOST_COPY = PhysicsTerm(
    "ghost_copy", "optics",
    (P("epsilon", 0.0, (0.0, 0.2), 0.005, 1e-4), P("sigma_px", 6.0, (0.5, 40.0), 6.0, 0.05, unit="px"),
     P("centre_x", 0.0, (-0.3, 0.3), 0.0, 0.005), P("centre_y", 0.0, (-0.3, 0.3), 0.0, 0.005)),
    "epsilon", _apply_ghost_copy,
    physics="Generic lens ghost: a defocused copy of the image inverted about the optical axis (a "
            "second reflection between lens surfaces or the sensor; not in the library: a "
            "competitor of the smooth fields, scatter and the mirror ghost).",
    linear_params=("epsilon",), linear_in_light=True)
GENERIC_COMPETITORS = (SMOOTH_GAIN, SMOOTH_ADDITIVE, SMOOTH_WARP, KEYSTONE, GHOST_COPY)
GENERIC_SIGNATURE = {"smooth_gain": "smooth multiplicative field not matching any library term",
                     "smooth_additive": "smooth additive light (stray light / haze) not matching "
                                        "any library term",
                     "smooth_warp": "smooth geometric distortion (keystone, tilted sensor or "
                                    "screen) not matching any library term",
                     "keystone": "smooth geometric distortion of keystone form (projective: camera "
                                 "or screen tilted against the other) not matching any library term",
                     "ghost_copy": "ghost-like copy of the image (inverted about the optical axis and "
                                   "blurred: a lens ghost) not matching any library term"}


#: Suffix of a smooth-field term's additive twin (see :func:`additive_twin`).
ADDITIVE_TWIN_SUFFIX = "_as_additive_light"
_TWINS: dict[str, PhysicsTerm] = {}


def additive_twin(term: PhysicsTerm) -> PhysicsTerm:
    """The same smooth field as ``term`` (heel, inverse square, vignetting) with the same
    parameters, but ADDED to the light (``light + (m - 1)``, open field = 1) instead of
    multiplying it (``light · m``). A fluence or lens field scales with the object's
    transmission; stray light or haze does not: where the twin fits as well as the term, the
    mismatch is additive light, not the library term."""
    if term.name not in _TWINS:
        def apply(state: ChainState, p: dict, _term=term) -> None:
            unit = ChainState(state.grid, fluence=np.ones(state.grid.shape), light=np.ones(state.grid.shape))
            _term.apply(unit, p)
            field = unit.fluence if _term.stage == "fluence" else unit.light
            state.light = state.light + (field - 1.0)

        _TWINS[term.name] = PhysicsTerm(term.name + ADDITIVE_TWIN_SUFFIX, "camera", term.params, term.main, apply,
                                        physics=f"{term.name}'s field as additive light (not physics: a competitor).",
                                        linear_in_light=True)
    return _TWINS[term.name]


def inverse_square_strength(grid: ChainGrid) -> float:
    """``s = (R_diag / SDD)^2`` of :func:`physics_terms._apply_inverse_square` for this field:
    the strength the scene's geometry fixes (``R_diag`` = half diagonal of the field in mm)."""
    half_diag_mm = np.sqrt(2.0) * grid.half_size_px * grid.pitch_mm
    return float((half_diag_mm / grid.source_to_detector_mm) ** 2)


def physical_bounds(term: PhysicsTerm, grid: ChainGrid) -> dict[str, tuple[float, float]]:
    """Bounds for ``term``'s parameters that the scene and physics allow (subset of the prior).

    * inverse square: strength ``(R_diag/SDD)²`` from the stated geometry, allowing an SDD down
      to 0.8× the stated one (1.56× the strength); the foot point within the field.
    * vignetting: a camera lens darkens toward the corners (``k1 ≤ 0.02``, ``|k| ≤ 0.5``,
      cos⁴ of a 40° half-field gives k ≈ -0.4) with its axis near the sensor centre (±0.3).
    * heel: at most ±30 % fluence change across the field.
    * magnitudes: glare η ≤ 0.3, scatter-to-primary amplitude ≤ 1, camera non-linearity
      |κ| ≤ 0.1, mirror ghost ε ≤ 0.1 (uncoated glass reflects ≈ 4-7 %), beam hardening
      β ≤ 0.3, lens distortion |k1| ≤ 0.05, focal-spot lobes ≤ 0.8 mm apart.
    """
    name = term.name.removesuffix(ADDITIVE_TWIN_SUFFIX)
    if name == "inverse_square":
        s = inverse_square_strength(grid)
        return {"strength": (0.0, 1.5625 * s)}
    table = {
        "vignetting": {"k1": (-0.5, 0.02), "k2": (-0.5, 0.1), "centre_x": (-0.3, 0.3), "centre_y": (-0.3, 0.3)},
        "heel_effect": {"h1": (-0.3, 0.3), "h2": (-0.3, 0.3)},
        "veiling_glare": {"eta": (0.0, 0.3)},
        "scatter": {"amplitude": (0.0, 1.0)},
        "detector_gamma": {"kappa": (-0.1, 0.1)},
        "mirror_ghost": {"epsilon": (0.0, 0.1)},
        "beam_hardening": {"beta": (0.0, 0.3)},
        "lens_distortion": {"k1": (-0.05, 0.05)},
        "focal_spot_shape": {"half_separation_mm": (0.0, 0.8)},
    }
    return dict(table.get(name, {}))


def probe_params(term: PhysicsTerm, grid: ChainGrid) -> dict[str, float]:
    """Probe point of the score test inside the physical bounds."""
    probe = term.probe_params()
    for key, (lo, hi) in physical_bounds(term, grid).items():
        if not lo <= probe[key] <= hi:
            probe[key] = 0.5 * (lo + hi) if lo > 0 or hi < 0 else (hi if abs(hi) > abs(lo) else lo) * 0.5
    return probe
