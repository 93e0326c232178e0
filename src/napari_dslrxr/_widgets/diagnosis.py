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

import threading
import webbrowser
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import Container, FileEdit, PushButton, SpinBox, create_widget

from ..core.diagnosis import DiagnosisOptions, DiagnosisResult, diagnose_scene, multiscale_maps
from ..core.errors import ParameterError
from ..core.diagnosis.report import write_report
from ..core.simulation.simulator import Scene, load_scene, parse_scene
from ._common import WorkCancelled, guarded, notify_info, readout_label, run_in_worker, show_layer

if TYPE_CHECKING:
    import napari

Z_LIMITS = (-5.0, 5.0)
BINNED_Z_LIMITS = (-3.0, 3.0)
#: Block size of the binned residual maps (unit variance under the null, like the per-pixel
#: ones), where smooth mismatch such as glare or vignetting stands out of the noise.
BINNED_BLOCK = 4


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
        lines.append(f"+ {term.effect}: {params} (ΔBIC {term.delta_bic:.1f}, held-out Δχ² "
                     f"{term.heldout_gain:.1f}){confusable}")
    lines.append(f"noise: var = {result.noise_poisson_gain_dn:.3g}·(μ − b) + {result.noise_read_dn:.3g}² DN²")
    lines.append(f"mismatch regions (r0, c0, r1, c1 px): {result.regions or 'none'}")
    if result.unexplained:
        lines.append(f"unexplained structure at {result.unexplained_regions}")
    return "\n".join(lines)


class DiagnosisWidget(Container):
    """Run the mismatch diagnosis on a recording layer and a scene; show residuals and effects."""

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._recording = create_widget(annotation="napari.layers.Image", label="recording")
        self._scene_file = FileEdit(mode="r", filter="*.toml", label="scene file")
        self._thickness = create_widget(annotation="napari.layers.Image | None", label="or thickness layer")
        self._max_terms = SpinBox(value=4, min=1, max=10, label="max added terms")
        self._run = PushButton(text="Diagnose")
        self._cancel = PushButton(text="Cancel", enabled=False)
        self._readout = readout_label()
        self._report_dir = FileEdit(mode="d", label="report folder", value="diagnosis_report")
        self._write = PushButton(text="Write report", enabled=False)
        self._open = PushButton(text="Open report", enabled=False)
        super().__init__(widgets=[self._recording, self._scene_file, self._thickness, self._max_terms, self._run,
                                  self._cancel, self._readout, self._report_dir, self._write, self._open])
        self.result: DiagnosisResult | None = None
        self.report_paths: dict[str, Path] = {}
        self._cancel_event = threading.Event()
        self._inputs: list[Path] = []
        self._recording.changed.connect(self._recording_chosen)
        self._run.changed.connect(self.run)
        self._cancel.changed.connect(self._cancel_event.set)
        self._write.changed.connect(self.write)
        self._open.changed.connect(self.open_report)
        self._recording_chosen()

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
            return scene
        recording = self._recording.value
        table = None if recording is None else recording.metadata.get("scene_table")
        if table is None:
            raise ParameterError("choose a scene file (*.toml)")
        if thickness_layer is None:
            raise ParameterError("choose the thickness layer of the scene")
        self._inputs = []
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
        options = DiagnosisOptions(max_terms=int(self._max_terms.value))
        self._cancel_event.clear()
        cancel = self._cancel_event

        def progress(_message: str) -> None:
            if cancel.is_set():
                raise WorkCancelled("diagnosis cancelled")

        self._run.enabled, self._cancel.enabled = False, True
        self._readout.value = "diagnosing..."
        return run_in_worker(diagnose_scene, scene, recording, options, progress=progress, desc="mismatch diagnosis",
                             on_returned=lambda result: self._show(layer, result), on_finished=self._done)

    def _done(self) -> None:
        self._run.enabled, self._cancel.enabled = True, False
        if self._readout.value.endswith("..."):
            self._readout.value = "diagnosis cancelled or failed (see notifications)"

    def _show(self, layer, result: DiagnosisResult) -> None:
        self.result = result
        scale = np.asarray(layer.scale[-2:], float)
        z_scale = tuple(scale * result.binning)
        # A binned pixel's centre sits (binning - 1) / 2 recording pixels in.
        z_translate = tuple(np.asarray(layer.translate[-2:], float) + scale * (result.binning - 1) / 2.0)
        block = BINNED_BLOCK
        binned_scale = tuple(scale * result.binning * block)
        binned_translate = tuple(np.asarray(layer.translate[-2:], float)
                                 + scale * (result.binning * block - 1) / 2.0)
        for z, stage in ((result.z_base, "base model"), (result.z_final, "final model")):
            show_layer(self._viewer, z, f"residual z ({stage})", "image", colormap="bwr", contrast_limits=Z_LIMITS,
                       scale=z_scale, translate=z_translate, visible=False)
            binned = multiscale_maps(z, result.mask, scales=(block,))[block]
            show_layer(self._viewer, binned, f"residual z {block}x{block} ({stage})", "image", colormap="bwr",
                       contrast_limits=BINNED_Z_LIMITS, scale=binned_scale, translate=binned_translate,
                       visible=stage == "final model")
        rectangles = [np.array([[r0, c0], [r0, c1], [r1, c1], [r1, c0]], float) - 0.5
                      for r0, c0, r1, c1 in result.regions]
        name = "mismatch regions"
        if name in self._viewer.layers:
            self._viewer.layers.remove(name)
        if rectangles:
            self._viewer.add_shapes(rectangles, shape_type="rectangle", name=name, edge_color="yellow",
                                    face_color="transparent", edge_width=2, scale=tuple(scale),
                                    translate=tuple(layer.translate[-2:]))
        self._readout.value = summary_text(result)
        self._write.enabled = True

    @guarded("diagnosis report")
    def write(self) -> dict[str, Path] | None:
        """Write the report files into the chosen folder."""
        if self.result is None:
            raise ParameterError("run the diagnosis first")
        folder = Path(self._report_dir.value)
        self.report_paths = write_report(self.result, folder, inputs=self._inputs,
                                         parameters={"max_terms": int(self._max_terms.value)})
        self._open.enabled = True
        notify_info(f"diagnosis report written to {folder}")
        return self.report_paths

    @guarded("open report")
    def open_report(self) -> bool:
        """Open ``report.html`` in the web browser."""
        report = self.report_paths.get("report")
        if report is None or not Path(report).is_file():
            raise ParameterError("write the report first")
        return webbrowser.open(Path(report).resolve().as_uri())
