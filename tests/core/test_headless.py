"""The headless core and the command line must import without Qt or napari."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import napari_dslrxr.core

FORBIDDEN = ("qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6", "napari", "vispy", "magicgui")


def _walk_core() -> list[pkgutil.ModuleInfo]:
    """Every module of the core, subpackages and their modules included."""
    return list(pkgutil.walk_packages(napari_dslrxr.core.__path__, prefix="napari_dslrxr.core."))


def _core_modules() -> list[str]:
    return sorted(m.name for m in _walk_core())


def test_walk_reaches_the_nested_modules():
    modules = _core_modules()
    for name in ("napari_dslrxr.core.io", "napari_dslrxr.core.io.readers", "napari_dslrxr.core.stages.impulse",
                 "napari_dslrxr.core.psf.edge_fit", "napari_dslrxr.core.simulation.simulator",
                 "napari_dslrxr.core.diagnosis.report", "napari_dslrxr.core.pipeline"):
        assert name in modules


def test_core_and_cli_import_without_gui_packages():
    modules = _core_modules() + ["napari_dslrxr.cli"]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        # the lazily re-exported names too: each resolves to its defining module
        "for m in map(importlib.import_module, sys.argv[1:]):\n"
        "    [getattr(m, name) for name in getattr(m, '__all__', ())]\n"
        f"bad = sorted(k for k in sys.modules if k.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    packages = ["napari_dslrxr.core"] + [m.name for m in _walk_core() if m.ispkg]
    out = subprocess.run([sys.executable, "-c", code, *packages], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"GUI packages imported by the headless core: {out.stdout.strip()}"


#: Libraries the command line must not load to start (``dslrxr --help`` stays quick): each
#: command imports what it needs when it runs.
HEAVY_AT_START = ("scipy", "matplotlib", "dask", "distributed", "skimage", "rawpy", "pydicom", "tifffile")


def test_cli_starts_without_heavy_libraries():
    code = (
        "import sys, napari_dslrxr.cli\n"
        f"print(','.join(sorted({{k.split('.')[0] for k in sys.modules}} & set({HEAVY_AT_START!r}))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"imported on start-up: {out.stdout.strip()}"
