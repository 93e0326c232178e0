"""Parameter file: round trip, comments, and one-line errors."""

import tomllib

import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.params import (PipelineParams, default_params_toml, load_params,
                                       params_from_dict, save_params)


def test_default_file_round_trips_and_every_key_is_commented(tmp_path):
    text = default_params_toml()
    assert params_from_dict(tomllib.loads(text)) == PipelineParams()
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if "=" in line and not line.startswith("#"):
            assert lines[i - 1].startswith("#"), line
    for section in ("impulse", "flatfield", "region", "deblur", "dynamic_range", "contrast", "output"):
        assert f"[{section}]" in text
    params = PipelineParams()
    params.contrast.detail_contrast = 0.8
    params.region.polygon_xy = [[1.0, 2.0], [30.0, 2.0], [30.0, 40.0], [1.0, 40.0]]
    params.deblur.reg = 12.5
    path = save_params(params, tmp_path / "p.toml")
    assert load_params(path) == params


@pytest.mark.parametrize("data,message", [
    ({"contrast": {"detial_contrast": 0.5}}, "unknown key 'detial_contrast' in [contrast]; did you mean 'detail_contrast'?"),
    ({"contrst": {}}, "did you mean '[contrast]'"),
    ({"contrast": {"levels": "many"}}, "contrast.levels: expected an integer"),
    ({"contrast": {"bone_contrast": 10.0}}, "contrast.bone_contrast: 10.0 is out of range"),
    ({"region": {"rectify": 1}}, "region.rectify: expected true or false"),
    ({"deblur": {"reg": "automatic"}}, "deblur.reg"),
    ({"output": {"polarity": "bone"}}, "output.polarity: must be one of"),
    ({"impulse": {"window_px": 4}}, "impulse.window_px"),
])
def test_bad_values_give_one_line_errors(data, message):
    with pytest.raises(ParameterError) as err:
        params_from_dict(data)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ParameterError, match="not found"):
        load_params(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[contrast\nlevels = 3\n")
    with pytest.raises(ParameterError, match="not valid TOML"):
        load_params(bad)
    partial = tmp_path / "partial.toml"
    partial.write_text("[contrast]\nlevels = 5\n")
    assert load_params(partial).contrast.levels == 5
    assert load_params(partial).dynamic_range == PipelineParams().dynamic_range


@pytest.mark.parametrize("data,message", [
    ({"deblur": {"reg": float("inf")}}, "deblur.reg"),
    ({"deblur": {"reg": 1e10}}, "deblur.reg"),
    ({"deblur": {"reg": 1e-4}}, "deblur.reg"),
    ({"region": {"polygon_xy": [[float("nan"), 0], [1, 1], [2, 2], [3, 3]]}}, "region.polygon_xy"),
    ({"flatfield": {"flat_smoothing_px": float("inf")}}, "flatfield.flat_smoothing_px"),
])
def test_non_finite_and_huge_values_refused(data, message):
    with pytest.raises(ParameterError, match=message):
        params_from_dict(data)


def test_batch_section_accepts_local_and_addresses_and_never_changes_the_run_identity(tmp_path):
    from napari_dslrxr.core.files import run_identity

    for value in ("", "local", "tcp://10.0.0.5:8786", "tls://sched.example.org:8786", "node12:8786"):
        assert params_from_dict({"batch": {"scheduler": value, "jobs": 4}}).batch.scheduler == value
    with pytest.raises(ParameterError, match="batch.scheduler: expected"):
        params_from_dict({"batch": {"scheduler": "my cluster"}})
    with pytest.raises(ParameterError, match="batch.jobs"):
        params_from_dict({"batch": {"jobs": 0}})
    frame = tmp_path / "f.bin"
    frame.write_bytes(b"frame")
    plain = PipelineParams()
    spread = params_from_dict({"batch": {"scheduler": "local", "jobs": 2}})
    assert run_identity([frame], plain) == run_identity([frame], spread)  # same DICOM UIDs
    changed = params_from_dict({"contrast": {"bone_contrast": 1.5}})
    assert run_identity([frame], plain) != run_identity([frame], changed)


def test_field_info_is_the_one_source_of_help_unit_and_range():
    from napari_dslrxr.core.stages.contrast import ContrastParams
    from napari_dslrxr.core.stages.impulse import ImpulseParams
    from napari_dslrxr.core.param_fields import field_info
    from napari_dslrxr.core.params import params_to_toml

    info = field_info(ContrastParams, "bone_contrast")
    assert (info["min"], info["max"], info["default"], info["unit"]) == (0.5, 6.0, 4.0, "gain")
    passes = field_info(ImpulseParams, "passes_h")
    assert (passes["min"], passes["max"], passes["default"]) == (0, 10, 3)
    text = params_to_toml()
    assert f"# {passes['help']} (unit: passes; range 0 to 10)" in text
    assert f"# {info['help']} (unit: gain; range 0.5 to 6)" in text
    with pytest.raises(KeyError):
        field_info(ContrastParams, "no_such_field")
