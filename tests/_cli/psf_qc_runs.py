"""Run ``dslrxr qc`` and ``dslrxr psf fit`` as processes on the same edges and put the kernel's
MTF beside the measured one like for like (``docs/algorithms/qc.md``, section 'A blur model
against the measured MTF'): the same frames and edge regions, one kernel per edge direction, the
kernel seen through the measurement's own LSF window (``core.qc.edge.edge_method_mtf``)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from napari_dslrxr.core.psf.psf_file import load_psf
from napari_dslrxr.core.qc.edge import edge_method_mtf

TOLERANCE = 0.03


def load_generator():
    """The tests' independent edge generator (``tests/core/psf/independent_edge_generator.py``)."""
    from core.psf import independent_edge_generator

    return independent_edge_generator


def _start(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _finish(procs) -> None:
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err


def kernel_mtf_as_measured(model, edge: dict, frequency_cy_per_mm: np.ndarray) -> np.ndarray:
    """The kernel's presampling MTF along the edge's normal through qc's LSF window (one
    distance per fit: the kernel holds the combined blur at the fit's own geometry)."""
    angle = math.radians(edge["angle_deg"])
    normal = angle if edge["direction"] == "horizontal" else math.pi / 2 - angle
    return edge_method_mtf(lambda f: model.presampling_mtf(f, 100.0, 100.0, normal), frequency_cy_per_mm,
                           model.pixel_pitch_mm, lsf_half_width_px=edge["lsf_half_width_px"],
                           oversampling=edge["oversampling"])


def run_both(out: Path, flat: Path, dark: Path, qc_runs: list, fits: dict, pitch_mm: float) -> dict:
    """Run ``dslrxr qc`` once per entry of ``qc_runs`` (a list of ``(edge file, roi)``, one per
    direction) and ``dslrxr psf fit`` once per direction of ``fits`` (its ``(edge file, roi)``
    list), all at once. Returns per direction: frequency (cycles/mm), the measured MTF (mean over
    the qc runs), its uncertainty, the kernel's MTF as qc measures it, the model and the edges."""
    procs = []
    for k, edges in enumerate(qc_runs):
        args = [a for path, _ in edges for a in ("--edge", path)]
        args += [a for _, roi in edges if roi is not None for a in ("--edge-roi", ",".join(map(str, roi)))]
        procs.append(_start("qc", "--flat", flat, "--dark", dark, *args, "--pixel-pitch-mm", pitch_mm,
                            "--air-kerma-ugy", 1, "--beam", "RQA5", "-o", out / f"qc{k}"))
    for direction, edges in fits.items():
        config = out / f"edges_{direction}.toml"
        config.write_text(f"pixel_pitch_mm = {pitch_mm!r}\n" + "".join(
            f'[[edges]]\nimage = "{Path(path).as_posix()}"\nbright = "{flat.as_posix()}"\n'
            f'dark = "{dark.as_posix()}"\nsource_to_object_mm = 100.0\nsource_to_detector_mm = 100.0\n'
            + (f"roi = {list(roi)}\n" if roi is not None else "") for path, roi in edges))
        procs.append(_start("psf", "fit", config, "-o", out / f"psf_{direction}.json"))
    _finish(procs)
    reports = [json.loads((out / f"qc{k}" / "qc.json").read_text()) for k in range(len(qc_runs))]
    result = {}
    for direction in fits:
        model = load_psf(out / f"psf_{direction}.json")
        freq = np.asarray(reports[0]["frequency_cy_per_mm"], float)
        per = [r["per_direction"][direction] for r in reports]
        measured = np.mean([p["mtf"] for p in per], axis=0)
        unc = np.sqrt(np.sum(np.square([p["mtf_uncertainty"] for p in per]), axis=0)) / len(per)
        edges = [e for r in reports for e in r["edges"] if e["direction"] == direction]
        predicted = np.mean([kernel_mtf_as_measured(model, e, freq) for e in edges], axis=0)
        result[direction] = {"f": freq, "measured": measured, "u": unc, "predicted": predicted, "model": model,
                             "edges": edges}
    return result
