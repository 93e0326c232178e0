"""Outputs of a diagnosis: ``diagnosis.json``, residual TIFFs and an offline ``report.html``.

Every file is written atomically and gets a provenance sidecar ``<file>.json``. The HTML report
embeds its PNG plots as base64 so it opens offline in any browser; they are drawn on matplotlib
``Figure`` objects (no pyplot, and the caller's matplotlib backend is left alone).
"""

from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from .. import io
from ..io import provenance
from ..io.report_files import figure_png as _figure_png
from ..io.report_files import report_folder
from ..io.report_files import write_text as _write_text
from ..simulation.physics_terms import LIBRARY_BY_NAME
from .locating import multiscale_maps
from .result import DiagnosisResult

PROFILE_LABELS = {
    "edge_distance_px": "signed distance to edges (px, + = open side)",
    "radius": "radius (corner of a square = 1)",
    "intensity_dn": "expected intensity (DN)",
    "columns": "column (px)",
    "rows": "row (px)",
    "thickness_mm": "thickness (mm)",
    "ripple_phase": "intensity phase at the ripple's period",
}


def residual_maps_figure(result: DiagnosisResult, scale: int = 4, title: str = "") -> bytes:
    """PNG bytes: binned normalised residual before and after the added terms (same colour scale)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    before = multiscale_maps(result.z_base, result.mask, (scale,))[scale]
    after = multiscale_maps(result.z_final, result.mask, (scale,))[scale]
    lim = max(3.0, float(np.percentile(np.abs(before), 99.5)))
    fig = Figure(figsize=(13.0, 4.4))
    axes = fig.subplots(1, 3)
    names = ", ".join(a.effect for a in result.added) or "nothing added"
    for ax, img, label in ((axes[0], before, f"base model  χ²/dof {result.base_chi2_per_dof:.4f}"),
                           (axes[1], after, f"+ {names}  χ²/dof {result.final_chi2_per_dof:.4f}"),
                           (axes[2], before - after, "explained by the added terms (before − after)")):
        im = ax.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    for r0, c0, r1, c1 in result.regions:
        b = scale * result.binning
        axes[0].add_patch(Rectangle((c0 / b - 0.5, r0 / b - 0.5), (c1 - c0) / b,
                                    (r1 - r0) / b, fill=False, ec="k", lw=1))
    fig.colorbar(im, ax=axes, shrink=0.8, label=f"Σz/√n over {scale}×{scale} blocks")
    if title:
        fig.suptitle(title, fontsize=10)
    return _figure_png(fig)


def profiles_figure(result: DiagnosisResult, keys: Iterable[str] = ("edge_distance_px", "radius",
                                                                     "intensity_dn", "columns"),
                    title: str = "") -> bytes:
    """PNG bytes: residual profiles (bin z-score Σz/√n) before and after, per covariate."""
    from matplotlib.figure import Figure

    keys = list(keys)
    if "ripple_phase" in result.profiles_final and "ripple_phase" not in keys:
        keys.append("ripple_phase")  # the evidence of a reported intensity ripple
    fig = Figure(figsize=(4.0 * len(keys), 3.4))
    axes = np.atleast_1d(fig.subplots(1, len(keys)))
    for ax, key in zip(axes, keys):
        for prof, label, style in ((result.profiles_base.get(key), "base", "o-"),
                                   (result.profiles_final.get(key), "final", "s-")):
            if prof and prof["centre"]:
                ax.plot(prof["centre"], prof["bin_z"], style, ms=3, label=label)
        ax.axhspan(-3, 3, color="0.9", zorder=0)
        ax.axhline(0, color="k", lw=0.5)
        label = PROFILE_LABELS.get(key, key)
        if key == "ripple_phase":
            label += f" ({result.structure['tests']['intensity_ripple']['period_dn']:.0f} DN)"
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("bin z = Σz/√n", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _figure_png(fig)


def write_png_bytes(path: str | os.PathLike, data: bytes, *, inputs: Iterable = ()) -> Path:
    """Write already-encoded PNG bytes atomically."""
    def _write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    return io.atomic_write(path, _write, inputs=inputs)


def render_html(result: DiagnosisResult, title: str = "dslrxr mismatch diagnosis", *,
                input_names: Iterable[str] = (), created: str | None = None) -> str:
    """The self-contained report page (plots as base64 PNG, scaled to the page width).

    ``input_names`` (files or layers) and ``created`` (a date the caller gives, so a report
    written twice from the same inputs stays byte-identical unless a date is asked for) are
    listed under the title.
    """
    maps_b64 = base64.b64encode(residual_maps_figure(result)).decode("ascii")
    prof_b64 = base64.b64encode(profiles_figure(result)).decode("ascii")
    rows = []
    for a in result.added:
        term = LIBRARY_BY_NAME[a.effect]
        params = ", ".join(f"{k} = {v:.5g} ± {a.uncertainty.get(k, float('nan')):.2g}"
                           for k, v in a.params.items())
        conf = ", ".join(f"{n} ({c:.2f})" for n, c in a.confusable_with) or "—"
        if a.runner_up:
            conf += f"<br>runner-up: {html.escape(a.runner_up)} (ΔBIC {a.runner_up_delta_bic:.1f})"
        if a.ambiguous:
            conf += f"<br><b>ambiguous</b> — separate by: {html.escape(a.separating)}"
        if a.at_bound:
            params += f" [{', '.join(a.at_bound)}: at bound, not an estimate]"
        rows.append(f"<tr><td>{html.escape(a.effect)}</td><td>{html.escape(params)}</td>"
                    f"<td>{a.delta_bic:.1f}</td><td>{a.heldout_gain:.1f}</td><td>{a.chi2_per_dof:.4f}</td>"
                    f"<td>{conf}</td><td>{html.escape(term.physics)}<br><i>separate by: "
                    f"{html.escape(term.separating)}</i></td></tr>")
    ranking_rows = []
    for i, ranking in enumerate(result.rankings):
        top = ", ".join(f"{r['effect']} (S {r['score']:.1f}, ΔBIC≈{r['delta_bic_est']:.1f})" for r in ranking[:5])
        refits = ""
        if i < len(result.comparisons) and result.comparisons[i]:
            refits = "; refitted ΔBIC: " + ", ".join(
                f"{c['effect']}{' (generic)' if c.get('generic') else ''} {c['delta_bic']:.1f}"
                if "delta_bic" in c else
                f"{c['effect']} beyond a smooth additive field {c['delta_bic_beyond_smooth_light']:.1f}"
                for c in result.comparisons[i])
        ranking_rows.append(f"<li>round {i + 1}: {html.escape(top + refits)}</li>")
    names = [str(n) for n in input_names]
    about = (f"<p>Inputs: {html.escape('; '.join(names)) if names else 'not recorded'}"
             + (f"<br>Created: {html.escape(created)}" if created else "") + "</p>")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:1em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #999;padding:3px 6px;font-size:90%;vertical-align:top}}
img{{max-width:100%;height:auto}}</style></head><body>
<h1>{html.escape(title)}</h1>
{about}
<p><b>{html.escape(result.message)}</b></p>
<p>Base model: χ²/dof {result.base_chi2_per_dof:.4f}, BIC {result.base_bic:.1f}; final χ²/dof
{result.final_chi2_per_dof:.4f}; {result.n_pixels} pixels fitted (binning {result.binning}×).
Noise model ({html.escape(str(result.noise.get('source', 'residual')))}): var = {result.noise_poisson_gain_dn:.4g}·(μ − b) +
{result.noise_read_dn:.3g}² DN², lag-1 correlation {result.noise.get('lag1_correlation', 0.0):.2f}
({'white' if result.noise.get('white', True) else 'prewhitened'}).
Registration: {html.escape(', '.join(f'{k} {v:+.4g}' for k, v in result.registration.items()) or 'off')}.
Mismatch regions (r0, c0, r1, c1): {result.regions or 'none'}.
Unexplained: {html.escape('; '.join(result.signatures)) + ' at ' + str(result.unexplained_regions)
              if result.unexplained else 'no (every residual test passes)'}.</p>
<h2>Added terms</h2>
<table><tr><th>effect</th><th>parameters ± SE</th><th>ΔBIC</th><th>held-out Δχ²</th><th>χ²/dof</th>
<th>confusable with</th><th>physics</th></tr>{''.join(rows) or '<tr><td colspan=7>none</td></tr>'}</table>
<h2>Residual maps (before / after)</h2><img alt="residual maps" src="data:image/png;base64,{maps_b64}">
<h2>Residual profiles</h2><img alt="residual profiles" src="data:image/png;base64,{prof_b64}">
<h2>Score-test rankings and refitted comparisons</h2><ul>{''.join(ranking_rows)}</ul>
</body></html>
"""


