"""Save and load the parameter TOML shared with the command line (``dslrxr run -c FILE``).

The file is written and read by :func:`napari_dslrxr.core.params.save_params` and
:func:`~napari_dslrxr.core.params.load_params`, so it is exactly what the CLI takes. Saving
collects the sections of the stage widgets docked in this viewer (impulse, flat field,
deblur, dynamic range and contrast) over the last loaded file (or the defaults), so sections
without a widget (region, output) are kept as they were. Loading hands each docked widget
its section.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magicgui.widgets import Container, FileEdit, PushButton

from ..core.errors import ParameterError
from ..core.params import PipelineParams, load_params, save_params, validate_params
from ._jobs import guarded, notify_info, readout_label
from ._registry import stage_widgets

if TYPE_CHECKING:
    import napari


def widget_sections(widget: Any) -> dict[str, Any]:
    """A stage widget's parameters as ``{section: dataclass}``."""
    params = widget.get_params()
    return dict(params) if isinstance(params, dict) else {widget.SECTION: params}


def collect_params(viewer: Any, base: PipelineParams | None = None) -> PipelineParams:
    """``base`` (default: the defaults) with every docked stage widget's sections applied.

    A widget's section dataclass is converted field by field into the class the parameter
    file uses for that section, then the whole set is validated.
    """
    params = base or PipelineParams()
    updates = {}
    for widget in stage_widgets(viewer).values():
        for section, value in widget_sections(widget).items():
            target = type(getattr(params, section))
            updates[section] = target(**dataclasses.asdict(value))
    return validate_params(dataclasses.replace(params, **updates))


def distribute_params(viewer: Any, params: PipelineParams) -> list[str]:
    """Give each docked stage widget its section(s); return the sections set."""
    done = []
    for widget in stage_widgets(viewer).values():
        sections = getattr(widget, "SECTIONS", (widget.SECTION,))
        if len(sections) > 1:
            widget.set_params({s: getattr(params, s) for s in sections})
        else:
            widget.set_params(getattr(params, sections[0]))
        done.extend(sections)
    return sorted(done)


class ParamsFileWidget(Container):
    """Load/save the pipeline parameter TOML for the stage widgets of this viewer."""

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._path = FileEdit(mode="w", filter="*.toml", label="parameter file", value="params.toml",
                              tooltip="the TOML parameter file 'dslrxr run -c FILE' reads")
        self._load = PushButton(text="Load", tooltip="read the file and set every docked stage widget from it")
        self._save = PushButton(text="Save", tooltip="write the docked widgets' values as a commented TOML file")
        self._restore = PushButton(text="Restore defaults",
                                   tooltip="set every docked stage widget back to the default parameters")
        self._readout = readout_label()
        self._readout.value = "sections: none loaded (defaults)"
        super().__init__(widgets=[self._path, self._load, self._save, self._readout, self._restore])
        self.params: PipelineParams = PipelineParams()
        self._load.changed.connect(self.load)
        self._save.changed.connect(self.save)
        self._restore.changed.connect(self.restore_defaults)

    def _chosen(self) -> Path:
        path = Path(self._path.value) if self._path.value else None
        if path is None or path.is_dir() or str(path) in ("", "."):
            raise ParameterError("choose a parameter file name (*.toml)")
        return path

    @guarded("load parameters")
    def load(self) -> PipelineParams | None:
        """Read the file and set every docked stage widget from it."""
        path = self._chosen()
        params = load_params(path)
        self.params = params
        sections = distribute_params(self._viewer, params)
        self._readout.value = f"loaded {path.name}: " + (", ".join(sections) or "no stage widgets docked")
        notify_info(f"parameters loaded from {path}")
        return params

    @guarded("save parameters")
    def save(self) -> Path | None:
        """Write the docked widgets' values (over the last loaded file) as commented TOML."""
        path = self._chosen()
        params = collect_params(self._viewer, self.params)
        written = save_params(params, path)
        self.params = params
        self._readout.value = f"saved {written.name} (use: dslrxr run -c {written.name} ...)"
        notify_info(f"parameters saved to {written}")
        return written

    @guarded("restore defaults")
    def restore_defaults(self) -> list[str]:
        """Every docked stage widget back to the defaults (the file is not touched)."""
        self.params = PipelineParams()
        sections = distribute_params(self._viewer, self.params)
        self._readout.value = "defaults restored: " + (", ".join(sections) or "no stage widgets docked")
        return sections
