"""The plan of an edge fit: what the edges can identify, the bounds, and the starting point."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..robust import robust_sigma
from .edge_images import _Prepared
from .edge_model import _TAIL_FWHM_MIN_PX

#: ``s / FWHM`` of a Gaussian written as the MTF ``exp(-(f s)^2)``.
_GAUSSIAN_SCALE_PER_FWHM = math.pi / (2.0 * math.sqrt(math.log(2.0)))


@dataclass
class _FitPlan:
    """What the edges allow the fit to identify, and the bounds of the detector widths."""

    fit_source: bool
    tie: bool                   # one source width for both axes (edges of one orientation only)
    ratios: np.ndarray          # ODD / SOD of every edge
    tail_fwhm_max_px: float
    core_fwhm_max_px: float



def _check_fit_arguments(edges, pixel_pitch_mm, shape_power, esf_step_px) -> float:
    """Refuse unusable arguments (one line each); return the pixel pitch as a float."""
    if not edges:
        raise ParameterError("fit_edges: no edge images given")
    pitch = float(pixel_pitch_mm)
    if not (math.isfinite(pitch) and pitch > 0):
        raise ParameterError(f"pixel_pitch_mm must be finite and > 0, got {pixel_pitch_mm!r}")
    if shape_power not in (1.0, 2.0):
        raise ParameterError(f"shape_power must be 1 or 2 for edge fitting, got {shape_power!r}")
    if not 1e-3 <= esf_step_px <= 0.5:
        raise ParameterError(f"esf_step_px must be in [0.001, 0.5], got {esf_step_px!r}")
    return pitch


def _plan_fit(prepared: list[_Prepared], fit_source: bool | None, tail_fwhm_max_px: float | None) -> _FitPlan:
    """Whether the source is separable (two or more ODD/SOD ratios), whether its two axes are
    (edges of both orientations), and the largest core and tail widths allowed."""
    ratios = np.array([p.magnification_m1 for p in prepared])
    distinct = np.unique(np.round(ratios, 6))
    if fit_source is None:
        fit_source = distinct.size >= 2 and ratios.max() > 0
    elif fit_source and (distinct.size < 2 or ratios.max() <= 0):
        raise ParameterError("fit_source needs edges at two or more different ODD/SOD ratios (object heights)")
    normals = np.array([[abs(math.cos(p.angle_rad)), abs(math.sin(p.angle_rad))] for p in prepared])
    both_orientations = bool((normals[:, 0] > 0.7).any() and (normals[:, 1] > 0.7).any())
    largest_side = max(max(p.shape) for p in prepared)
    if tail_fwhm_max_px is None:
        tail_fwhm_max_px = max(4.0 * largest_side, 64.0)
    if not tail_fwhm_max_px > 2 * _TAIL_FWHM_MIN_PX:
        raise ParameterError(f"tail_fwhm_max_px must be > {2 * _TAIL_FWHM_MIN_PX:g}, got {tail_fwhm_max_px!r}")
    return _FitPlan(fit_source=bool(fit_source), tie=bool(fit_source and not both_orientations), ratios=ratios,
                    tail_fwhm_max_px=tail_fwhm_max_px,
                    core_fwhm_max_px=min(max(0.125 * largest_side, 16.0), 128.0))


def _starting_point(prepared: list[_Prepared], plan: _FitPlan, generalised: bool = False,
                    with_tail: bool = True) -> tuple[np.ndarray, float]:
    """Initial parameters (blur from the 10-90 % rise of the edges, split between core and
    source) and the initial noise scale."""
    noise0 = np.median([robust_sigma(np.diff(p.values)) / math.sqrt(2) for p in prepared])
    noise0 = float(noise0) if noise0 > 0 else 0.01
    rise = _initial_rise_px(prepared)
    core0 = min(max(0.3, 0.6 * rise), 0.5 * plan.core_fwhm_max_px)
    theta0 = []
    if plan.fit_source:
        src0 = min(max(0.3 * rise, 1e-2), 0.5 * plan.core_fwhm_max_px) / plan.ratios.max()
        theta0 += [math.log(src0)] if plan.tie else [math.log(src0), math.log(src0 * 1.1)]
    if generalised:
        # Scale of a Gaussian MTF exp(-(f s)^2) of this FWHM (s = pi FWHM / (2 sqrt(ln 2))); start
        # half-way between the Gaussian and the Lorentzian (q = 2, u = 0.5).
        theta0 += [math.log(core0 * _GAUSSIAN_SCALE_PER_FWHM), 2.0, 0.5]
    else:
        theta0 += [math.log(core0)]
    if with_tail:
        theta0 += [math.log(min(max(10.0 * core0, 8.0), 0.5 * plan.tail_fwhm_max_px)), 0.95]
    for p in prepared:
        theta0 += [p.offset_px, 0.0]
    return np.asarray(theta0, float), noise0


def _initial_rise_px(prepared: list[_Prepared]) -> float:
    """Median 10-90 % rise distance of the binned edge profiles (pixels)."""
    rises = []
    for p in prepared:
        d = p.x_px * math.cos(p.angle_rad) + p.y_px * math.sin(p.angle_rad) - p.offset_px
        near = np.abs(d) < 40
        if near.sum() < 32:
            continue
        order = np.argsort(d[near])
        dd, vv = d[near][order], p.values[near][order]
        bins = np.arange(-40, 40.5, 0.5)
        idx = np.digitize(dd, bins)
        prof = np.array([np.median(vv[idx == k]) if np.any(idx == k) else np.nan for k in range(1, bins.size)])
        centres = bins[:-1] + 0.25
        ok = np.isfinite(prof)
        if ok.sum() < 8:
            continue
        level = (prof[ok] - p.low) / (p.high - p.low)
        level = np.maximum.accumulate(np.clip(level, 0, 1))
        x10 = np.interp(0.1, level, centres[ok])
        x90 = np.interp(0.9, level, centres[ok])
        rises.append(max(x90 - x10, 0.5))
    return float(np.median(rises)) if rises else 2.0
