"""Blur estimation: the source + detector PSF model and its fit to edge radiographs.

* :mod:`.model` - the PSF model (focal spot and detector blur, scaled by magnification) and its
  kernels, over :mod:`.mtf_shapes` (radial MTF shapes, FWHM <-> scale) and
  :mod:`.kernel_sampling` (pixel-area-integrated sampling, kernel crop/pad/finish);
* :mod:`.psf_file` - the model's JSON file (``psf.json``): save, load and validate;
* :mod:`.edge_fit` - fitting the model jointly to slanted-edge radiographs at several object
  distances (``fit_edges``: tail score test, focal-spot identification), in phases:
  :mod:`.edge_fit_plan` (what the edges identify, bounds, starting point),
  :mod:`.edge_optimiser` (L-BFGS-B passes, noise weights, outlier masks) and
  :mod:`.edge_fit_result` (fitted model, uncertainties, report); over :mod:`.edge_images` (the
  input record, normalisation, first edge estimate), :mod:`.edge_model` (transfer functions,
  ESF grid) and :mod:`.edge_objective` (cost, exact gradient, Jacobian);
* :mod:`.edge_config` - the edge configuration file of ``dslrxr psf fit``;
* :mod:`.fit_params` - the ``[psf_fit]`` section of the parameter file.

Synthetic edge radiographs are made in :mod:`napari_dslrxr.core.simulation.edge_synthesis`.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "mtf_shapes": ("fwhm_to_scale", "scale_to_fwhm"),
    "kernel_sampling": ("DEFAULT_MAX_RADIUS_PX", "SUPPORT_FWHM_MULTIPLE", "DELTA_FWHM_PX",
        "sample_exponential_power"),
    "model": ("PSF_FORMAT", "PSF_FORMAT_VERSION", "PARAMETER_NAMES", "magnification_factor", "PSFModel"),
    "psf_file": ("save_psf", "load_psf"),
    "edge_images": ("EdgeImage", "normalise_edge_image"),
    "edge_model": ("DEFAULT_ESF_STEP_PX",),
    "edge_fit": ("fit_edges",),
    "edge_config": ("EdgeConfig", "load_edge_config"),
    "fit_params": ("PsfFitParams",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
