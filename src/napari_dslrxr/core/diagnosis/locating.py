"""Where the residual departs from noise: profiles along the library's organising covariates,
multiscale maps, the signed edge distance, a generic smooth surface and held-out blocks."""

from __future__ import annotations

import numpy as np

from ..simulation.physics_terms import ChainGrid
from .fitting import orthonormal
from .terms import _legendre_basis


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
    h, w = z.shape
    rr, cc = np.broadcast_arrays(np.arange(h)[:, None], np.arange(w)[None, :])
    zm, m = z[mask], mask
    rho = np.sqrt(((grid.x**2 + grid.y**2) / 2.0) * np.ones(z.shape))
    signed = signed_edge_distance(thickness_coarse)
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


def signed_edge_distance(thickness_coarse: np.ndarray) -> np.ndarray:
    """Distance (fitted-grid pixels) to the edge of the attenuating object (above 5 % of the
    thickest part): negative inside, positive outside, +-0.5 next to the edge."""
    from scipy import ndimage

    attenuating = thickness_coarse > 0.05 * max(float(thickness_coarse.max()), 1e-12)
    inside = ndimage.distance_transform_edt(attenuating)
    outside = ndimage.distance_transform_edt(~attenuating)
    return np.where(attenuating, -inside + 0.5, outside - 0.5)


def checkerboard(shape: tuple[int, int], block: int) -> np.ndarray:
    r = (np.arange(shape[0]) // block)[:, None]
    c = (np.arange(shape[1]) // block)[None, :]
    return ((r + c) % 2).astype(bool)


def smooth_term_delta_bic(z: np.ndarray, mask: np.ndarray, q0: np.ndarray, grid: ChainGrid,
                           degree: int = 4) -> tuple[float, np.ndarray]:
    """ΔBIC of a generic smooth 2-D Legendre surface in the residual (location of leftovers)."""
    # the smooth competitors' basis, P_i(y) P_j(x); columns here in the order P_i(x) P_j(y)
    full = _legendre_basis(grid, degree)
    pairs = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i) if i or j]
    basis = np.ascontiguousarray(full[[pairs.index((j, i)) for i, j in pairs]][:, mask].T)
    zm = z[mask]
    perp = basis - q0 @ (q0.T @ basis)
    qb = orthonormal(perp, np.linalg.norm(basis, axis=0).max())
    coef = qb.T @ zm
    score = float(coef @ coef)
    smooth = np.zeros(z.shape)
    smooth[mask] = qb @ coef
    return score - qb.shape[1] * np.log(max(zm.size, 2)), smooth
