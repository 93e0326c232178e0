"""The impulse stage as it was before issue 13 (commit BASE), loaded from git for side-by-side figures."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

BASE_COMMIT = "5d6e0cb"
ROOT = Path(__file__).resolve().parents[1]


def load_previous():
    """The module ``impulse.py`` of BASE_COMMIT, importable as ``_previous_impulse_module``."""
    if "_previous_impulse_module" in sys.modules:
        return sys.modules["_previous_impulse_module"]
    try:
        text = subprocess.run(["git", "show", f"{BASE_COMMIT}:src/napari_dslrxr/core/impulse.py"], cwd=ROOT,
                              check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        detail = getattr(exc, "stderr", "") or exc
        raise SystemExit(f"the previous impulse stage is read from git history (commit {BASE_COMMIT}), which is "
                         f"not available here ({' '.join(str(detail).split())}); run from a full clone") from None
    # its relative imports, at their places in today's layout
    text = text.replace("from .errors import", "from napari_dslrxr.core.errors import")
    text = text.replace("from .io import", "from napari_dslrxr.core.io import")
    module = types.ModuleType("_previous_impulse_module")
    sys.modules[module.__name__] = module
    exec(compile(text, f"{BASE_COMMIT}:impulse.py", "exec"), module.__dict__)
    return module
