"""Sample data generated at run time by the core (nothing is downloaded).

* a DSLR-like radiograph with impulsive pulses, its flat (open beam) and dark frames, from
  :func:`napari_dslrxr.core.phantom.make_dslr_radiograph` (seeded, so always the same);
* two edge radiographs of the same blur at two object distances (each with a near-vertical
  and a near-horizontal edge) for the PSF edge picker, from
  :func:`napari_dslrxr.core.edge_fit.synthesize_edge_image`;
* a simulator scene (thickness map and simulated recording) from
  :mod:`napari_dslrxr.core.simulator`.

Each function returns napari layer-data tuples ``[(data, kwargs, layer_type), ...]``; the
``metadata`` of each layer records what it is (and, for the edges, the distances the PSF
widget needs).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: Frame size of the DSLR-like samples, (rows, cols): small enough to generate in ~0.3 s.
PHANTOM_SHAPE = (480, 720)
PHANTOM_SEED = 0


@lru_cache(maxsize=1)
def _phantom():
    from .core.phantom import make_dslr_radiograph

    return make_dslr_radiograph(PHANTOM_SHAPE, seed=PHANTOM_SEED)


def _frame_metadata(kind: str) -> dict:
    frames = _phantom()
    return {"format": "sample", "sample": kind, "black_level": frames.black_level,
            "white_level": frames.white_level, "linear": True}


def make_sample_radiograph() -> list[tuple]:
    """A DSLR photograph of a scintillator (linear RGB counts, uint16) with pulses."""
    frames = _phantom()
    return [(frames.raw_rgb, {"name": "DSLR radiograph", "rgb": True,
                              "metadata": _frame_metadata("radiograph")}, "image")]


def make_sample_flat() -> list[tuple]:
    """The matching flat (open-beam) frame, same camera settings (uint16 RGB)."""
    frames = _phantom()
    return [(frames.flat, {"name": "flat", "rgb": True, "metadata": _frame_metadata("flat")}, "image")]


def make_sample_dark() -> list[tuple]:
    """The matching dark frame (X-rays off: black level and read noise, uint16 RGB)."""
    frames = _phantom()
    return [(frames.dark, {"name": "dark", "rgb": True, "metadata": _frame_metadata("dark")}, "image")]


def make_sample_dslr_set() -> list[tuple]:
    """Radiograph, flat and dark together."""
    return make_sample_dark() + make_sample_flat() + make_sample_radiograph()
