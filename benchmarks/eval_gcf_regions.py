"""Where the GCF of a display comes from: anatomy, direct exposure, or the outline between them.

``eval_contrast`` scores the GCF on the largest box inside the exposed field. On the real leg
that box is 41 % direct exposure (the beam beside the leg), and our display's GCF there stays
below the stretched input's while it rises over the anatomy alone. This script says why. For
the real CR chest and leg (``$DSLRXR_DATA/cr_dicom``) and three phantom frames (seed 0: the
demo frame ``eval_halo`` probes, at 600 x 900):

* renders: the input (0.5-99.5 % stretch within the exposed field, as ``eval_contrast``), the
  value-of-interest window and display curve alone (no dynamic range, no contrast), the
  defaults, and the coarse remapping without compression (``coarse_edge_gain`` 1);
* GCF on the exposed-field box and on the anatomy box, and the box's GCF split by
  :func:`napari_dslrxr.core.metrics.gcf_by_region` into anatomy (inside the field, outside the
  direct exposure, as the display's clipped fraction counts it), direct exposure, and the
  superpixels straddling the outline (the skin line), per resolution and in total;
* the mean display of the anatomy 0-20, 20-60 and 60-150 px in from the direct exposure;
* on the leg, the anatomy's foot lifted: the defaults' display with the anatomy's lowest value
  (value-of-interest 0) shown at ``floor`` instead of 2 % grey and a ramp down to black at the
  direct exposure's level, so the skin line stands out from a black background. This is the
  display range the stretched input gives the step from the beam to the thinnest tissue; it
  shows what that step is worth against the anatomy's own GCF.

Writes ``results/eval_gcf_regions.json``. Run: ``python benchmarks/eval_gcf_regions.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import record  # noqa: E402
from eval_contrast import DATA, anatomy_box, gcf, inner_box, stretch  # noqa: E402
from eval_halo import params_for  # noqa: E402

from napari_dslrxr.core.metrics import GCF_SUPERPIXELS_PX, gcf_by_region  # noqa: E402

#: label -> {"section.field": value}: the renders compared with the input.
RENDERS = {
    "window and curve alone": {"contrast.enabled": False, "dynamic_range.enabled": False},
    "default": {},
    "default without the skin line (anatomy_floor 0)": {"dynamic_range.anatomy_floor": 0.0},
    "coarse_edge_gain 1": {"contrast.coarse_edge_gain": 1.0},
}
#: Display values given to the anatomy's foot in the leg's trade-off by value alone (the curve's
#: foot: 0.02; the defaults' lift beside direct exposure, ``anatomy_floor``, is by the body's outline).
FOOT_FLOORS = (0.05, 0.1, 0.15, 0.2)


def anatomy_mask(attenuation: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Full-size anatomy (inside ``region``, outside direct exposure), as the clipped fraction counts it."""
    from napari_dslrxr.core.display import anatomy_grid
    from napari_dslrxr.core.params import PipelineParams

    _, grid = anatomy_grid(attenuation, region, PipelineParams())
    h, w = attenuation.shape
    return cv2.resize(grid.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


def score(display: np.ndarray, crop, anatomy_crop, anatomy: np.ndarray, depth: np.ndarray) -> dict:
    """GCF on the box and on the anatomy box, the box's GCF by region, the anatomy's foot."""
    parts = gcf_by_region(np.clip(display[crop], 0, 1), anatomy[crop])
    row = {"gcf_box": round(gcf(display[crop]), 3), "gcf_anatomy_box": round(gcf(display[anatomy_crop]), 3),
           "gcf_parts": {name: round(float(parts[:, col].sum()), 3)
                         for col, name in enumerate(("anatomy", "direct_exposure", "outline"))},
           "gcf_parts_by_resolution_px": {str(size): [round(float(v), 4) for v in parts[i]]
                                          for i, size in enumerate(GCF_SUPERPIXELS_PX)}}
    if depth is not None:
        shown, inside, deep = display[crop], anatomy[crop], depth[crop]
        bands = {f"{a}-{b}": inside & (deep > a) & (deep <= b) for a, b in ((0, 20), (20, 60), (60, 150))}
        row["anatomy_display_by_depth_px"] = {key: round(float(shown[sel].mean()), 3)
                                              for key, sel in bands.items() if sel.any()}
    return row


def lifted_foot(image: np.ndarray, floor: float) -> np.ndarray:
    """The defaults' display of a radiograph with the anatomy's foot (VOI 0) at ``floor``, black below the beam."""
    from napari_dslrxr.core.display import anatomy_grid
    from napari_dslrxr.core.params import PipelineParams
    from napari_dslrxr.core.pipeline import process_display_radiograph
    from napari_dslrxr.core.stages.dynamic_range import fit_to_display, sigmoid_lut
    from napari_dslrxr.core.stages.region import direct_exposure_level

    params = PipelineParams()
    result = process_display_radiograph(image, params=params, keep_intermediates=True)
    attenuation, mask = result.intermediates["attenuation"], result.region.mask
    step, anatomy = anatomy_grid(attenuation, mask, params)
    processed = result.intermediates["contrast"]
    fit_to_display(processed, processed[::step, ::step][anatomy], params.dynamic_range)  # as the pipeline does
    beam = direct_exposure_level(attenuation[::step, ::step][mask[::step, ::step]])
    beam = min(beam if beam is not None else -0.05, -1e-3)
    shown = sigmoid_lut(processed, params.dynamic_range)
    shown = floor + (shown - 0.02) * ((0.98 - floor) / 0.96)
    shown = np.where(processed < 0, floor * np.clip((processed - beam) / -beam, 0, 1), shown)
    shown[~mask] = 0.0
    return np.clip(shown, 0, 1).astype(np.float32)


def radiograph_rows(name: str) -> dict | None:
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.pipeline import process_display_radiograph
    from napari_dslrxr.core.stages.collimation import detect_collimation

    path = DATA / "cr_dicom" / f"{name}.dcm"
    if not path.exists():
        print(f"skipping {path}: not found")
        return None
    image = read_image(path).data.astype(np.float32)
    field = detect_collimation(image, drop_penumbra=True)  # the field as the display shutters it
    crop = inner_box(field.polygon_xy, image.shape) if field.detected else np.s_[:, :]
    anatomy = anatomy_mask(image, field.mask)
    anatomy_crop = anatomy_box(image, field.mask)
    depth = cv2.distanceTransform(anatomy.astype(np.uint8), cv2.DIST_L2, 5) if not anatomy[field.mask].all() else None
    rows = {"input": score(stretch(image, field.mask), crop, anatomy_crop, anatomy, depth),
            "direct_exposure_share_of_box": round(float(1 - anatomy[crop].mean()), 3)}
    for label, setting in RENDERS.items():
        rows[label] = score(process_display_radiograph(image, params=params_for(setting)).display, crop,
                            anatomy_crop, anatomy, depth)
    if depth is not None:
        for floor in FOOT_FLOORS:
            rows[f"default, anatomy foot at {floor}"] = score(lifted_foot(image, floor), crop, anatomy_crop,
                                                              anatomy, depth)
    return rows


def phantom_rows(seed: int, shape=(600, 900)) -> dict:
    """A phantom frame through the pipeline; the input is its value-of-interest image (as ``eval_contrast``)."""
    from napari_dslrxr.core.pipeline import process_frame
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    frames = make_dslr_radiograph(shape, seed=seed)
    rows = {}
    for label, setting in {"input": None, **RENDERS}.items():
        result = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark],
                               params=params_for(setting or {}), keep_intermediates=True)
        if setting is None:
            display = np.clip(result.intermediates["attenuation"], 0, 1)
            display[~result.region.mask] = 0.0
            crop = inner_box(result.region.polygon_xy, display.shape)
            anatomy = anatomy_mask(result.intermediates["attenuation"], result.region.mask)
            rows["direct_exposure_share_of_box"] = round(float(1 - anatomy[crop].mean()), 3)
        else:
            display = result.display
        rows[label] = score(display, crop, crop, anatomy, None)
    return rows


def main() -> int:
    images = {}
    for name in ("RG3_UNCR", "RG1_UNCR"):  # leg, chest
        rows = radiograph_rows(name)
        if rows is not None:
            images[name] = rows
            print(name, {k: (v["gcf_box"], v["gcf_anatomy_box"], v["gcf_parts"]) if isinstance(v, dict) else v
                         for k, v in rows.items()}, flush=True)
    for seed in (0, 1, 2):  # seed 0: the demo frame eval_halo probes
        images[f"phantom_seed{seed}"] = rows = phantom_rows(seed)
        print(seed, {k: (v["gcf_box"], v["gcf_parts"]) if isinstance(v, dict) else v for k, v in rows.items()},
              flush=True)
    record("eval_gcf_regions", {"images": images})
    return 0


if __name__ == "__main__":
    sys.exit(main())
