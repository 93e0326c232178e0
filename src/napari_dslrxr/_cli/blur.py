"""``dslrxr psf fit`` and ``dslrxr psf kernel``: estimate the blur model from edges, sample kernels.

``psf fit CONFIG.toml -o psf.json`` fits the SABER source + detector model jointly to the edge
radiographs listed in CONFIG (see :func:`napari_dslrxr.core.psf.edge_config.load_edge_config`)::

    pixel_pitch_mm = 0.05
    detector_core = "generalised"  # optional; or "exponential_power" (SABER's core + tail)
    [[edges]]
    image = "edge_h_near.tif"
    source_to_object_mm = 400
    source_to_detector_mm = 1000
    bright = "flat.tif"          # optional, with dark: (image - dark) / (bright - dark)
    dark = "dark.tif"            # optional
    roi = [0, 0, 512, 512]       # optional [r0, c0, r1, c1], end exclusive

``psf kernel psf.json --source-to-object-mm X --source-to-detector-mm Y -o kernel.tif`` writes
the blur kernel at that geometry: float32, odd size, sums to 1, on the detector pixel grid.
Every output gets a JSON sidecar.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from .common import HELP_MARKUP_MODE, option_help


def register(app: typer.Typer) -> None:
    """Add the ``psf`` command group (``fit``, ``kernel``) to ``app``."""
    psf_app = typer.Typer(help="Blur (PSF) estimation from edge radiographs and kernel sampling.",
                          rich_markup_mode=HELP_MARKUP_MODE,
                          no_args_is_help=True)
    app.add_typer(psf_app, name="psf")

    @psf_app.command("fit")
    def fit_cmd(
        config: Path = typer.Argument(..., help="Edge-fit configuration (TOML)."),
        output: Path = typer.Option(..., "-o", "--output", help="PSF model to write (psf.json)."),
        params_file: Optional[Path] = typer.Option(
            None, "-c", "--config", help="Parameter file (its psf_fit section; options override it)."),
        outlier_sigma: Optional[float] = typer.Option(None, "--outlier-sigma",
                                                      help=option_help("psf_fit", "outlier_sigma")),
    ) -> None:
        """Fit the source + detector blur model jointly to the edge radiographs in CONFIG."""
        from functools import partial

        from ..core import io
        from ..core.files import write_output
        from ..core.params import load_section
        from ..core.psf import edge_fit
        from ..core.psf import save_psf

        t0 = time.perf_counter()
        settings = load_section(params_file, "psf_fit", outlier_sigma=outlier_sigma)
        outlier_sigma = settings.outlier_sigma
        cfg = edge_fit.load_edge_config(config)
        inputs = [config] + cfg.input_files + ([params_file] if params_file is not None else [])
        io.check_not_an_input(output, inputs)
        t_load = time.perf_counter() - t0
        model = edge_fit.fit_edges(cfg.edges, cfg.pixel_pitch_mm, shape_power=cfg.shape_power,
                                   detector_core=cfg.detector_core, detector_tail=cfg.detector_tail,
                                   outlier_sigma=outlier_sigma or None)
        t_fit = time.perf_counter() - t0 - t_load
        report = model.fit_report
        write_output(
            output, partial(save_psf, model, inputs=inputs), stage="psf fit",
            parameters={"config": str(config), "pixel_pitch_mm": cfg.pixel_pitch_mm,
                        "shape_power": cfg.shape_power, "detector_core": cfg.detector_core,
                        "detector_tail": cfg.detector_tail, "outlier_sigma": outlier_sigma,
                        "edges": [{"image": e.name, "source_to_object_mm": e.source_to_object_mm,
                                   "source_to_detector_mm": e.source_to_detector_mm,
                                   "roi": list(e.roi) if e.roi else None} for e in cfg.edges]},
            inputs=inputs, timings_s={"load": t_load, "fit": t_fit},
            results={k: report[k] for k in ("residual_rms", "noise_rms_estimate", "iterations",
                                            "converged", "n_images", "n_outliers_masked")})
        typer.echo(f"wrote {output}: " + "; ".join(model.describe())
                   + f"; residual RMS {report['residual_rms']:.4g} (noise {report['noise_rms_estimate']:.4g})")

    @psf_app.command("kernel")
    def kernel_cmd(
        psf: Path = typer.Argument(..., help="PSF model (psf.json from 'dslrxr psf fit')."),
        source_to_object_mm: float = typer.Option(..., "--source-to-object-mm", help="SOD of the object, mm."),
        source_to_detector_mm: float = typer.Option(..., "--source-to-detector-mm", help="SDD, mm."),
        output: Path = typer.Option(..., "-o", "--output", help="Kernel TIFF to write (float32)."),
        max_radius_px: Optional[int] = typer.Option(None, "--max-radius-px", min=0,
                                                    help="Cap on the kernel half-width (default 2048 px)."),
    ) -> None:
        """Write the blur kernel of PSF at one geometry: float32, odd size, sums to 1."""
        from ..core import io
        from ..core.files import write_output
        from ..core.psf import load_psf

        t0 = time.perf_counter()
        model = load_psf(psf)
        io.check_not_an_input(output, [psf])
        kernel = model.kernel(source_to_object_mm, source_to_detector_mm, max_radius_px=max_radius_px)
        parameters = {"psf": str(psf), "source_to_object_mm": source_to_object_mm,
                      "source_to_detector_mm": source_to_detector_mm, "max_radius_px": max_radius_px,
                      "pixel_pitch_mm": model.pixel_pitch_mm}
        write_output(output, kernel, description=json.dumps({"dslrxr": "psf kernel", **parameters}),
                     stage="psf kernel", parameters=parameters, inputs=[psf],
                     timings_s={"kernel": time.perf_counter() - t0},
                     results={"shape": list(kernel.shape), "sum": float(kernel.sum(dtype=float))})
        typer.echo(f"wrote {output} ({kernel.shape[0]}x{kernel.shape[1]} float32 kernel)")