def write_report(result: DiagnosisResult, out_dir: str | os.PathLike, *, inputs: Iterable = (),
                 parameters: dict | None = None, timings_s: dict | None = None,
                 input_names: Iterable[str] | None = None, created: str | None = None) -> dict[str, Path]:
    """Write ``diagnosis.json``, ``diagnosis_details.json``, ``residual_base.tif``,
    ``residual_final.tif`` (float32 normalised residuals z) and ``report.html`` into ``out_dir``,
    each with a provenance sidecar. Returns the paths by name.

    The page names ``input_names`` (default: the ``inputs`` files) and the date ``created``
    when given (without it the bytes depend on the inputs only)."""
    out = report_folder(out_dir)
    inputs = [Path(p) for p in inputs]
    names = [str(p) for p in inputs] if input_names is None else list(input_names)
    params = parameters or {}
    paths = {
        "diagnosis": _write_text(out / "diagnosis.json", json.dumps(result.to_json(), indent=2) + "\n", inputs),
        "details": _write_text(out / "diagnosis_details.json",
                               json.dumps(provenance.to_jsonable(result.details()), indent=2) + "\n", inputs),
        "residual_base": io.write_tiff(out / "residual_base.tif", result.z_base,
                                       description="normalised residual z, base model", inputs=inputs),
        "residual_final": io.write_tiff(out / "residual_final.tif", result.z_final,
                                        description="normalised residual z, final model", inputs=inputs),
        "report": _write_text(out / "report.html", render_html(result, input_names=names, created=created), inputs),
    }
    for name, path in paths.items():
        provenance.write_sidecar(path, stage="diagnose", parameters=params, inputs=inputs,
                                 timings_s=timings_s, results=result.to_json() if name == "diagnosis" else None)
    return paths
