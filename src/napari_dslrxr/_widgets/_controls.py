"""Parameter controls of the widgets, derived from the core's parameter dataclasses.

:func:`param_widget` builds a control whose range, step, default, unit and tooltip all come from
the field's metadata (the same facts the parameter file and the command line use), so a value is
accepted or refused identically everywhere; :func:`restore_defaults_button` sets them back.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ._jobs import guarded


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def param_tooltip(cls: type, name: str, *, label: str = "", section: str | None = None,
                  term: str | None = None) -> str:
    """Tooltip of the control of field ``name`` of parameter dataclass ``cls``: meaning, unit,
    range (or choices), default and where it lives in the parameter file, all from the
    field's metadata (:func:`napari_dslrxr.core.param_fields.field_info`)."""
    from ..core.param_fields import field_info

    info = field_info(cls, name)
    lines = [f"{label}: {info['help']}" if label else info["help"]]
    if term:
        lines.append(f"Technical term: {term}.")
    facts = []
    if info.get("unit"):
        facts.append(f"unit: {info['unit']}")
    if info.get("choices"):
        facts.append("one of " + ", ".join(_fmt(c) for c in info["choices"]))
    elif info.get("min") is not None or info.get("max") is not None:
        facts.append(f"range {_fmt(info.get('min'))} to {_fmt(info.get('max'))}")
    if "default" in info:
        facts.append(f"default {_fmt(info['default'])}")
    if facts:
        text = "; ".join(facts)
        lines.append(text[0].upper() + text[1:] + ".")
    if section:
        lines.append(f"Parameter file: [{section}] {name}")
    return "\n".join(lines)


def param_widget(cls: type, name: str, *, label: str, section: str | None = None, term: str | None = None,
                 slider: bool = False, **kwargs: Any):
    """The magicgui control of a parameter field: type, range, choices, default and tooltip
    all from the field's metadata (one source with the TOML comments and the CLI).

    ``kwargs`` go to the magicgui widget (e.g. ``step``); ``value`` overrides the default.
    """
    from magicgui.widgets import CheckBox, ComboBox, FloatSlider, FloatSpinBox, SpinBox

    from ..core.param_fields import field_info

    info = field_info(cls, name)
    default = kwargs.pop("value", info.get("default"))
    tooltip = param_tooltip(cls, name, label=label, section=section, term=term)
    common = {"label": label, "tooltip": tooltip, **kwargs}
    if info.get("choices"):
        return ComboBox(choices=list(info["choices"]), value=default, **common)
    if isinstance(default, bool):
        return CheckBox(value=default, **common)
    lo, hi = info.get("min"), info.get("max")
    if isinstance(default, int):
        return SpinBox(value=default, min=int(lo if lo is not None else 0), max=int(hi if hi is not None else 10**9),
                       **common)
    lo = float(lo) if lo is not None else 0.0
    hi = float(hi) if hi is not None else 1e9
    common.setdefault("step", _nice_step(hi - lo))
    if slider:
        widget = FloatSlider(value=float(default), min=lo, max=hi, **common)
        widget.native.setMinimumWidth(200)  # the track stays visible beside its label
        return widget
    return FloatSpinBox(value=float(default), min=lo, max=hi, **common)


def _nice_step(span: float) -> float:
    """A round step of about a hundredth of ``span`` (0.01 for 0..1, 1 for 0..100...)."""
    if not span > 0:
        return 0.01
    return float(10 ** np.floor(np.log10(span / 100.0)))


def restore_defaults_button(restore: Callable[[], None]):
    """A "Restore defaults" push button calling ``restore`` (errors become notifications)."""
    from magicgui.widgets import PushButton

    button = PushButton(text="Restore defaults", tooltip="set this widget's parameters back to their defaults")

    @guarded("restore defaults")
    def _restore() -> None:
        restore()

    button.changed.connect(_restore)
    return button
