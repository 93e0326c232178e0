"""Lazy re-exports for the core's package ``__init__`` modules.

A package lists its public names per submodule; a name is imported from its submodule the first
time it is used. So ``from napari_dslrxr.core import read_image`` works, while importing one
module (``napari_dslrxr.core.errors`` for the command line's start-up, one stage for a widget)
still loads only what that module needs, as before the core was split into subpackages.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping


def lazy_exports(package: str, public: Mapping[str, tuple[str, ...]]
                 ) -> tuple[list[str], Callable[[str], object], Callable[[], list[str]]]:
    """Return ``__all__``, ``__getattr__`` and ``__dir__`` for ``package``.

    ``public`` maps a submodule name (relative to ``package``) to the names it exports.
    """
    where = {name: module for module, names in public.items() for name in names}
    if len(where) != sum(len(names) for names in public.values()):
        raise ValueError(f"{package}: a public name is listed twice")
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        namespace[name] = value  # later look-ups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(where))

    return list(where), __getattr__, __dir__
