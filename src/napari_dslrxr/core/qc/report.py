"""Outputs of ``dslrxr qc``: ``qc.json``, ``qc.csv`` and an offline ``qc.html``.

Every file is written atomically with a provenance sidecar ``<file>.json``. The page embeds its
PNG figures as base64 (matplotlib ``Figure`` objects; pyplot and the caller's backend are left
alone). No date is written, so the same inputs give the same bytes.
"""

from __future__ import annotations

import base64
import html
import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..io import provenance
from ..io.report_files import figure_png, report_folder, write_text
from .measure import DetectorQuality

_DIRECTION_LABEL = {"horizontal": "horizontal (along rows)", "vertical": "vertical (along columns)"}
_STYLE = {"horizontal": ("C0", "-"), "vertical": ("C3", "--")}


def curves_figure(result: DetectorQuality) -> bytes:
    """PNG: MTF, NNPS and DQE against frequency, every direction, with ±1 standard-uncertainty bands."""
    from matplotlib.figure import Figure

    f = result.frequency_cy_per_mm
    fig = Figure(figsize=(13.0, 4.0))
    axes = fig.subplots(1, 3)
    for name, d in result.per_direction.items():
        colour, ls = _STYLE[name]
        label = _DIRECTION_LABEL[name]
        for ax, value, unc in ((axes[0], d.mtf, d.mtf_uncertainty), (axes[1], d.nnps_mm2, d.nnps_uncertainty_mm2),
                               (axes[2], d.dqe, d.dqe_uncertainty)):
            ax.plot(f, value, color=colour, ls=ls, lw=1.4, label=label)
            unc = np.nan_to_num(unc)
            ax.fill_between(f, value - unc, value + unc, color=colour, alpha=0.25, lw=0)
    titles = ("presampled MTF", "NNPS (mm²)", f"DQE  (q = {result.q_photons_per_mm2:.4g} /mm², {result.beam}, "
                                               f"{result.air_kerma_ugy:g} µGy)")
    for ax, title in zip(axes, titles):
        ax.axvline(result.nyquist_cy_per_mm, color="0.5", lw=0.8, ls=":")
        ax.set_xlabel("spatial frequency (cycles/mm)", fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_xlim(0, result.nyquist_cy_per_mm * 1.02)
    axes[0].set_ylim(0, 1.05)
    axes[1].set_yscale("log")
    top = np.nanmax([np.nanmax(d.dqe + np.nan_to_num(d.dqe_uncertainty)) for d in result.per_direction.values()])
    axes[2].set_ylim(0, max(0.05, min(1.05, 1.1 * float(top))))
    axes[0].legend(fontsize=7, loc="upper right")
    fig.text(0.99, 0.01, "bands: ±1 standard uncertainty; dotted: Nyquist frequency", fontsize=7, ha="right")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    return figure_png(fig)


def _shown(image: np.ndarray):
    lo, hi = np.percentile(image, [1, 99])
    return dict(cmap="gray", vmin=float(lo), vmax=float(hi) if hi > lo else float(lo) + 1, interpolation="nearest")


def esf_lsf_dark_to_bright(edge) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance (mm), ESF scaled to 0..1 and LSF scaled to a peak of 1, drawn from the dark side
    to the bright side: the ESF rises and the LSF is positive whichever way the edge faces (a
    bright-to-dark edge gave a negative LSF)."""
    side = 1.0 if float(edge.lsf.sum()) >= 0 else -1.0
    esf = (edge.esf - edge.esf.min()) / max(float(np.ptp(edge.esf)), 1e-30)
    lsf = side * edge.lsf / max(float(np.abs(edge.lsf).max()), 1e-30)
    return side * edge.esf_distance_mm, esf, lsf


def geometry_figure(result: DetectorQuality) -> bytes:
    """PNG: each analysed edge with its fitted line, the flat with the NNPS area and ROIs, and the
    oversampled ESF / LSF of the first edge."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    n_edges = len(result.edge_images)
    fig = Figure(figsize=(4.2 * (n_edges + 2), 4.2))
    axes = fig.subplots(1, n_edges + 2)
    for ax, img, e in zip(axes, result.edge_images, result.edges):
        ax.imshow(img, **_shown(img))
        r0, c0, r1, c1 = e.edge_line
        ax.plot([c0, c1], [r0, r1], color="C1", lw=1.0)
        ax.set_title(f"{e.direction} MTF: edge at {e.angle_deg:.2f}°, {e.n_outliers} px left out", fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    ax = axes[n_edges]
    if result.flat_image is not None:
        ax.imshow(result.flat_image, **_shown(result.flat_image))
    a0, b0, a1, b1 = result.nnps.analysis_area
    ax.add_patch(Rectangle((b0 - 0.5, a0 - 0.5), b1 - b0, a1 - a0, fill=False, ec="C1", lw=1.5))
    size = int(result.settings.get("roi_size_px", 256))
    for k, (r, c) in enumerate(result.nnps.roi_origins):
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), size, size, fill=False, ec="C0", lw=0.6,
                               ls="-" if k % 2 == 0 else "--"))
    ax.set_title(f"flat: NNPS area and {len(result.nnps.roi_origins)} ROIs of {size}² px", fontsize=8)
    ax.set_xticks([]), ax.set_yticks([])
    ax = axes[n_edges + 1]
    distance, esf, lsf = esf_lsf_dark_to_bright(result.edges[0])
    ax.plot(distance, esf, lw=1.0, label="ESF (normalised)")
    ax.plot(distance, lsf, lw=1.0, label="LSF (normalised)")
    ax.set_xlabel("distance to the edge, dark side to bright side (mm)", fontsize=8)
    ax.set_title(f"oversampled ESF/LSF, {result.settings.get('edge_oversampling')} bins per pixel", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return figure_png(fig)


def conversion_figure(result: DetectorQuality) -> bytes:
    """PNG: mean signal against air kerma with the proportional fit, and the deviations."""
    from matplotlib.figure import Figure

    c = result.conversion
    k = np.asarray(c.air_kerma_ugy)
    s = np.asarray(c.mean_signal)
    fig = Figure(figsize=(9.0, 3.6))
    axes = fig.subplots(1, 2)
    kk = np.linspace(0, k.max() * 1.1, 50)
    axes[0].plot(k, s, "o", ms=4, label="flats")
    axes[0].plot(kk, c.gain_per_ugy * kk, "-", lw=1, label=f"S = {c.gain_per_ugy:.4g} × K")
    axes[0].set_xlabel("air kerma (µGy)", fontsize=8)
    axes[0].set_ylabel("mean signal above dark", fontsize=8)
    axes[0].legend(fontsize=7)
    dev = np.asarray(c.deviation_percent)
    tol = float(result.settings.get("linearity_tolerance_percent", 5.0))
    axes[1].axhspan(-tol, tol, color="0.9", zorder=0)
    axes[1].plot(k, dev, "o", ms=4)
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].set_xlabel("air kerma (µGy)", fontsize=8)
    axes[1].set_ylabel("deviation from the fit (%)", fontsize=8)
    axes[1].set_title("linearity checked" if c.checked else "not checked: one air kerma only", fontsize=9)
    for ax in axes:
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return figure_png(fig)


