"""The impulse stage as it was before issue 13 (commit BASE), loaded from git for side-by-side figures."""

from __future__ import annotations

import importlib
import subprocess
import sys
import types
from pathlib import Path

BASE_COMMIT = "5d6e0cb"
ROOT = Path(__file__).resolve().parents[1]


def _module_path(name: str) -> str:
    """Where a core module lives now (the layout may have moved since BASE)."""
    for candidate in (f"napari_dslrxr.core.{name}", f"napari_dslrxr.core.io.{name}",
                      f"napari_dslrxr.core.stages.{name}", f"napari_dslrxr.core.io.io"):
        try:
            module = importlib.import_module(candidate)
        except ImportError:
            continue
        if name == "io" and not hasattr(module, "validate_image"):
            continue
        return candidate
    raise ImportError(name)


def load_previous():
    """The module ``impulse.py`` of BASE_COMMIT, importable as ``_previous_impulse_module``."""
    if "_previous_impulse_module" in sys.modules:
        return sys.modules["_previous_impulse_module"]
    text = subprocess.run(["git", "show", f"{BASE_COMMIT}:src/napari_dslrxr/core/impulse.py"], cwd=ROOT,
                          check=True, capture_output=True, text=True).stdout
    text = text.replace("from .errors import", f"from {_module_path('errors')} import")
    text = text.replace("from .io import", f"from {_module_path('io')} import")
    module = types.ModuleType("_previous_impulse_module")
    sys.modules[module.__name__] = module
    exec(compile(text, f"{BASE_COMMIT}:impulse.py", "exec"), module.__dict__)
    return module
