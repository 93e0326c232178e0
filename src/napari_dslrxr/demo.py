"""``python -m napari_dslrxr.demo OUTDIR`` (what ``make demo`` runs).

Generates a synthetic DSLR photograph of a scintillator (keystoned screen, uneven flat
field, blur, photon and read noise, colour pulses; :mod:`napari_dslrxr.core.simulation.phantom`) with
matching flat and dark frames, runs the whole pipeline on it exactly as ``dslrxr run`` does,
and writes into OUTDIR:

* ``input/radiograph.tif``, ``input/flat.tif``, ``input/dark.tif`` - the generated frames;
* ``input/edge_*.tif`` and ``input/edges.toml`` - edge radiographs of a plate at two object
  distances, blurred like the frame, and the configuration ``dslrxr psf fit`` reads;
* ``psf.json`` - the source and detector blur fitted from those edges (with a sidecar); the
  pipeline deblurs the frame with it (stage iv);
* ``radiograph_dslrxr.tif`` (16-bit), ``.png`` (preview), ``.dcm`` (DICOM DX), each with a
  ``.json`` sidecar (parameters, version, input checksums, stage timings);
* ``input/scene.toml`` and ``input/scene_thickness.tif`` - a simulator scene (the analytic
  phantom in aluminium, thickness in mm) for ``dslrxr simulate`` and ``dslrxr diagnose``;
* ``params.toml`` - the parameters used (the default file);
* ``before_after.png`` - the raw green channel (linear, stretched) beside the result.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np


def before_after(raw_rgb: np.ndarray, display: np.ndarray, black_level: float) -> np.ndarray:
    """Side-by-side uint8 image: raw green channel (0.5-99.5 % stretch) | processed."""
    green = raw_rgb[..., 1].astype(np.float32) - black_level
    lo, hi = np.percentile(green, [0.5, 99.5])
    before = np.clip((green - lo) / max(hi - lo, 1e-6), 0, 1)
    after = np.clip(display, 0, 1)
    gap = np.ones((before.shape[0], 8), np.float32)
    return np.round(np.hstack([before, gap, after]) * 255).astype(np.uint8)


#: Geometry of the demo: the frame and the edge plates, mm.
DEMO_SOURCE_TO_DETECTOR_MM = 1200.0
DEMO_SOURCE_TO_OBJECT_MM = 1150.0
DEMO_PIXEL_PITCH_MM = 0.2


def write_edge_radiographs(folder: Path, blur_sigma_px: float, *, seed: int = 0) -> Path:
    """Write four noisy edge radiographs (two distances x two orientations) and their config.

    The plate edges are blurred by a Gaussian detector PSF of ``blur_sigma_px`` (as the frame
    from :func:`~napari_dslrxr.core.simulation.phantom.make_dslr_radiograph`), with Poisson noise at about
    4000 counts in the open beam. Returns the path of ``edges.toml``.
    """
    import tomli_w

    from .core.simulation.edge_synthesis import synthesize_edge_image
    from .core.io import write_tiff
    from .core.psf import PSFModel

    fwhm_mm = 2.0 * np.sqrt(2.0 * np.log(2.0)) * blur_sigma_px * DEMO_PIXEL_PITCH_MM
    truth = PSFModel(pixel_pitch_mm=DEMO_PIXEL_PITCH_MM, source_fwhm_x_mm=0.0, source_fwhm_y_mm=0.0,
                     detector_fwhm_core_mm=fwhm_mm, detector_fwhm_tail_mm=4.0 * fwhm_mm,
                     detector_weight_core=1.0, shape_power=2.0)
    rng = np.random.default_rng(seed)
    edges = []
    for sod in (1100.0, DEMO_SOURCE_TO_OBJECT_MM):
        for angle in (3.0, 93.0):  # slightly slanted vertical and horizontal edges
            image = synthesize_edge_image(truth, sod, DEMO_SOURCE_TO_DETECTOR_MM, (128, 128), angle,
                                          low=0.05, high=1.0)
            counts = rng.poisson(image * 4000.0).astype(np.float32)
            name = f"edge_{int(sod)}mm_{int(angle)}deg.tif"
            write_tiff(folder / name, counts)
            edges.append({"image": name, "source_to_object_mm": sod,
                          "source_to_detector_mm": DEMO_SOURCE_TO_DETECTOR_MM})
    config = folder / "edges.toml"
    config.write_text(tomli_w.dumps({"pixel_pitch_mm": DEMO_PIXEL_PITCH_MM, "shape_power": 2.0,
                                     "edges": edges}), encoding="utf-8")
    return config


def write_scene(folder: Path) -> Path:
    """Write the sample simulator scene (TOML + thickness TIFF) into ``folder``; return the TOML.

    The same scene the napari sample offers: ``dslrxr simulate`` records it through the imaging
    chain and ``dslrxr diagnose`` compares a recording with it.
    """
    import copy

    import tomli_w

    from ._sample_data import SCENE_SHAPE, SCENE_TABLE
    from .core.io import write_tiff
    from .core.simulation.simulator import phantom_thickness_mm

    thickness = write_tiff(folder / "scene_thickness.tif", phantom_thickness_mm(SCENE_SHAPE))
    table = copy.deepcopy(SCENE_TABLE)
    table["object"]["thickness_mm"] = thickness.name
    scene = folder / "scene.toml"
    scene.write_text(tomli_w.dumps(table), encoding="utf-8")
    return scene


def main(argv: list[str] | None = None) -> int:
    """Generate the sample data, run the pipeline, write outputs; return an exit code."""
    from . import cli
    from .core.io import read_image, write_png, write_tiff
    from .core.params import PipelineParams, save_params
    from .core.simulation.phantom import make_dslr_radiograph
    from .core.files import run_file

    argv = sys.argv[1:] if argv is None else argv
    small = "--small" in argv  # a quick 384x576 run (tests)
    argv = [a for a in argv if a != "--small"]
    if len(argv) != 1:
        print("usage: python -m napari_dslrxr.demo OUTDIR [--small]", file=sys.stderr)
        return 2
    out = Path(argv[0])
    shape = (384, 576) if small else (1200, 1800)
    inputs = out / "input"
    inputs.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    frames = make_dslr_radiograph(shape, seed=0)
    paths = {}
    for name, arr in (("radiograph", frames.raw_rgb), ("flat", frames.flat), ("dark", frames.dark)):
        paths[name] = write_tiff(inputs / f"{name}.tif", arr)
    print(f"generated a {shape[0]}x{shape[1]} DSLR-like frame with flat and dark in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    config = write_edge_radiographs(inputs, frames.truth.blur_sigma_px, seed=0)
    scene = write_scene(inputs)
    psf_path = out / "psf.json"
    if cli.main(["psf", "fit", str(config), "-o", str(psf_path)]) != 0:
        return 1
    print(f"fitted the blur from 4 edge radiographs in {time.perf_counter() - t0:.1f} s -> {psf_path}")
    params = PipelineParams()
    params.output.dicom = True
    params.output.pixel_spacing_mm = DEMO_PIXEL_PITCH_MM
    save_params(params, out / "params.toml")

    def progress(done: int, total: int) -> None:
        print(f"\r  pipeline: stage {done}/{total}", end="", file=sys.stderr, flush=True)

    t1 = time.perf_counter()
    written = run_file(paths["radiograph"], out, params=params, flat_paths=[paths["flat"]],
                       dark_paths=[paths["dark"]], psf_path=psf_path,
                       source_to_object_mm=DEMO_SOURCE_TO_OBJECT_MM,
                       source_to_detector_mm=DEMO_SOURCE_TO_DETECTOR_MM, progress=progress)
    print(file=sys.stderr)
    print(f"pipeline ran in {time.perf_counter() - t1:.1f} s")
    processed = read_image(out / "radiograph_dslrxr.tif").data.astype(np.float32) / 65535.0
    write_png(out / "before_after.png", before_after(frames.raw_rgb, processed, frames.black_level))
    for path in [*written, psf_path, out / "before_after.png", out / "params.toml", scene]:
        print(f"  wrote {path}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
