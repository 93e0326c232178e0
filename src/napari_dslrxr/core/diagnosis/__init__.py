"""Mismatch diagnosis: what the base model of a scene leaves out of a recording, and its report.

* :mod:`.mismatch` - the noise model, residual maps and profiles, and the greedy search that
  locates the mismatch and names the physics terms that explain it;
* :mod:`.report` - ``diagnosis.json``, residual TIFFs and the offline ``report.html``.

Builds on :mod:`napari_dslrxr.core.simulation`.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "mismatch": ("BASE_FREE", "DiagnosisOptions", "AddedTerm", "DiagnosisResult", "estimate_noise_model",
        "residual_profiles", "multiscale_maps", "diagnose", "diagnose_scene",
        "noise_model_from_repeats", "edge_object_from_image", "diagnose_edge_repeats"),
    "report": ("PROFILE_LABELS", "residual_maps_figure", "profiles_figure", "write_png_bytes",
        "render_html", "write_report"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
