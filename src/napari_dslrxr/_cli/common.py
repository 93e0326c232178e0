"""Helpers shared by the sub-command modules."""

from __future__ import annotations

from pathlib import Path

from ..core.errors import ParameterError

#: Help layout of every command and command group: plain (click) text, whose option names are
#: never cut at any terminal width; the rich table layout truncates long option names
#: ("--source-to-obj…") at 80 columns.
HELP_MARKUP_MODE = None


def parse_int_list(text: str, n: int, name: str) -> list[int]:
    """Parse ``"a,b,c"`` into ``n`` integers or raise a one-line :class:`ParameterError`."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != n:
        raise ParameterError(f"{name}: expected {n} comma-separated integers, got {text!r}")
    try:
        return [int(p) for p in parts]
    except ValueError:
        raise ParameterError(f"{name}: expected integers, got {text!r}") from None


def parse_roi(text: str | None) -> tuple[int, int, int, int] | None:
    """Parse ``"r0,c0,r1,c1"`` (pixels, end exclusive) into a tuple, or None."""
    if text is None:
        return None
    r0, c0, r1, c1 = parse_int_list(text, 4, "--roi")
    if r1 <= r0 or c1 <= c0 or min(r0, c0) < 0:
        raise ParameterError(f"--roi: need 0 <= r0 < r1 and 0 <= c0 < c1, got {text!r}")
    return r0, c0, r1, c1


def ensure_parent(path: Path) -> None:
    """Create the output folder if needed (never the file itself)."""
    path.parent.mkdir(parents=True, exist_ok=True)


def option_help(section: str, name: str, text: str | None = None) -> str:
    """Help of the command-line option for field ``name`` of TOML section ``section``: the
    field's own help, unit, range and default (the parameter file's comment), and where the
    option lives in the parameter file."""
    from ..core.param_fields import describe_range, field_info
    from ..core.params import section_class

    info = field_info(section_class(section), name)
    facts = [f"unit {info['unit']}"] if info.get("unit") else []
    limits = describe_range(info)
    if limits:
        facts.append(limits)
    default = info["default"]
    if default not in (None, [], ""):
        facts.append(f"default {default:g}" if isinstance(default, float) else f"default {default}")
    body = text or info["help"]
    # "section.name" as in the error messages (square brackets are markup in the help renderer)
    return f"{body[0].upper()}{body[1:]} ({'; '.join(facts)}; file: {section}.{name})."
