"""Sample data generated at run time by the core (nothing is downloaded).

* a DSLR-like radiograph with impulsive pulses, its flat (open beam) and dark frames, from
  :func:`napari_dslrxr.core.simulation.phantom.make_dslr_radiograph` (seeded, so always the same);
* two edge radiographs of the same blur at two object distances (each with a near-vertical
  and a near-horizontal edge) for the PSF edge picker, from
  :func:`napari_dslrxr.core.simulation.edge_synthesis.synthesize_edge_image`;
* a simulator scene (thickness map and simulated recording) from
  :mod:`napari_dslrxr.core.simulation.simulator`.

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
    from .core.simulation.phantom import make_dslr_radiograph

    return make_dslr_radiograph(PHANTOM_SHAPE, seed=PHANTOM_SEED)


def _frame_metadata(kind: str) -> dict:
    frames = _phantom()
    return {"format": "sample", "sample": kind, "black_level": frames.black_level,
            "white_level": frames.white_level, "linear": True}


def _frame_layer(data: np.ndarray, name: str, kind: str) -> tuple:
    """A frame as an RGB image layer shown from black to its brightest counts (napari's default
    for uint16 is the whole 0-65535 range, which shows a 12-bit frame almost black)."""
    top = float(np.percentile(data[::4, ::4], 99.9))
    return (data, {"name": name, "rgb": True, "contrast_limits": (0.0, max(top, 1.0)),
                   "metadata": _frame_metadata(kind)}, "image")


def make_sample_radiograph() -> list[tuple]:
    """A DSLR photograph of a scintillator (linear RGB counts, uint16) with pulses."""
    return [_frame_layer(_phantom().raw_rgb, "DSLR radiograph", "radiograph")]


def make_sample_flat() -> list[tuple]:
    """The matching flat (open-beam) frame, same camera settings (uint16 RGB)."""
    return [_frame_layer(_phantom().flat, "flat", "flat")]


def make_sample_dark() -> list[tuple]:
    """The matching dark frame (X-rays off: black level and read noise, uint16 RGB)."""
    return [_frame_layer(_phantom().dark, "dark", "dark")]


def make_sample_dslr_set() -> list[tuple]:
    """Radiograph, flat and dark together."""
    return make_sample_dark() + make_sample_flat() + make_sample_radiograph()


# --------------------------------------------------------------------------- edges

#: Blur the edge samples are made with (pixel pitch 0.1 mm; SABER model, exponential profiles).
EDGE_TRUTH = {"pixel_pitch_mm": 0.1, "source_fwhm_x_mm": 0.4, "source_fwhm_y_mm": 0.4,
              "detector_fwhm_core_mm": 0.15, "detector_fwhm_tail_mm": 1.0, "detector_weight_core": 0.9,
              "shape_power": 1.0}
EDGE_SOURCE_TO_DETECTOR_MM = 1000.0
#: Object distances of the two samples: magnification 2 (focal spot blur 4 px) and 1.11 (0.4 px).
EDGE_SOURCE_TO_OBJECT_MM = (500.0, 900.0)
EDGE_HALF_SHAPE = (128, 128)
EDGE_BRIGHT_COUNTS = 4000.0


@lru_cache(maxsize=1)
def _edge_images() -> tuple:
    from .core.simulation.edge_synthesis import synthesize_edge_image
    from .core.psf import PSFModel

    truth = PSFModel(**EDGE_TRUTH)
    rng = np.random.default_rng(1)
    images = []
    for sod in EDGE_SOURCE_TO_OBJECT_MM:
        # Left half: a near-vertical edge (bright right); right half: a near-horizontal one.
        halves = [synthesize_edge_image(truth, sod, EDGE_SOURCE_TO_DETECTOR_MM, EDGE_HALF_SHAPE, angle,
                                        low=0.1, high=1.0, supersample=4) for angle in (3.0, 93.0)]
        expected = np.concatenate(halves, axis=1) * EDGE_BRIGHT_COUNTS
        images.append((sod, rng.poisson(expected).astype(np.float32)))
    return tuple(images)


def make_sample_edges() -> list[tuple]:
    """Two edge radiographs of the same blur at two object distances (Poisson, 4000 counts).

    Each image holds a near-vertical edge in its left half and a near-horizontal one in its
    right half; the layer metadata give the distances, pixel pitch and the true PSF.
    """
    layers = []
    for sod, image in _edge_images():
        meta = {"format": "sample", "sample": "edge", "source_to_object_mm": sod,
                "source_to_detector_mm": EDGE_SOURCE_TO_DETECTOR_MM,
                "pixel_pitch_mm": EDGE_TRUTH["pixel_pitch_mm"], "psf_truth": dict(EDGE_TRUTH)}
        layers.append((image, {"name": f"edge SOD {sod:.0f} mm", "colormap": "gray", "metadata": meta}, "image"))
    return layers


# --------------------------------------------------------------------------- simulator scene

#: The scene the user believes in (what the diagnosis starts from): the analytic phantom in
#: aluminium at 60 kVp, 0.1 mm pixels. The recording adds an effect the scene leaves out.
SCENE_TABLE = {"geometry": {"source_to_detector_mm": 1200.0, "source_to_object_mm": 1000.0, "pixel_pitch_mm": 0.1},
               "object": {"material": "aluminium"}, "source": {"kvp": 60},
               "noise": {"poisson_gain_dn": 1.2, "read_noise_dn": 6.3}}
SCENE_SHAPE = (128, 128)
SCENE_HIDDEN_EFFECTS = {"veiling_glare": {"eta": 0.03, "range_mm": 1.5}}
SCENE_SEED = 0


@lru_cache(maxsize=1)
def _scene_recording() -> tuple:
    from .core.simulation.simulator import parse_scene, phantom_thickness_mm, simulate_recording

    thickness = phantom_thickness_mm(SCENE_SHAPE)
    scene = parse_scene(SCENE_TABLE, thickness=thickness)
    recording, _ = simulate_recording(scene, effects=SCENE_HIDDEN_EFFECTS, seed=SCENE_SEED)
    return thickness, recording


def make_sample_scene() -> list[tuple]:
    """A simulator scene: the thickness map (mm) and a simulated recording (DN).

    The recording was simulated with veiling glare (eta 0.03, range 1.5 mm) that the scene
    itself does not contain: the mismatch diagnosis should find and name it. The recording's
    metadata hold the scene table and the name of its thickness layer.
    """
    thickness, recording = _scene_recording()
    pitch = SCENE_TABLE["geometry"]["pixel_pitch_mm"]
    thickness_name = "scene thickness (mm)"
    return [
        (thickness, {"name": thickness_name, "colormap": "viridis", "scale": (pitch, pitch),
                     "metadata": {"format": "sample", "sample": "scene thickness"}}, "image"),
        (recording, {"name": "simulated recording", "colormap": "gray", "scale": (pitch, pitch),
                     "metadata": {"format": "sample", "sample": "scene recording", "scene_table": SCENE_TABLE,
                                  "thickness_layer": thickness_name,
                                  "hidden_effects": SCENE_HIDDEN_EFFECTS}}, "image"),
    ]


# --------------------------------------------------------------------------- detector quality

#: The detector the QC samples are made with: a pixel detector with 0.1 mm pixels that detects
#: ``QC_QUANTA_PER_UGY`` X-ray quanta per pixel per µGy of RQA5, spreads each quantum's light
#: over a Gaussian of ``QC_LIGHT_SPREAD_PX`` (sigma) and reads ``QC_COUNTS_PER_QUANTUM`` counts
#: per quantum on an offset with read noise.
QC_TRUTH = {"pixel_pitch_mm": 0.1, "beam": "RQA5", "air_kerma_ugy": 2.5, "quanta_per_ugy": 180.0,
            "light_spread_sigma_px": 0.7, "counts_per_quantum": 2.0, "offset_counts": 100.0,
            "read_noise_counts": 3.0, "edge_angle_deg": 2.5}
QC_SHAPE = (512, 512)


@lru_cache(maxsize=1)
def _qc_frames() -> tuple:
    from scipy import ndimage

    t = QC_TRUTH
    rng = np.random.default_rng(3)
    quanta = t["quanta_per_ugy"] * t["air_kerma_ugy"]

    def detect(transmission: np.ndarray) -> np.ndarray:
        detected = rng.poisson(quanta * transmission).astype(np.float32)
        light = ndimage.gaussian_filter(detected, t["light_spread_sigma_px"], mode="reflect")
        counts = t["counts_per_quantum"] * light + t["offset_counts"] + rng.normal(0, t["read_noise_counts"], light.shape)
        return np.clip(np.round(counts), 0, 65535).astype(np.uint16)

    h, w = QC_SHAPE
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    angle = np.deg2rad(t["edge_angle_deg"])
    # signed distance (px) from a near-vertical edge through the centre; the pixel's open share
    # is its area right of the edge (a box pixel crossed by a straight line)
    distance = (cols - w / 2) * np.cos(angle) - (rows - h / 2) * np.sin(angle)
    edge_transmission = 0.03 + 0.97 * np.clip(distance + 0.5, 0.0, 1.0)
    flats = [detect(np.ones(QC_SHAPE)) for _ in range(2)]
    dark = np.clip(np.round(t["offset_counts"] + rng.normal(0, t["read_noise_counts"], QC_SHAPE)), 0, None)
    return flats, dark.astype(np.uint16), detect(edge_transmission)


def make_sample_qc_set() -> list[tuple]:
    """Detector-quality frames: two flats and a dark at 2.5 µGy RQA5 and a slanted edge (2.5°).

    A synthetic 0.1 mm pixel detector (Poisson quanta, Gaussian light spread after detection,
    read noise: :data:`QC_TRUTH` in each layer's metadata) for the QC widget.
    """
    flats, dark, edge = _qc_frames()
    meta = {"format": "sample", "pixel_pitch_mm": QC_TRUTH["pixel_pitch_mm"], "detector_truth": dict(QC_TRUTH)}
    layers = [(f, {"name": f"QC flat {i + 1}", "colormap": "gray", "metadata": {**meta, "sample": "qc flat"}}, "image")
              for i, f in enumerate(flats)]
    layers.append((dark, {"name": "QC dark", "colormap": "gray", "metadata": {**meta, "sample": "qc dark"}}, "image"))
    layers.append((edge, {"name": "QC edge", "colormap": "gray", "metadata": {**meta, "sample": "qc edge"}}, "image"))
    return layers
