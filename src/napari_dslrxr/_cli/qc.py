"""``dslrxr qc``: detector MTF, NNPS and DQE per IEC 62220-1-1 from flats, darks and slanted edges.

::

    dslrxr qc --flat F1.tif --flat F2.tif --dark D.tif --edge E.tif \\
              --pixel-pitch-mm 0.1 --air-kerma-ugy 2.5 --beam RQA5 -o qc_out

writes ``qc_out/qc.json``, ``qc.csv`` and ``qc.html``, each with a JSON sidecar. Give
``--air-kerma-ugy`` once (every flat) or once per flat (the conversion-function check then
refuses a response that is not linear in air kerma). Camera raw files are read as one linear
CFA plane (``[qc] raw_plane``) at twice the sensor pitch.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from .common import option_help, parse_roi


def _read_linear_frame(path: Path, raw_plane: str):
    """One single-channel linear frame: a grey image as it is, camera raw as one CFA plane."""
    from ..core import io
    from ..core.errors import InputError

    loaded = io.read_image(path)
    if loaded.raw is not None:
        names = list(loaded.raw.cfa_names)
        return loaded.raw.cfa_planes[names.index(raw_plane)], True
    if loaded.data.ndim != 2:
        raise InputError(path, "a colour image is not a linear detector frame; give the camera raw file or a "
                               "single-channel image")
    return loaded.data, False


def register(app: typer.Typer) -> None:
    """Add ``qc`` to ``app``."""

    @app.command("qc")
    def qc_cmd(
        flat: list[Path] = typer.Option(..., "--flat", help="Open-beam (flat) frame; repeatable."),
        edge: list[Path] = typer.Option(..., "--edge", help="Slanted-edge frame (one per orientation); repeatable."),
        output: Path = typer.Option(..., "-o", "--output", help="Folder for qc.json, qc.csv and qc.html."),
        dark: Optional[list[Path]] = typer.Option(None, "--dark", help="Dark frame; repeatable."),
        pixel_pitch_mm: Optional[float] = typer.Option(None, "--pixel-pitch-mm",
                                                       help=option_help("qc", "pixel_pitch_mm")),
        air_kerma_ugy: Optional[list[float]] = typer.Option(
            None, "--air-kerma-ugy", help=option_help("qc", "air_kerma_ugy", "air kerma at the detector: once for "
                                                      "every flat or once per flat, in --flat order")),
        beam: Optional[str] = typer.Option(None, "--beam", help=option_help("qc", "beam")),
        edge_roi: Optional[list[str]] = typer.Option(
            None, "--edge-roi", help="Region r0,c0,r1,c1 (px, end exclusive) of each edge to analyse; once per --edge."),
        roi_size_px: Optional[int] = typer.Option(None, "--roi-size-px", help=option_help("qc", "roi_size_px")),
        params_file: Optional[Path] = typer.Option(
            None, "-c", "--config", help="Parameter file (its qc section; options override it)."),
    ) -> None:
        """Measure the detector's presampled MTF, NNPS and DQE (IEC 62220-1-1)."""
        from ..core import io
        from ..core.errors import ParameterError
        from ..core.params import load_section
        from ..core.qc import measure_detector_quality, write_qc_outputs

        t0 = time.perf_counter()
        kermas = list(air_kerma_ugy or [])
        settings = load_section(params_file, "qc", pixel_pitch_mm=pixel_pitch_mm, beam=beam,
                                roi_size_px=roi_size_px, air_kerma_ugy=kermas[0] if kermas else None)
        if len(kermas) not in (0, 1, len(flat)):
            raise ParameterError(f"--air-kerma-ugy: give one value for every flat or one per flat "
                                 f"({len(flat)}), got {len(kermas)}")
        rois = [parse_roi(text) for text in (edge_roi or [])] or None
        darks = list(dark or [])
        inputs = list(flat) + darks + list(edge) + ([params_file] if params_file is not None else [])
        for name in ("qc.json", "qc.csv", "qc.html"):
            io.check_not_an_input(output / name, inputs)
        frames, raw_flags = {}, []
        for key, paths in (("flats", flat), ("darks", darks), ("edges", edge)):
            frames[key] = []
            for p in paths:
                data, is_raw = _read_linear_frame(p, settings.raw_plane)
                frames[key].append(data)
                raw_flags.append(is_raw)
        pitch = settings.pixel_pitch_mm
        if any(raw_flags):
            if not all(raw_flags):
                raise ParameterError("mix of camera raw and other files: give all frames in one kind")
            pitch = 2.0 * pitch  # one CFA plane samples every second sensor pixel
        t_read = time.perf_counter() - t0
        result = measure_detector_quality(
            frames["flats"], frames["darks"], frames["edges"], pixel_pitch_mm=pitch,
            air_kerma_ugy=kermas if len(kermas) > 1 else None, params=settings, edge_rois=rois,
            names={"flats": [str(p) for p in flat], "darks": [str(p) for p in darks],
                   "edges": [str(p) for p in edge]})
        if any(raw_flags):
            result.warnings.append(f"camera raw: the {settings.raw_plane} CFA plane was analysed at "
                                   f"{pitch:g} mm (twice the sensor pitch)")
        t_measure = time.perf_counter() - t0 - t_read
        paths = write_qc_outputs(result, output, inputs=inputs, input_names=[str(p) for p in inputs],
                                 timings_s={"read": t_read, "measure": t_measure})
        i = result.index_at(0.5)
        for w in result.warnings:
            typer.echo(f"dslrxr: warning: {w}", err=True)
        typer.echo(f"wrote {paths['json']}, {paths['csv'].name}, {paths['html'].name}: at "
                   f"{result.frequency_cy_per_mm[i]:.3g} cycles/mm MTF {result.mtf[i]:.3f}, "
                   f"DQE {result.dqe[i]:.3f} ± {result.dqe_uncertainty[i]:.3f} ({result.direction})")