def qc_figures(result: DetectorQuality) -> dict[str, bytes]:
    """The report's figures as PNG bytes: ``curves``, ``geometry``, ``conversion``."""
    return {"curves": curves_figure(result), "geometry": geometry_figure(result),
            "conversion": conversion_figure(result)}


def _csv_text(result: DetectorQuality) -> str:
    columns = [("frequency_cy_per_mm", result.frequency_cy_per_mm), ("mtf", result.mtf),
               ("mtf_uncertainty", result.mtf_uncertainty), ("nnps_mm2", result.nnps_mm2),
               ("nnps_uncertainty_mm2", result.nnps_uncertainty_mm2), ("dqe", result.dqe),
               ("dqe_uncertainty", result.dqe_uncertainty)]
    for name, d in result.per_direction.items():
        columns += [(f"{name}_mtf", d.mtf), (f"{name}_mtf_uncertainty", d.mtf_uncertainty),
                    (f"{name}_nnps_mm2", d.nnps_mm2), (f"{name}_nnps_uncertainty_mm2", d.nnps_uncertainty_mm2),
                    (f"{name}_dqe", d.dqe), (f"{name}_dqe_uncertainty", d.dqe_uncertainty)]
    lines = [",".join(name for name, _ in columns)]
    for i in range(result.frequency_cy_per_mm.size):
        lines.append(",".join(f"{float(v[i]):.6g}" if np.isfinite(v[i]) else "" for _, v in columns))
    return "\n".join(lines) + "\n"


