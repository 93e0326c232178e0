"""Report files shared by the commands that write them (``diagnose``, ``qc``): matplotlib
figures as PNG bytes and text files written atomically."""

from __future__ import annotations

import io as _bytesio
from collections.abc import Iterable
from pathlib import Path

from ..errors import OutputError
from .writers import atomic_write


def report_folder(path: str | Path) -> Path:
    """Create the report folder (and its parents) if needed; refuse with one line if it cannot be."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the report folder ({exc.strerror})") from None
    return out


def figure_png(fig, dpi: int = 90) -> bytes:
    """PNG bytes of a matplotlib ``Figure``, without the software tag (same bytes on every run)."""
    buf = _bytesio.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return buf.getvalue()


def write_text(path: str | Path, text: str, inputs: Iterable = ()) -> Path:
    """Write a UTF-8 text file atomically (never over one of ``inputs``)."""
    def _write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    return atomic_write(path, _write, inputs=inputs)
