"""Which stage widgets are docked in which viewer, for the shared parameter file.

Each stage widget registers itself with its viewer and exposes ``SECTION`` (its TOML table),
``get_params()`` and ``set_params(params)``. The parameter widget saves the sections of the
registered widgets and, on load, hands each widget its section. Weak references only: a
closed viewer or widget simply disappears.
"""

from __future__ import annotations

import weakref
from typing import Any

_WIDGETS: weakref.WeakKeyDictionary[Any, weakref.WeakSet] = weakref.WeakKeyDictionary()


def register_stage_widget(viewer: Any, widget: Any) -> None:
    """Record that ``widget`` (with SECTION/get_params/set_params) belongs to ``viewer``."""
    _WIDGETS.setdefault(viewer, weakref.WeakSet()).add(widget)


def stage_widgets(viewer: Any) -> dict[str, Any]:
    """The registered stage widgets of ``viewer`` by TOML section (latest one per section)."""
    found: dict[str, Any] = {}
    for widget in list(_WIDGETS.get(viewer, ())):
        found[widget.SECTION] = widget
    return found
