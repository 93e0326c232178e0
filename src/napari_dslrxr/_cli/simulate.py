"""``dslrxr simulate`` and ``dslrxr diagnose``: the imaging-chain simulator and mismatch diagnosis.

``--effect`` syntax: ``NAME=VALUE`` sets the term's main amplitude (other parameters at their
defaults), ``NAME=key:value,key:value`` sets named parameters, e.g.
``--effect veiling_glare=eta:0.02,range_mm:1.5`` or ``--effect heel_effect=0.05``. Terms:
beam_hardening (beta), heel_effect (h1), inverse_square (strength), scatter (amplitude),
focal_spot_shape (half_separation_mm), veiling_glare (eta), mirror_ghost (epsilon),
lens_distortion (k1), vignetting (k1), detector_gamma (kappa).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from .common import option_help


def parse_effect_option(text: str) -> tuple[str, dict[str, float]]:
    """Parse ``NAME=VALUE`` (main amplitude) or ``NAME=k1:v1,k2:v2`` into ``(name, params)``."""
    from ..core.errors import ParameterError
    from ..core.simulation.physics_terms import get_term, validate_params

    if "=" not in text:
        raise ParameterError(f"--effect {text!r}: expected NAME=VALUE or NAME=key:value,key:value")
    name, _, value = text.partition("=")
    term = get_term(name.strip())
    value = value.strip()
    if ":" not in value:
        try:
            return term.name, validate_params(term, {term.main: float(value)})
        except ValueError:
            raise ParameterError(f"--effect {text!r}: {value!r} is not a number") from None
    params = {}
    for part in value.split(","):
        key, sep, val = part.partition(":")
        if not sep:
            raise ParameterError(f"--effect {text!r}: expected key:value pairs separated by commas")
        try:
            params[key.strip()] = float(val)
        except ValueError:
            raise ParameterError(f"--effect {text!r}: {val!r} is not a number") from None
    return term.name, validate_params(term, params)


def register(app: typer.Typer) -> None:
    """Add ``simulate`` and ``diagnose`` to ``app``."""

    @app.command("simulate")
    def simulate_cmd(
        scene: Path = typer.Argument(..., help="Scene TOML file."),
        output: Path = typer.Option(..., "-o", "--output", help="Recording to write (float32 TIFF, DN)."),
        effect: Optional[list[str]] = typer.Option(
            None, "--effect", help="NAME=VALUE (main amplitude) or NAME=k1:v1,k2:v2; repeatable."),
        seed: int = typer.Option(0, "--seed", min=0, help="Noise seed, >= 0 (same seed, same bytes)."),
    ) -> None:
        """Simulate a recording of the scene through the imaging chain."""
        from ..core import io
        from ..core.files import write_output
        from ..core.simulation import simulator

        t0 = time.perf_counter()
        sc = simulator.load_scene(scene)
        effects = dict(parse_effect_option(text) for text in (effect or []))
        inputs = [scene] + ([sc.thickness_path] if sc.thickness_path else [])
        io.check_not_an_input(output, inputs)
        recording, truth = simulator.simulate_recording(sc, effects=effects, seed=seed)
        write_output(output, recording, description="dslrxr simulate", stage="simulate",
                     parameters={"scene": str(scene), "effects": truth["effects"], "seed": seed},
                     inputs=inputs, timings_s={"simulate": time.perf_counter() - t0},
                     results={"pulse_pixels": int(truth["pulse_mask"].sum())})
        typer.echo(f"wrote {output} ({recording.shape[0]}x{recording.shape[1]}, "
                   f"effects: {', '.join(truth['effects']) or 'none'})")

    @app.command("diagnose")
    def diagnose_cmd(
        scene: Path = typer.Argument(..., help="Scene TOML file (geometry, object, start values)."),
        recording: Path = typer.Argument(..., help="Single-channel linear recording (TIFF etc.)."),
        output: Path = typer.Option(..., "-o", "--output", help="Report folder."),
        params_file: Optional[Path] = typer.Option(
            None, "-c", "--config", help="Parameter file (its diagnose section; options override it)."),
        max_terms: Optional[int] = typer.Option(None, "--max-terms", help=option_help("diagnose", "max_terms")),
        candidates: Optional[str] = typer.Option(
            None, "--candidates", help=option_help("diagnose", "candidates",
                                                   "comma-separated library terms to consider")),
        binning: str = typer.Option(
            "auto", "--binning", help="Block-averaging of the fit: auto (large frames binned while the "
                                      "blur stays >= 1 binned px) or an integer N >= 1."),
    ) -> None:
        """Locate and name what the base model of the scene leaves out of a recording."""
        from ..core import diagnosis, io
        from ..core.diagnosis import report
        from ..core.simulation import simulator
        from ..core.errors import InputError
        from ..core.params import load_section

        t0 = time.perf_counter()
        names = None if candidates is None else [n.strip() for n in candidates.split(",") if n.strip()]
        settings = load_section(params_file, "diagnose", max_terms=max_terms, candidates=names)
        sc = simulator.load_scene(scene)
        loaded = io.read_image(recording)
        data = loaded.data
        if data.ndim != 2:
            raise InputError(recording, f"diagnosis needs a single-channel recording, got shape {data.shape}")
        from dataclasses import replace

        result = diagnosis.diagnose_scene(
            sc, data, replace(settings.options(), binning=diagnosis.parse_binning(binning)))
        inputs = [scene, recording] + ([sc.thickness_path] if sc.thickness_path else []) + (
            [params_file] if params_file is not None else [])
        report.write_report(result, output, inputs=inputs,
                            parameters={"scene": str(scene), "recording": str(recording),
                                        "max_terms": settings.max_terms,
                                        "candidates": tuple(settings.candidates) or None,
                                        "binning": binning, "binning_used": result.binning},
                            timings_s={"diagnose": time.perf_counter() - t0})
        typer.echo(result.message)
        typer.echo(f"base chi2/dof {result.base_chi2_per_dof:.4f} -> final {result.final_chi2_per_dof:.4f}; "
                   f"wrote {output / 'diagnosis.json'}")
