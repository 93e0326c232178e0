"""Forward simulation of the imaging chain, and synthetic DSLR frames.

* :mod:`.physics_terms` - the library of physical effects (beam hardening, heel effect, scatter,
  glare, ghosts, distortion...) a recording may show, each a named term with parameters;
* :mod:`.simulator` - scenes (geometry, object, source) and the chain model that renders a
  recording from a scene and a set of terms;
* :mod:`.phantom` - seeded DSLR-like photographs of a scintillator with flat and dark frames and the
  truth that made them (sample data, demo, tests);
* :mod:`.edge_synthesis` - radiographs of straight edges blurred by a PSF model (tests, demo,
  sample data), made independently of the edge fit's forward model.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "physics_terms": ("STAGES", "ParamSpec", "ChainGrid", "ChainState", "PhysicsTerm", "LIBRARY",
        "LIBRARY_BY_NAME", "get_term", "validate_params"),
    "simulator": ("MATERIALS", "effective_attenuation_per_mm", "Scene", "parse_scene", "load_scene",
        "block_mean", "ChainModel", "simulate_recording", "phantom_thickness_mm"),
    "phantom": ("SCINTILLATOR_RGB_WEIGHTS", "PhantomTruth", "PhantomFrames", "make_object",
        "make_dslr_radiograph"),
    "edge_synthesis": ("synthesize_edge_image",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