def _table_rows(result: DetectorQuality) -> str:
    rows = []
    for frac in (0.25, 0.5, 0.75, 1.0):
        i = result.index_at(frac)
        f = result.frequency_cy_per_mm[i]
        rows.append(f"<tr><td>{f:.3g}</td><td>{frac:g}</td><td>{result.mtf[i]:.3f} ± {result.mtf_uncertainty[i]:.3f}</td>"
                    f"<td>{result.nnps_mm2[i]:.3e} ± {result.nnps_uncertainty_mm2[i]:.1e}</td>"
                    f"<td>{result.dqe[i]:.3f} ± {result.dqe_uncertainty[i]:.3f}</td></tr>")
    return "".join(rows)


def render_html(result: DetectorQuality, *, input_names: Iterable[str] = (),
                figures: dict[str, bytes] | None = None) -> str:
    """The self-contained QC page."""
    figs = figures or qc_figures(result)
    b64 = {k: base64.b64encode(v).decode("ascii") for k, v in figs.items()}
    names = list(input_names)
    c = result.conversion
    conv_text = (f"proportional fit {c.gain_per_ugy:.4g} per µGy, largest deviation {c.max_deviation_percent:.2f} % "
                 f"(tolerance {result.settings.get('linearity_tolerance_percent')} %)" if c.checked else
                 "not checked (all flats at one air kerma)")
    edges = "; ".join(f"{e.direction} edge at {e.angle_deg:.2f}°" for e in result.edges)
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings) or "<li>none</li>"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>dslrxr detector quality (IEC 62220-1-1)</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #999;padding:3px 6px;font-size:90%}}img{{max-width:100%;height:auto}}</style></head><body>
<h1>Detector quality: MTF, NNPS, DQE (IEC 62220-1-1)</h1>
<p>Inputs: {html.escape('; '.join(names)) if names else 'not recorded'}</p>
<p>Beam {html.escape(result.beam)}, air kerma {result.air_kerma_ugy:g} µGy, q = {result.q_photons_per_mm2:.5g}
photons/mm²; pixel pitch {result.pixel_pitch_mm:g} mm (Nyquist {result.nyquist_cy_per_mm:.3g} cycles/mm);
{html.escape(edges)}; NNPS from {result.nnps.n_rois} ROIs ({result.nnps.n_independent:.3g} independent areas).
Main direction: {html.escape(_DIRECTION_LABEL[result.direction])}.</p>
<table><tr><th>f (cycles/mm)</th><th>f / Nyquist</th><th>MTF</th><th>NNPS (mm²)</th><th>DQE</th></tr>
{_table_rows(result)}</table>
<h2>Warnings</h2><ul>{warn}</ul>
<h2>MTF, NNPS and DQE</h2><img alt="MTF, NNPS and DQE" src="data:image/png;base64,{b64['curves']}">
<h2>Edges and NNPS regions</h2><img alt="edge and ROI positions" src="data:image/png;base64,{b64['geometry']}">
<h2>Conversion function</h2><p>{html.escape(conv_text)}.</p>
<img alt="conversion function" src="data:image/png;base64,{b64['conversion']}">
</body></html>
"""


def write_qc_outputs(result: DetectorQuality, outdir: str | os.PathLike, *, inputs: Iterable = (),
                     input_names: Iterable[str] | None = None, parameters: dict | None = None,
                     timings_s: dict | None = None) -> dict[str, Path]:
    """Write ``qc.json``, ``qc.csv`` and ``qc.html`` into ``outdir``, each with a JSON sidecar
    (parameters, version, input checksums, timings). Returns the paths by name."""
    out = report_folder(outdir)
    inputs = [Path(p) for p in inputs]
    names = [str(p) for p in inputs] if input_names is None else list(input_names)
    record = result.to_json()
    paths = {
        "json": write_text(out / "qc.json", json.dumps(record, indent=2, allow_nan=False) + "\n", inputs),
        "csv": write_text(out / "qc.csv", _csv_text(result), inputs),
        "html": write_text(out / "qc.html", render_html(result, input_names=names), inputs),
    }
    summary = {"q_photons_per_mm2": result.q_photons_per_mm2, "direction": result.direction,
               "edge_angles_deg": [e.angle_deg for e in result.edges], "warnings": result.warnings}
    for name, path in paths.items():
        provenance.write_sidecar(path, stage="qc", parameters=parameters or result.settings, inputs=inputs,
                                 timings_s=timings_s, results=summary)
    return paths
