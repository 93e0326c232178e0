"""The joint objective of the edge fit: residuals, cost, exact gradient and Jacobian blocks of
all edges at once (see :mod:`.edge_fit` for the method).
"""

from __future__ import annotations

import math

import numpy as np

from .edge_images import _Prepared
from .edge_model import (_CORE_LINNIK_BOUNDS, _CORE_POWER_BOUNDS, _LOG_FWHM_MIN, _TAIL_FWHM_MIN_PX,
                         _TAIL_STEP_PX, _WEIGHT_BOUNDS, _dot, _EsfGrid, _part_otf, _solve_levels)


class _JointProblem:
    """Cost, exact gradient and Jacobian blocks of the joint edge fit.

    The ESF is split as ``w * E_core + (1 - w) * E_tail`` (the detector mixture is linear): the
    core part (source * pixel * core) is compact and lives on a fine grid with a short period;
    the tail part (source * pixel * tail, tail FWHM >= 4 px) is smooth and lives on a coarse grid
    whose period covers the widest tail allowed. Both are exact up to the interpolation.

    ``generalised_core``: the core is the MTF-defined generalised core (its log scale, power
    ``q`` and Linnik ``u`` are fitted) instead of an exponential-power FWHM. ``with_tail``:
    False fixes the core weight at 1 (no tail part is computed).
    """

    def __init__(self, edges: list[_Prepared], shape_power: float, fit_source: bool, tie_source_axes: bool,
                 tail_fwhm_max_px: float, step_px: float, noise_scale: float, core_fwhm_max_px: float,
                 generalised_core: bool = False, with_tail: bool = True):
        self.edges = edges
        self.p = shape_power
        half_range = max(float(np.abs(np.hypot(e.x_px, e.y_px)).max()) for e in edges) + 2.0
        self.core_max = core_fwhm_max_px
        self.tail_max = tail_fwhm_max_px
        self.max_m1 = max(e.magnification_m1 for e in edges)
        # Periods: data range on both sides plus 12 widths of the widest core (+ source) or
        # 8 widths of the widest tail allowed, so periodic copies never reach the data.
        self.fine = _EsfGrid(2.0 * half_range + 12.0 * 2.0 * core_fwhm_max_px + 64.0, step_px)
        self.coarse = _EsfGrid(2.0 * half_range + 8.0 * tail_fwhm_max_px + 12.0 * core_fwhm_max_px + 64.0,
                               _TAIL_STEP_PX)
        self.fit_source = fit_source
        self.tie = tie_source_axes
        self.noise_scale = noise_scale
        self.generalised = generalised_core
        self.with_tail = with_tail
        self.global_free = (["sx"] if tie_source_axes else ["sx", "sy"]) if fit_source else []
        self.global_free += ["core"] + (["power", "linnik"] if generalised_core else [])
        self.global_free += ["tail", "w"] if with_tail else []
        self.n_global = len(self.global_free)
        self.n_total_pixels = sum(int(e.keep.sum()) for e in edges)
        self._kept_cache: dict[int, tuple] = {}

    def _kept(self, j: int):
        """Coordinates, values and weights of edge ``j``'s used pixels (cached per mask/weights)."""
        e = self.edges[j]
        cached = self._kept_cache.get(j)
        if cached is None or cached[0] is not e.keep or cached[1] is not e.weight:
            keep = e.keep
            cached = (e.keep, e.weight, e.x_px[keep], e.y_px[keep], e.values[keep], e.weight[keep])
            self._kept_cache[j] = cached
        return cached[2:]

    def unpack(self, theta: np.ndarray):
        g = dict(zip(self.global_free, theta[:self.n_global]))
        fwhm = {"sx": math.exp(g["sx"]) if "sx" in g else 0.0, "core": math.exp(g["core"]),
                "tail": math.exp(g["tail"]) if "tail" in g else float("nan"),
                "w": float(g["w"]) if "w" in g else 1.0,
                "power": float(g.get("power", 2.0)), "linnik": float(g.get("linnik", 0.0))}
        fwhm["sy"] = math.exp(g["sy"]) if "sy" in g else fwhm["sx"]
        local = theta[self.n_global:].reshape(len(self.edges), 2)
        return fwhm, local

    def bounds(self):
        b = []
        for name in self.global_free:
            if name == "w":
                b.append(_WEIGHT_BOUNDS)
            elif name in ("sx", "sy"):
                # Source projected onto the detector stays within the fine grid's reach.
                b.append((_LOG_FWHM_MIN, math.log(self.core_max / max(self.max_m1, 1e-9))))
            elif name == "core":
                # The generalised core's scale is about twice its FWHM (a Gaussian's: 1.9x).
                b.append((_LOG_FWHM_MIN, math.log(self.core_max * (2.0 if self.generalised else 1.0))))
            elif name == "power":
                b.append(_CORE_POWER_BOUNDS)
            elif name == "linnik":
                b.append(_CORE_LINNIK_BOUNDS)
            else:
                b.append((math.log(_TAIL_FWHM_MIN_PX), math.log(self.tail_max)))
        for e in self.edges:
            b += [(None, None), (-0.3 * e.angle_scale_px, 0.3 * e.angle_scale_px)]
        return b

    def _edge_terms(self, j: int, fwhm: dict, local_j: np.ndarray, need_derivatives: bool):
        e = self.edges[j]
        offset, angle_scaled = local_j
        phi = e.angle_rad + angle_scaled / e.angle_scale_px
        cphi, sphi = math.cos(phi), math.sin(phi)
        x, yv, values, pixel_weight = self._kept(j)
        d = x * cphi + yv * sphi - offset
        w = fwhm["w"]
        parts = {}
        specs = [("core", self.fine, fwhm["core"], (fwhm["power"], fwhm["linnik"]) if self.generalised else None)]
        if self.with_tail:
            specs.append(("tail", self.coarse, fwhm["tail"], None))
        for label, grid, width, core_shape in specs:
            otf, derivs = _part_otf(grid, fwhm, width, e.magnification_m1, phi, self.p, need_derivatives, core_shape)
            esf_grid = grid.esf(otf)
            i0, frac = grid.locate(d)
            e0, e1 = esf_grid[i0], esf_grid[i0 + 1]
            parts[label] = dict(grid=grid, derivs=derivs, i0=i0, frac=frac,
                                esf=e0 + frac * (e1 - e0), slope=(e1 - e0) / grid.step)
        if self.with_tail:
            esf = w * parts["core"]["esf"] + (1.0 - w) * parts["tail"]["esf"]
            slope = w * parts["core"]["slope"] + (1.0 - w) * parts["tail"]["slope"]
        else:
            esf, slope = parts["core"]["esf"], parts["core"]["slope"]
        low, high = _solve_levels(esf, values, pixel_weight)
        model = low + (high - low) * esf
        return dict(e=e, phi=phi, d=d, esf=esf, slope=slope, model=model, parts=parts, w=w,
                    x=x, y=yv, low=low, high=high, pixel_weight=pixel_weight, values=values)

    def cost_and_gradient(self, theta: np.ndarray):
        fwhm, local = self.unpack(theta)
        scale = 1.0 / (self.n_total_pixels * self.noise_scale ** 2)
        cost = 0.0
        grad_global = dict.fromkeys(("sx", "sy", "core", "tail", "w", "power", "linnik"), 0.0)
        grad_local = np.zeros_like(local)
        for j in range(len(self.edges)):
            t = self._edge_terms(j, fwhm, local[j], True)
            r = t["model"] - t["values"]
            wr = t["pixel_weight"] * r     # weighted residual: d(cost)/d(model) up to the scale
            cost += 0.5 * scale * _dot(wr, r)
            contrast = t["high"] - t["low"]
            w = t["w"]
            g_phi_grid = 0.0
            for label, weight in (("core", w), ("tail", 1.0 - w)):
                part = t["parts"].get(label)
                if part is None or weight == 0.0:
                    continue
                r_hat = part["grid"].backproject(part["i0"], part["frac"], wr)
                k = scale * contrast * weight
                grad_global["sx"] += k * part["grid"].inner(part["derivs"]["sx"], r_hat)
                grad_global["sy"] += k * part["grid"].inner(part["derivs"]["sy"], r_hat)
                grad_global[label] += k * part["grid"].inner(part["derivs"]["component"], r_hat)
                for shape_name in ("power", "linnik"):
                    if shape_name in part["derivs"]:
                        grad_global[shape_name] += k * part["grid"].inner(part["derivs"][shape_name], r_hat)
                g_phi_grid += k * part["grid"].inner(part["derivs"]["phi"], r_hat)
            if self.with_tail:
                grad_global["w"] += scale * contrast * _dot(wr, t["parts"]["core"]["esf"] - t["parts"]["tail"]["esf"])
            dd_dphi = -t["x"] * math.sin(t["phi"]) + t["y"] * math.cos(t["phi"])
            g_phi = scale * contrast * _dot(wr * t["slope"], dd_dphi) + g_phi_grid
            grad_local[j, 0] = -scale * contrast * _dot(wr, t["slope"])
            grad_local[j, 1] = g_phi / t["e"].angle_scale_px
        gradient = np.empty_like(theta)
        for k, name in enumerate(self.global_free):
            # log-FWHM parameters: the OTF derivatives are already taken w.r.t. log FWHM.
            gradient[k] = grad_global[name] + (grad_global["sy"] if (name == "sx" and self.tie) else 0.0)
        gradient[self.n_global:] = grad_local.ravel()
        return cost, gradient

    def residuals_and_jacobian_normal(self, theta: np.ndarray):
        """Residuals per edge and the weighted Gauss-Newton matrix ``J^T W J``.

        Columns: the optimiser's parameters, then ``(a_j, b_j)`` of every edge.
        """
        fwhm, local = self.unpack(theta)
        n_par = theta.size
        n_all = n_par + 2 * len(self.edges)
        jtj = np.zeros((n_all, n_all))
        residuals, terms = [], []
        for j in range(len(self.edges)):
            t = self._edge_terms(j, fwhm, local[j], True)
            r = t["model"] - t["values"]
            contrast = t["high"] - t["low"]
            w = t["w"]

            def column(name):
                total = 0.0
                for label, weight in (("core", w), ("tail", 1.0 - w)):
                    part = t["parts"].get(label)
                    key = "component" if name == label else name
                    if part is None or key not in part["derivs"] or weight == 0.0:
                        continue
                    g = part["grid"].derivative(part["derivs"][key])
                    i0, frac = part["i0"], part["frac"]
                    total = total + weight * (g[i0] + frac * (g[i0 + 1] - g[i0]))
                return contrast * total

            cols, index = [], []
            for k, name in enumerate(self.global_free):
                if name == "w":
                    col = contrast * (t["parts"]["core"]["esf"] - t["parts"]["tail"]["esf"])
                elif name == "sx" and self.tie:
                    col = column("sx") + column("sy")
                else:
                    col = column(name)
                cols.append(np.broadcast_to(col, r.shape))
                index.append(k)
            dd_dphi = -t["x"] * math.sin(t["phi"]) + t["y"] * math.cos(t["phi"])
            dphi = contrast * t["slope"] * dd_dphi + column("phi")
            base = self.n_global + 2 * j
            levels = n_par + 2 * j   # transmission levels: linear, solved in closed form
            cols += [-contrast * t["slope"], dphi / t["e"].angle_scale_px, 1.0 - t["esf"], t["esf"]]
            index += [base, base + 1, levels, levels + 1]
            block = np.stack(cols, axis=1)
            jtj[np.ix_(index, index)] += np.einsum("i,ij,ik->jk", t["pixel_weight"], block, block)
            residuals.append(r)
            terms.append(t)
        return residuals, jtj, terms
