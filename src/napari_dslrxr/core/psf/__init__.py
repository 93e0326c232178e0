"""Blur estimation: the source + detector PSF model and its fit to edge radiographs.

* :mod:`.model` - the PSF model (focal spot and detector blur, scaled by magnification), its
  kernels and its JSON file;
* :mod:`.edge_fit` - fitting the model jointly to slanted-edge radiographs at several object
  distances (the phases of the fit), over :mod:`.edge_images` (the input record, normalisation,
  first edge estimate), :mod:`.edge_model` (transfer functions, ESF grid) and
  :mod:`.edge_objective` (cost, exact gradient, Jacobian);
* :mod:`.edge_config` - the edge configuration file of ``dslrxr psf fit``;
* :mod:`.fit_params` - the ``[psf_fit]`` section of the parameter file.

Synthetic edge radiographs are made in :mod:`napari_dslrxr.core.simulation.edge_synthesis`.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "model": ("DEFAULT_MAX_RADIUS_PX", "SUPPORT_FWHM_MULTIPLE", "DELTA_FWHM_PX", "PSF_FORMAT",
        "PSF_FORMAT_VERSION", "PARAMETER_NAMES", "fwhm_to_scale", "scale_to_fwhm", "magnification_factor",
        "sample_exponential_power", "PSFModel", "save_psf", "load_psf"),
    "edge_images": ("EdgeImage", "normalise_edge_image"),
    "edge_model": ("DEFAULT_ESF_STEP_PX",),
    "edge_fit": ("fit_edges",),
    "edge_config": ("EdgeConfig", "load_edge_config"),
    "fit_params": ("PsfFitParams",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
