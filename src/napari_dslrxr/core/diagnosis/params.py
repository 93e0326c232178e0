"""Parameters of ``dslrxr diagnose`` (TOML section ``[diagnose]`` of the parameter file)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..param_fields import validate_fields
from ..simulation.physics_terms import LIBRARY

#: Names of the library terms the diagnosis may add.
TERM_NAMES: tuple[str, ...] = tuple(t.name for t in LIBRARY)


@dataclass
class DiagnoseParams:
    """What the diagnosis may add to the base model (TOML section ``[diagnose]``), checked on
    construction; the remaining settings of :class:`.mismatch.DiagnosisOptions` keep their
    defaults.

    Attributes
    ----------
    max_terms : int
        Add at most this many physics terms (0 to the library size).
    candidates : list of str
        Library terms to consider; empty = all.
    """

    max_terms: int = field(default=4, metadata={
        "help": "add at most this many physics terms to the base model", "unit": "terms",
        "min": 0, "max": len(TERM_NAMES)})
    candidates: list = field(default_factory=list, metadata={
        "help": "library terms to consider; [] = all", "choices": TERM_NAMES})

    def __post_init__(self) -> None:
        validate_fields(self, "diagnose")

    def options(self):
        """The :class:`.mismatch.DiagnosisOptions` of these settings."""
        from .mismatch import DiagnosisOptions

        return DiagnosisOptions(max_terms=self.max_terms, candidates=tuple(self.candidates) or None)
