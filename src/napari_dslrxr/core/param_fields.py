"""Parameter fields: the one place a parameter's default, range, unit, help and check are read.

Every parameter dataclass (one per TOML section) declares, in each field's metadata, ``help``
and, where they apply, ``unit``, ``min``, ``max`` and ``choices`` (``auto: True`` lets a number
field also be the string ``"auto"``). :func:`validate_fields`, called from the class's
``__post_init__``, checks and converts every value on construction, so a value is accepted or
refused with the same message whether it comes from a parameter file, a command-line option,
a widget or a script. :func:`field_info` gives the same facts to the TOML comments, the
command-line help and the widgets' ranges and tooltips.

This module imports nothing from the stages, so every stage can use it.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
from typing import Any

import numpy as np

from .errors import ParameterError


def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def field_info(cls: type, name: str) -> dict:
    """Help, unit, range, choices and default of field ``name`` of parameter dataclass ``cls``.

    Keys: ``help`` and ``default`` (always), ``unit``, ``min``, ``max``, ``choices`` and
    ``auto`` when the field declares them.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if name not in fields:
        raise KeyError(f"{cls.__name__} has no field {name!r}")
    f = fields[name]
    info = dict(f.metadata or {})
    info.setdefault("help", name.replace("_", " "))
    info["default"] = _default_of(f)
    return info


def describe_range(info: dict) -> str:
    """``"range 0 to 1"``, ``"one of a, b"``, ``""``: the limits of a field for help texts."""
    if info.get("choices"):
        return "one of " + ", ".join(map(str, info["choices"]))
    lo, hi = info.get("min"), info.get("max")
    if lo is None and hi is None:
        return ""
    if info.get("open_range"):
        return f"{lo:g} < value < {hi:g}"
    text = f"range {lo:g} to {hi:g}" if lo is not None and hi is not None else (
        f">= {lo:g}" if lo is not None else f"<= {hi:g}")
    return text + (' or "auto"' if info.get("auto") else "")


def _out_of_range(name: str, value, lo, hi, auto: bool) -> ParameterError:
    limits = f"[{lo}, {hi}]" if lo is not None and hi is not None else (
        f">= {lo}" if lo is not None else f"<= {hi}")
    either = ' or "auto"' if auto else ""
    return ParameterError(f"{name}: {value} is out of range {limits}{either}")


def _check_number(name: str, value, default, meta: dict):
    as_int = isinstance(default, int) and not isinstance(default, bool) and not meta.get("auto")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        if meta.get("auto"):
            raise ParameterError(f"{name}: expected a number or \"auto\", got {value!r}")
        raise ParameterError(f"{name}: expected {'an integer' if as_int else 'a number'}, got {value!r}")
    if as_int:
        if isinstance(value, numbers.Integral):
            value = int(value)
        else:
            if not float(value).is_integer():
                raise ParameterError(f"{name}: expected an integer, got {value!r}")
            value = int(value)
    else:
        value = float(value)
        if math.isnan(value):
            raise ParameterError(f"{name}: expected a number, got NaN")
    lo, hi = meta.get("min"), meta.get("max")
    if meta.get("open_range"):
        if not lo < value < hi:
            raise ParameterError(f"{name}: {value} is out of range ({lo}, {hi}), ends excluded")
    elif lo is not None and value < lo or hi is not None and value > hi:
        raise _out_of_range(name, value, lo, hi, bool(meta.get("auto")))
    return value


def _check_points(name: str, value, n: int):
    ok = len(value) == n and all(
        isinstance(p, (list, tuple)) and len(p) == 2
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in p)
        for p in value)
    if not ok:
        raise ParameterError(f"{name}: expected [] or {n} [x, y] points in pixels, got {value!r}")
    return [[float(c) for c in p] for p in value]


def check_field(section: str, f: dataclasses.Field, value):
    """Check one value of field ``f`` of TOML section ``section``; return it converted.

    Raises :class:`ParameterError` with a one-line message naming ``section.field``.
    """
    name = f"{section}.{f.name}"
    meta = f.metadata or {}
    default = _default_of(f)
    if meta.get("auto") and isinstance(value, str):
        if value.strip().lower() != "auto":
            raise ParameterError(f"{name}: expected a number or \"auto\", got {value!r}")
        return "auto"
    if meta.get("nullable") and value is None:
        return None
    if isinstance(default, bool):
        if not isinstance(value, (bool, np.bool_)):
            raise ParameterError(f"{name}: expected true or false, got {value!r}")
        return bool(value)
    if isinstance(default, (int, float)) or meta.get("auto"):
        number = _check_number(name, value, default, meta)
        if meta.get("choices") and number not in meta["choices"]:
            raise ParameterError(f"{name}: must be one of {', '.join(map(str, meta['choices']))}, got {value!r}")
        return number
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ParameterError(f"{name}: expected a string, got {value!r}")
        choices = meta.get("choices")
        if choices and value not in choices:
            hint = difflib.get_close_matches(value, choices, n=1)
            extra = f"; did you mean '{hint[0]}'?" if hint else ""
            raise ParameterError(f"{name}: must be one of {', '.join(choices)}, got {value!r}{extra}")
        return value
    if isinstance(default, (list, tuple)):
        if not isinstance(value, (list, tuple)):
            raise ParameterError(f"{name}: expected a list, got {value!r}")
        if meta.get("points") and value:
            return _check_points(name, value, int(meta["points"]))
        choices = meta.get("choices")
        if choices:
            bad = [v for v in value if v not in choices]
            if bad:
                hint = difflib.get_close_matches(str(bad[0]), choices, n=1)
                extra = f"; did you mean '{hint[0]}'?" if hint else ""
                raise ParameterError(f"{name}: {bad[0]!r} is not one of {', '.join(choices)}{extra}")
        return list(value)
    return value


def validate_fields(obj, section: str) -> None:
    """Check and convert every field of the dataclass instance ``obj`` in place.

    Call it from ``__post_init__``: construction then refuses a wrong type or an out-of-range
    value with the message the parameter file and the command line give for it.
    """
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        checked = check_field(section, f, value)
        if checked is not value:
            object.__setattr__(obj, f.name, checked)


def check_value(cls: type, section: str, name: str, value):
    """Check one value of field ``name`` of ``cls`` (e.g. a command-line option) on its own."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    return check_field(section, fields[name], value)
