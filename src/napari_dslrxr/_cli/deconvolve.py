"""``dslrxr`` sub-commands for deconvolution (see the module docstring of napari_dslrxr._cli)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add this module's commands to ``app``; commands are added as the stages land."""
