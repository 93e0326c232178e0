"""The headless core and the command line must import without Qt or napari."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import napari_dslrxr.core

FORBIDDEN = ("qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6", "napari", "vispy", "magicgui")


def _core_modules() -> list[str]:
    return sorted(f"napari_dslrxr.core.{m.name}" for m in pkgutil.iter_modules(napari_dslrxr.core.__path__))


def test_core_has_modules():
    assert "napari_dslrxr.core.io" in _core_modules()


def test_core_and_cli_import_without_gui_packages():
    modules = _core_modules() + ["napari_dslrxr.cli"]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"bad = sorted(k for k in sys.modules if k.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"GUI packages imported by the headless core: {out.stdout.strip()}"
