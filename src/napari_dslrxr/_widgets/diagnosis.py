"""Mismatch diagnosis widget over :func:`napari_dslrxr.core.diagnosis.diagnose_scene`.

Inputs: a recording layer (single-channel linear DN) and the scene it is supposed to show,
either a scene TOML file (:func:`napari_dslrxr.core.simulation.simulator.load_scene`) or, without a
file, the scene table in the recording layer's metadata (the sample scene has one) with the
thickness map from a layer. The diagnosis runs in a thread worker (progress bar with
cancel). Results: the normalised residual maps before and after the added terms as layers
``"residual z (base model)"`` and ``"residual z (final model)"`` (blue-white-red, +-5 sigma),
also summed over 4x4 blocks (``"residual z 4x4 (...)"``, still unit variance under the null,
where smooth mismatch stands out of the pixel noise),
the mismatch regions as a Shapes layer, and the named effects with their numbers in the
read-out. "Write report" writes ``report.html`` and the JSON/TIFF files with
:func:`napari_dslrxr.core.diagnosis.report.write_report`; "Open report" shows it in the web browser.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, FileEdit, PushButton, create_widget

from ..core.diagnosis import DiagnosisOptions, DiagnosisResult, diagnose_scene, multiscale_maps, parse_binning
from ..core.errors import ParameterError
from ..core.diagnosis.report import write_report
from ..core.simulation.simulator import Scene, load_scene, parse_scene
from ._controls import param_widget, restore_defaults_button
from ._jobs import JobPanel, ReportButtonsMixin, guarded, readout_label, run_in_worker, scroll_long_readout
from ._layers import (NEXT_STEP_ADDS_LAYER, ShownLayers, finish_steps, remove_layer, reset_choices,
                      reveal_text_steps, same_geometry, show_layer_steps, single_channel_layers)

if TYPE_CHECKING:
    import napari

Z_LIMITS = (-5.0, 5.0)
BINNED_Z_LIMITS = (-3.0, 3.0)
#: Block size of the binned residual maps (unit variance under the null, like the per-pixel
#: ones), where smooth mismatch such as glare or vignetting stands out of the noise.
BINNED_BLOCK = 4
#: Points layer whose text labels the before and after maps on the canvas.
MAP_LABELS = "residual map labels"
MISMATCH_REGIONS = "mismatch regions"


def summary_text(result: DiagnosisResult) -> str:
    """The named effects and numbers, one per line, for the read-out."""
    lines = [result.message,
             f"base model χ²/dof {result.base_chi2_per_dof:.4f} → final {result.final_chi2_per_dof:.4f} "
             f"({result.n_pixels} px, binning {result.binning}×)"]
    for term in result.added:
        params = ", ".join(f"{k} = {v:.4g} ± {term.uncertainty.get(k, float('nan')):.2g}"
                           for k, v in term.params.items())
        confusable = "; confusable with " + ", ".join(f"{n} ({c:.2f})" for n, c in term.confusable_with) \
            if term.confusable_with else ""
        runner = f"; runner-up {term.runner_up} (ΔBIC {term.runner_up_delta_bic:.1f})" if term.runner_up else ""
        ambiguous = f"; AMBIGUOUS — separate by: {term.separating}" if term.ambiguous else ""
        bound = f"; at bound (not an estimate): {', '.join(term.at_bound)}" if term.at_bound else ""
        lines.append(f"+ {term.effect}: {params} (ΔBIC {term.delta_bic:.1f}, held-out Δχ² "
                     f"{term.heldout_gain:.1f}){runner}{ambiguous}{bound}{confusable}")
    lines.append(f"noise: var = {result.noise_poisson_gain_dn:.3g}·(μ − b) + {result.noise_read_dn:.3g}² DN², "
                 f"lag-1 correlation {result.noise.get('lag1_correlation', 0.0):.2f}")
    if result.registration:
        reg = result.registration
        lines.append(f"registration: shift ({reg.get('shift_x_px', 0):+.3f}, {reg.get('shift_y_px', 0):+.3f}) px, "
                     f"scale {reg.get('scale', 0):+.2e}, rotation {reg.get('rotation_deg', 0):+.3f}°")
    lines.append(f"mismatch regions (r0, c0, r1, c1 px): {result.regions or 'none'}")
    if result.unexplained:
        lines.append(f"unexplained: {'; '.join(result.signatures)} at {result.unexplained_regions}")
    return "\n".join(lines)


def binned_residual_maps(result: DiagnosisResult) -> dict[str, np.ndarray]:
    """The residual maps binned ``BINNED_BLOCK`` x ``BINNED_BLOCK``, before ("base model") and
    after ("final model")."""
    return {stage: multiscale_maps(z, result.mask, scales=(BINNED_BLOCK,))[BINNED_BLOCK]
            for z, stage in ((result.z_base, "base model"), (result.z_final, "final model"))}


def diagnose_for_display(scene: Scene, recording: np.ndarray, options: DiagnosisOptions,
                         progress=None) -> tuple[DiagnosisResult, dict[str, np.ndarray]]:
    """Worker job: the diagnosis and its binned maps (computed here, not on the GUI thread)."""
    result = diagnose_scene(scene, recording, options, progress=progress)
    return result, binned_residual_maps(result)


class DiagnosisWidget(ReportButtonsMixin, Container):
    """Run the mismatch diagnosis on a recording layer and a scene; show residuals and effects."""

    REPORT_PAGE = "report"
    REPORT_NAME = "diagnosis report"

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._recording = ComboBox(choices=self._single_channel_layers, label="recording",
                                   tooltip="the recorded radiograph in linear counts (DN), one channel "
                                           "(colour layers are not offered)")
        self._scene_file = FileEdit(mode="r", filter="*.toml", label="scene file",
                                    tooltip="the scene the recording should show (geometry, object, source, "
                                            "noise); without a file, the recording layer's own scene table")
        self._thickness = create_widget(annotation="napari.layers.Image | None", label="or thickness layer")
        self._thickness.tooltip = "object thickness map (mm) of the scene when no scene file is given"
        self._max_terms = param_widget(DiagnosisOptions, "max_terms", label="max added effects")
        self._binning = ComboBox(choices=["auto", "1", "2", "4", "8"], value="auto", label="binning",
                                 tooltip="block-averaging of the fit; auto keeps the blur at least one binned "
                                         "pixel (large frames)")
        self._run = PushButton(text="Diagnose", tooltip="fit the scene to the recording and name the effects "
                                                        "the scene leaves out")
        self._job = JobPanel(tooltip="stop the diagnosis at its next step")
        self._cancel = self._job.cancel_button
        self._readout = readout_label()
        self._report_dir = FileEdit(mode="d", label="report folder", value="diagnosis_report",
                                    tooltip="folder report.html and its JSON/TIFF files are written to")
        self._write = PushButton(text="Write report", enabled=False, tooltip="write report.html, diagnosis.json "
                                                                             "and the residual maps")
        self._open = PushButton(text="Open report", enabled=False, tooltip="show report.html in the web browser")
        self._restore = restore_defaults_button(lambda: setattr(self._max_terms, "value",
                                                                DiagnosisOptions().max_terms))
        super().__init__(widgets=[self._recording, self._scene_file, self._thickness, self._max_terms,
                                  self._binning, self._run,
                                  *self._job.widgets, self._readout, self._report_dir, self._write, self._open,
                                  self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self.result: DiagnosisResult | None = None
        self.report_paths: dict[str, Path] = {}
        self._inputs: list[Path] = []
        self._input_names: list[str] = []
        self._recording.changed.connect(self._recording_chosen)
        self._run.changed.connect(self.run)
        self._write.changed.connect(self.write)
        self._open.changed.connect(self.open_report)
        viewer.layers.events.inserted.connect(self._reset_recording_choices)
        viewer.layers.events.removed.connect(self._reset_recording_choices)
        self._recording_chosen()

    def _single_channel_layers(self, *_args) -> list:
        """Image layers holding one 2-D channel (the diagnosis' recording)."""
        return single_channel_layers(self._viewer)

    def _reset_recording_choices(self, *_args) -> None:
        reset_choices(self._recording)

    def _recording_chosen(self, *_args) -> None:
        layer = self._recording.value
        name = None if layer is None else layer.metadata.get("thickness_layer")
        if name and name in self._viewer.layers:
            self._thickness.value = self._viewer.layers[name]

    def scene(self) -> Scene:
        """The scene: the chosen file (with its own thickness map), else the recording's scene
        table (layer metadata) with the thickness layer."""
        path = self._scene_file.value
        thickness_layer = self._thickness.value
        if path and Path(path).is_file():
            scene = load_scene(path)
            self._inputs = [Path(path)] + ([scene.thickness_path] if scene.thickness_path else [])
            self._input_names = [str(p) for p in self._inputs]
            return scene
        recording = self._recording.value
        table = None if recording is None else recording.metadata.get("scene_table")
        if table is None:
            raise ParameterError("choose a scene file (*.toml)")
        if thickness_layer is None:
            raise ParameterError("choose the thickness layer of the scene")
        self._inputs = []
        self._input_names = [f"scene table of layer '{recording.name}'", f"thickness layer '{thickness_layer.name}'"]
        return parse_scene(table, source=f"{recording.name} scene", thickness=np.asarray(thickness_layer.data))

    @guarded("diagnosis")
    def run(self):
        """Diagnose in a thread worker; return the worker."""
        layer = self._recording.value
        if layer is None:
            raise ParameterError("choose the recording layer")
        recording = np.asarray(layer.data, np.float64)
        if recording.ndim != 2:
            raise ParameterError(f"{layer.name}: the diagnosis needs a single-channel recording, "
                                 f"got shape {recording.shape}")
        scene = self.scene()
        options = DiagnosisOptions(max_terms=int(self._max_terms.value),
                                   binning=parse_binning(self._binning.value))
        self._input_names.insert(0, f"recording layer '{layer.name}' ({recording.shape[1]}x{recording.shape[0]} px)")
        self._run.enabled = False
        self._readout.value = "diagnosing..."
        return run_in_worker(diagnose_for_display, scene, recording, options, progress=self._job.callback,
                             desc="mismatch diagnosis", on_returned=lambda out: self._show_steps(layer, *out),
                             on_finished=self._done, panel=self._job, readout=self._readout)

    def cancel(self) -> None:
        """Stop the diagnosis at its next step (the Cancel button)."""
        self._job.cancel()

    def _show(self, layer, result: DiagnosisResult, binned: dict[str, np.ndarray] | None = None) -> None:
        """Show a diagnosis result at once."""
        for _ in self._show_steps(layer, result, binned):
            pass

    def _show_steps(self, layer, result: DiagnosisResult,
                    binned: dict[str, np.ndarray] | None = None) -> Iterator[None]:
        """Show a diagnosis result one layer per event-loop turn (each new layer costs napari
        0.1-0.4 s on the GUI thread; six at once froze the viewer for over a second); a new
        layer shown is added hidden and shown at the next turn (:func:`show_layer_steps`).
        Stopped midway (Cancel, or a step failed), it leaves the layers as they were before:
        the ones it added are removed, the ones it updated get their previous state back
        (:class:`ShownLayers`), and ``result`` stays the previous one."""
        shown = ShownLayers(self._viewer)
        with shown.put_back_if_stopped():
            yield from self._show_steps_recorded(layer, result, binned, shown)

    def _show_steps_recorded(self, layer, result: DiagnosisResult, binned: dict[str, np.ndarray] | None,
                             shown: ShownLayers) -> Iterator[None]:
        binned = binned if binned is not None else binned_residual_maps(result)
        scale = np.asarray(layer.scale[-2:], float)
        z_scale = tuple(scale * result.binning)
        # A binned pixel's centre sits (binning - 1) / 2 recording pixels in.
        z_translate = tuple(np.asarray(layer.translate[-2:], float) + scale * (result.binning - 1) / 2.0)
        block = BINNED_BLOCK
        binned_scale = tuple(scale * result.binning * block)
        binned_translate = tuple(np.asarray(layer.translate[-2:], float)
                                 + scale * (result.binning * block - 1) / 2.0)
        # Before (base model) over the recording, after (final model) beside it, both shown
        # and labelled on the canvas.
        width = float(np.shape(layer.data)[1]) * scale[1]
        beside = np.array([0.0, width * 1.05])
        for z, stage, shift in ((result.z_base, "base model", 0.0 * beside), (result.z_final, "final model", beside)):
            yield from show_layer_steps(self._viewer, z, f"residual z ({stage})", "image", colormap="bwr",
                                        contrast_limits=Z_LIMITS, scale=z_scale,
                                        translate=tuple(np.asarray(z_translate) + shift), visible=False,
                                        shown=shown)
            yield
            yield from show_layer_steps(self._viewer, binned[stage], f"residual z {block}x{block} ({stage})", "image",
                                        colormap="bwr", contrast_limits=BINNED_Z_LIMITS, scale=binned_scale,
                                        translate=tuple(np.asarray(binned_translate) + shift), visible=True,
                                        shown=shown)
            yield
        top_left = np.asarray(layer.translate[-2:], float) - scale * 0.5
        added = ", ".join(term.effect.replace("_", " ") for term in result.added) or "nothing found"
        if MAP_LABELS not in self._viewer.layers:
            yield NEXT_STEP_ADDS_LAYER
        texts = ["before (scene as given)", f"after (+ {added})"]
        new = self._show_map_labels(np.array([top_left, top_left + beside]), width, texts, shown)
        yield
        if new is not None:
            yield from reveal_text_steps(new, "what", texts)
            yield
        rectangles = [np.array([[r0, c0], [r0, c1], [r1, c1], [r1, c0]], float) - 0.5
                      for r0, c0, r1, c1 in result.regions]
        if rectangles and MISMATCH_REGIONS not in self._viewer.layers:
            yield NEXT_STEP_ADDS_LAYER
        new = yield from self._show_regions(rectangles, layer, shown)
        yield
        if new is not None:
            # filled a turn after it was added: its rectangles and geometry took ~15 % more
            # on top of the add's turn (napari triangulates each rectangle and refreshes)
            self._fill_regions(new, rectangles, layer)
            yield
            new.visible = True
            yield
        self.result = result
        self._readout.value = summary_text(result)
        self._write.enabled = True

    # The labels and regions layers are updated in place when they exist: napari removes a
    # layer with a full garbage collection on the GUI thread. A new one is added hidden and
    # returned, to be shown at the next event-loop turn (its first draw is a turn's work).
    def _show_map_labels(self, positions: np.ndarray, width: float, texts: list[str], shown: ShownLayers):
        from napari.layers import Points

        translation = [-0.1 * width, 0.0]
        existing = self._viewer.layers[MAP_LABELS] if MAP_LABELS in self._viewer.layers else None
        if isinstance(existing, Points):
            previous = (existing.data, {"what": list(existing.features["what"])},
                        np.array(existing.text.translation))

            def restore(data=previous[0], features=previous[1], moved=previous[2]) -> None:
                existing.data, existing.features = data, features
                existing.text.translation = moved

            shown.undo_with(restore)
            existing.data = positions
            existing.features = {"what": texts}
            existing.text.translation = np.asarray(translation)
            return None
        remove_layer(self._viewer, MAP_LABELS)
        new = self._viewer.add_points(positions, name=MAP_LABELS, size=0, features={"what": texts},
                                      text={"string": "{what}", "color": "yellow", "size": 10,
                                            "anchor": "lower_left", "translation": translation},
                                      visible=False)
        shown.added(new)
        return new

    def _show_regions(self, rectangles: list[np.ndarray], layer, shown: ShownLayers):
        """Update the regions layer in place (:meth:`_update_regions`, over event-loop turns);
        or add it empty and hidden and return it, for :meth:`_fill_regions` at the next turn."""
        from napari.layers import Shapes

        name = MISMATCH_REGIONS
        existing = self._viewer.layers[name] if name in self._viewer.layers else None
        if isinstance(existing, Shapes):
            previous = [np.array(vertices) for vertices in existing.data]
            if set(existing.shape_type) <= {"rectangle"}:
                shown.undo_with(lambda: finish_steps(self._update_regions(existing, previous, layer)))
            yield from self._update_regions(existing, rectangles, layer)
            return None
        remove_layer(self._viewer, name)
        if not rectangles:
            return None
        new = self._viewer.add_shapes(name=name, visible=False, **same_geometry(layer))
        shown.added(new)
        return new

    @staticmethod
    def _fill_regions(regions, rectangles: list[np.ndarray], layer) -> None:
        geometry = same_geometry(layer)
        regions.data = []
        if rectangles:
            regions.add_rectangles(rectangles, edge_color="yellow", face_color="transparent", edge_width=2)
        regions.scale, regions.translate = geometry["scale"], geometry["translate"]

    @staticmethod
    def _update_regions(regions, rectangles: list[np.ndarray], layer) -> Iterator[None]:
        """A re-run's regions into the existing layer, touching only what changed: the same
        rectangles are left as they are, new ones replace them in one turn and the geometry
        (when it changed) follows at the next. Emptied, refilled and re-placed in one turn
        (each a refresh of the layer and of the layer list), then drawn, the update took
        90-105 ms of GUI time, the diagnosis re-run's longest block."""
        current = regions.data
        same = len(current) == len(rectangles) and all(
            np.shape(a) == np.shape(b) and np.array_equal(a, b) for a, b in zip(current, rectangles))
        if not same or set(regions.shape_type) - {"rectangle"}:
            regions.data = []
            if rectangles:
                regions.add_rectangles(rectangles, edge_color="yellow", face_color="transparent", edge_width=2)
            yield
        geometry = same_geometry(layer)
        for key in ("scale", "translate"):
            if not np.allclose(getattr(regions, key)[-2:], geometry[key]):
                setattr(regions, key, geometry[key])

    @guarded("diagnosis report")
    def write(self):
        """Write the report files into the chosen folder (in a worker: the figures take a
        second); return the worker."""
        if self.result is None:
            raise ParameterError("run the diagnosis first")
        folder = Path(self._report_dir.value)
        self._write.enabled = False
        return run_in_worker(write_report, self.result, folder, inputs=list(self._inputs),
                             input_names=list(self._input_names),
                             created=datetime.now().astimezone().isoformat(timespec="seconds"),
                             parameters={"max_terms": int(self._max_terms.value)}, desc="diagnosis report",
                             on_returned=lambda paths: self._written(folder, paths), on_finished=self._write_done,
                             panel=self._job, readout=self._readout)
