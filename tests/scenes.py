"""Scene files shared by the simulator, diagnosis and golden-output tests."""

#: A simulator scene over the phantom thickness map ``thickness.tif`` beside it.
PHANTOM_SCENE_TOML = """[geometry]
source_to_detector_mm = 1200.0
source_to_object_mm = 1000.0
pixel_pitch_mm = 0.1
[object]
thickness_mm = "thickness.tif"
material = "aluminium"
[source]
kvp = 60
"""
