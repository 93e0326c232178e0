"""Screen detection on rotated / keystoned quadrilaterals; VOI window."""

import cv2
import numpy as np
import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.stages.region import RegionParams, order_corners, polygon_mask, rectify, voi_window
from napari_dslrxr.core.stages.screen import detect_screen


def _quad_frame(rng, shape, corners):
    h, w = shape
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(corners * 16).astype(np.int32)], 1, shift=4)
    truth = mask.astype(bool)
    bright = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 1.5) * 3000.0
    # some dark "object" inside the screen (attenuating), not touching the edge
    yy, xx = np.mgrid[0:h, 0:w]
    centre = corners.mean(axis=0)
    blob = ((xx - centre[0]) ** 2 / (0.2 * w) ** 2 + (yy - centre[1]) ** 2 / (0.2 * h) ** 2) < 1
    bright[blob] *= 0.2
    noisy = rng.poisson(np.maximum(bright, 0) + 20.0).astype(np.float32) + rng.normal(0, 5, shape)
    return noisy.astype(np.float32), truth


@pytest.mark.parametrize("shape,rotation,keystone", [((400, 600), 3.0, 0.15), ((512, 512), -8.0, 0.25),
                                                     ((360, 480), 15.0, 0.05), ((300, 500), 0.0, 0.3)])
def test_corner_error_and_iou(rng, shape, rotation, keystone):
    h, w = shape
    half_w, half_h = 0.38 * w, 0.38 * h
    corners = np.array([[-half_w * (1 - keystone), -half_h], [half_w * (1 - keystone), -half_h],
                        [half_w, half_h], [-half_w, half_h]])
    a = np.deg2rad(rotation)
    corners = corners @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) + [w / 2, h / 2]
    frame, truth = _quad_frame(rng, shape, corners)
    region = detect_screen(frame, RegionParams(shrink_fraction=0.0))
    diagonal = np.hypot(h, w)
    error = np.hypot(*(region.polygon_xy - order_corners(corners)).T).max()
    iou = (region.mask & truth).sum() / (region.mask | truth).sum()
    assert error < 0.005 * diagonal, error
    assert iou > 0.98, iou
    # a naive bounding box of the thresholded image is much worse on keystoned screens
    ys, xs = np.nonzero(frame > 1500)
    box = np.zeros(shape, bool)
    box[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    assert (box & truth).sum() / (box | truth).sum() < iou


def test_user_polygon_overrides_detection(rng):
    frame = rng.normal(100, 5, (100, 120)).astype(np.float32)
    poly = [[10, 10], [100, 12], [98, 90], [12, 88]]
    region = detect_screen(frame, RegionParams(polygon_xy=poly))
    assert not region.detected and np.allclose(region.polygon_xy, poly)
    assert region.mask[50, 50] and not region.mask[5, 5]
    with pytest.raises(ParameterError, match="4"):
        detect_screen(frame, RegionParams(polygon_xy=[[0, 0], [1, 1]]))


def test_voi_excludes_direct_exposure(rng):
    obj = rng.normal(0.6, 0.1, 60000)
    direct = rng.normal(0.05, 0.01, 40000)  # large unattenuated background mode
    lo, hi = voi_window(np.concatenate([obj, direct]))
    assert lo > 0.25  # window starts at the object, not the background
    lo2, _ = voi_window(np.concatenate([obj, direct]), exclude_direct_exposure=False)
    assert lo2 < 0.1


def test_rectify_restores_rectangle():
    img = np.zeros((200, 300), np.float32)
    quad = np.array([[60, 40], [240, 50], [260, 170], [40, 160]], np.float64)
    cv2.fillPoly(img, [quad.astype(np.int32)], 1.0)
    out = rectify(img, quad)
    assert out[2:-2, 2:-2].min() > 0.9


# --------------------------------------------------------------------------- collimation


def _collimated_radiograph(rng, shape, margins, rotation_deg, noise=0.02):
    """Display-orientation radiograph (bright = unexposed) with a rotated rectangular field.

    ``margins`` = (left, top, right, bottom) distances (px) of the blades from the frame's
    sides at the frame centre's level; None = blade absent. Returns the image (float32, about
    0..1) and the true field mask (pixel centres inside every blade).
    """
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    a = np.deg2rad(rotation_deg)
    # coordinates along the field's (rotated) axes, centred on the frame centre
    u = (xx - w / 2) * np.cos(a) + (yy - h / 2) * np.sin(a)
    v = -(xx - w / 2) * np.sin(a) + (yy - h / 2) * np.cos(a)
    left, top, right, bottom = margins
    truth = np.ones(shape, bool)
    for margin, coord, limit, sign in ((left, u, w / 2, -1), (right, u, w / 2, 1), (top, v, h / 2, -1),
                                       (bottom, v, h / 2, 1)):
        if margin is not None:
            truth &= sign * coord < limit - margin
    # anatomy: direct exposure (dark) with a soft-tissue ellipse and a bone rod inside the field
    field = np.full(shape, 0.08)
    tissue = ((xx - 0.5 * w) / (0.28 * w)) ** 2 + ((yy - 0.5 * h) / (0.6 * h)) ** 2 < 1
    field[tissue] = 0.45
    field[tissue & (np.abs(xx - 0.47 * w) < 0.04 * w)] = 0.8
    blade = 0.92 + 0.04 * (yy / h)  # nearly uniform, a slight scatter gradient
    image = np.where(truth, field, blade)
    image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.2)
    image += rng.normal(0, noise, shape).astype(np.float32)
    return (image * 1000).astype(np.float32), truth


@pytest.mark.parametrize("shape,margins,rotation", [
    ((400, 500), (60, 40, 80, 50), 3.0),          # four blades, rotated
    ((480, 360), (30, 90, 45, 20), -6.0),         # four blades at other positions, other tilt
    ((400, 500), (70, None, 60, None), 2.0),      # two side blades, open top and bottom (like RG3)
    ((360, 480), (None, 50, 90, 35), 0.0),        # left blade absent
])
def test_collimation_field_against_truth(rng, shape, margins, rotation):
    from napari_dslrxr.core.stages.collimation import detect_collimation

    image, truth = _collimated_radiograph(rng, shape, margins, rotation)
    region = detect_collimation(image)
    assert region.detected
    iou = (region.mask & truth).sum() / (region.mask | truth).sum()
    assert iou > 0.98, iou
    # every wrong pixel lies within 3 px of the true field's edge
    edge = truth ^ cv2.erode(truth.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    distance = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 5)
    wrong = region.mask ^ truth
    assert wrong.sum() == 0 or distance[wrong].max() <= 3.0, distance[wrong].max()
    # baseline: the whole frame (today's region for display radiographs) has IoU = field / frame
    assert truth.sum() / truth.size < 0.85
    # inset moves every blade inwards: the mask shrinks but stays inside the field
    inset = detect_collimation(image, inset_px=5.0)
    assert not (inset.mask & ~region.mask).any() and inset.mask.sum() < region.mask.sum()


def test_no_collimation_gives_the_whole_frame(rng):
    from napari_dslrxr.core.stages.collimation import detect_collimation

    image, truth = _collimated_radiograph(rng, (300, 400), (None, None, None, None), 0.0)
    assert truth.all()
    region = detect_collimation(image)
    assert not region.detected and region.mask.all()
    np.testing.assert_array_equal(region.polygon_xy, [[0, 0], [399, 0], [399, 299], [0, 299]])
    # flat, constant and pure-noise images never raise
    for plain in (np.zeros((64, 80), np.uint16), rng.normal(100, 10, (128, 128)), np.full((50, 60), 7.0)):
        assert not detect_collimation(plain).detected


def test_collimation_bad_parameters(rng):
    from napari_dslrxr.core.errors import InputError
    from napari_dslrxr.core.stages.collimation import detect_collimation

    image = rng.normal(0, 1, (64, 64))
    with pytest.raises(ParameterError, match="max_tilt_deg"):
        detect_collimation(image, max_tilt_deg=45)
    with pytest.raises(ParameterError, match="inset_px"):
        detect_collimation(image, inset_px=-1)
    with pytest.raises(InputError, match="2-D"):
        detect_collimation(np.zeros((4, 64, 64)))


def test_collimation_on_real_cr(shared_data):
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.stages.collimation import detect_collimation

    leg = read_image(shared_data / "cr_dicom" / "RG3_UNCR.dcm").data
    region = detect_collimation(leg)
    assert region.detected
    h, w = leg.shape
    # two vertical blades; the field is open at the top and bottom
    xs = region.polygon_xy[:, 0]
    assert 380 < xs[0] < 520 and 380 < xs[3] < 520 and 1170 < xs[1] < 1310 and 1170 < xs[2] < 1310, xs
    assert region.polygon_xy[0, 1] < 0 and region.polygon_xy[2, 1] > h - 1
    # the unexposed band (saturated, bright) is outside; the leg and the air beside it inside
    band = leg >= 1015
    outside = ~region.mask
    assert band[:, : w // 5].mean() > 0.95 and band[:, -w // 5:].mean() > 0.95
    assert (band & region.mask).sum() < 0.02 * band.sum()
    assert outside[:, : w // 5].all() and outside[:, -w // 5:].all()
    assert region.mask[:, 520:1170].all()
    # RG1 (chest) has no collimator band: the whole frame
    chest = read_image(shared_data / "cr_dicom" / "RG1_UNCR.dcm").data
    assert not detect_collimation(chest).detected


def test_enhance_radiograph_uses_the_collimated_field(rng):
    import dataclasses

    from napari_dslrxr.core.params import PipelineParams
    from napari_dslrxr.core.pipeline import enhance_radiograph

    h, w = 300, 400
    image, truth = _collimated_radiograph(rng, (h, w), (70, None, 60, None), 2.0)
    params = PipelineParams()
    # the field's effect on the window alone: no compression onto the display curve
    params.dynamic_range.max_clipped_percent = 100.0
    off = dataclasses.replace(params, region=dataclasses.replace(params.region, detect_collimation=False))
    white = dataclasses.replace(params, output=dataclasses.replace(params.output, outside_region="white"))
    with_field, without, white_out = (enhance_radiograph(image, p) for p in (params, off, white))
    far_outside = ~cv2.dilate(truth.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert np.all(with_field[far_outside] == 0.0) and np.all(white_out[far_outside] == 1.0)
    # without the field, the band is processed as anatomy (grey, not the fill value)
    assert without[far_outside].mean() > 0.5
    # the value-of-interest window and low-pass now see only the field: bone vs air contrast rises
    yy, xx = np.mgrid[0:h, 0:w]
    bone = truth & (np.abs(xx - 0.47 * w) < 0.02 * w) & (np.abs(yy - h / 2) < 0.2 * h)
    direct = truth & (np.abs(xx - 0.27 * w) < 0.02 * w) & (np.abs(yy - h / 2) < 0.2 * h)
    assert bone.any() and direct.any()
    spread = [out[bone].mean() - out[direct].mean() for out in (with_field, without)]
    assert spread[0] > spread[1] + 0.05, spread


def test_sampling_many_points_beyond_the_remap_limit():
    """More than 32767 samples (a 24 Mpx frame's blade profiles) in one call: no OpenCV error."""
    from napari_dslrxr.core.stages.region import _sample

    image = np.add.outer(np.arange(100.0), 1000.0 * np.arange(120.0)).astype(np.float32)  # row + 1000 col
    points = np.random.default_rng(0).uniform(0, 99, (50000, 2)).astype(np.float32)
    values = _sample(image, points)
    assert values.shape == (50000,)
    np.testing.assert_allclose(values, points[:, 1] + 1000.0 * points[:, 0], rtol=1e-4)
    assert np.isnan(_sample(image, np.array([[500.0, 5.0]], np.float32)))[0]


def test_screen_evidence_on_a_side_shorter_than_the_averaging_run(rng):
    """A candidate with a side of a few pixels (seen on a held-out corpus frame): no crash."""
    from napari_dslrxr.core.stages.region import RegionParams
    from napari_dslrxr.core.stages.screen import screen_evidence

    small = rng.normal(10.0, 1.0, (60, 80)).astype(np.float32)
    small[20:40, 30:37] += 200.0
    corners = np.array([[30.0, 20.0], [36.0, 20.0], [36.0, 39.0], [30.0, 39.0]])  # 6 px wide
    evidence = screen_evidence(small, np.ones_like(small), corners, RegionParams())
    assert evidence["border_coverage"] > 0.7 and evidence["accepted"]


def test_no_screen_border_falls_back_to_the_area_the_flat_saw_exposed(rng):
    """A starved frame whose screen border is too noisy for evidence: the region is where the flat
    was lit (not the whole frame, whose dark room the flat-field division lifts), and a flat lit
    everywhere (the camera framed part of the screen) still gives the whole frame."""
    h, w = 180, 270
    yy, xx = np.mgrid[0:h, 0:w]
    screen = (np.abs(xx - 135) < 70) & (np.abs(yy - 90) < 55)
    vignetting = (1.0 / (1.0 + 0.5 * ((xx - 135) ** 2 + (yy - 90) ** 2) / 160.0**2) ** 2).astype(np.float32)
    flat_light = vignetting * np.where(screen, 1.0, 0.004).astype(np.float32)
    # the camera frame: 3 counts in the open beam, read noise 3 counts; a limb absorbs most of it
    limb = (np.abs(xx - 135) < 40) & screen
    signal = 3.0 * flat_light * np.where(limb, 0.1, 1.0)
    frame = (rng.poisson(signal) + rng.normal(0, 3.0, signal.shape)).astype(np.float32)
    corrected = frame / np.maximum(flat_light, 1e-3 * flat_light.max())
    region = detect_screen(corrected, illumination=flat_light)
    assert not region.detected
    assert region.evidence["reason"]
    overlap = (region.mask & screen).sum() / screen.sum()
    # shrunk by 2 px, without the soft rim: about 7 % of a 140 x 110 px screen, nothing of the room
    assert 0.9 < overlap < 0.97 and (region.mask & ~screen).sum() < 0.005 * screen.sum()
    assert region.evidence["flat_exposed_fraction"] == pytest.approx(screen.mean(), abs=0.03)
    whole = detect_screen(frame, illumination=np.ones((h, w), np.float32) * vignetting)
    assert whole.mask.all() and "flat_exposed_fraction" not in whole.evidence


def test_a_dark_area_the_flat_saw_exposed_is_not_the_room(rng):
    """A dense object at the frame's side (the camera framed part of the screen) is as dark as
    a room and has a straight, strong step: on the image alone it passes for the screen's edge
    and blanks what lies beyond. The flat frame saw that area lit, so it is no surround of a
    screen: the whole frame stays the region. A screen whose surround the flat saw dark is
    still found."""
    h, w = 180, 270
    yy, xx = np.mgrid[0:h, 0:w]
    vignetting = (1.0 / (1.0 + 0.4 * ((xx - 135) ** 2 + (yy - 90) ** 2) / 160.0**2) ** 2).astype(np.float32)
    dense = xx > 200 + 0.05 * (yy - 90)  # 2 % transmission, as dark as a room lit at 2 %
    transmission = np.where(dense, 0.02, 0.6 + 0.3 * np.sin(xx / 15.0) * np.cos(yy / 20.0))
    frame = (rng.poisson(3000.0 * vignetting * transmission) + rng.normal(0, 3.0, (h, w))).astype(np.float32)
    corrected = frame / vignetting
    alone = detect_screen(corrected)
    assert alone.detected and not alone.mask[dense].any()  # the image alone is fooled
    region = detect_screen(corrected, illumination=vignetting)
    assert not region.detected and region.mask.all()
    assert "flat frame saw" in region.evidence["reason"] and region.evidence["flat_lit_surround"] > 0.9
    # a screen in a dark room: the flat is dark around it too, and the screen is accepted
    corners = np.array([[50.0, 30.0], [225.0, 40.0], [215.0, 150.0], [45.0, 140.0]])
    screen, _ = _quad_frame(rng, (h, w), corners)
    flat_light = cv2.GaussianBlur(polygon_mask((h, w), corners).astype(np.float32), (0, 0), 1.0) + 0.004
    found = detect_screen(screen / flat_light, illumination=flat_light)
    assert found.detected and found.evidence["flat_lit_surround"] == 0.0


@pytest.mark.parametrize("edge", ["left", "right", "bottom", "top"])
@pytest.mark.parametrize("with_flat", [False, True])
def test_a_screen_running_off_a_frame_edge_keeps_everything_up_to_that_edge(rng, edge, with_flat):
    """A rotated screen whose one side lies partly beyond a frame edge and another wholly beyond
    the next one (the frame cuts one of its corners off, so the visible screen is a pentagon): the region reaches that frame edge
    and blanks none of the screen away from its rim. A four-corner fit of the pentagon cut off
    a wedge beside the frame edge (1-5 % of the anatomy on corpus frames) while only the side
    lying along the frame edge counted as open."""
    h, w = 180, 270
    # the screen's top-left corner 30 px beyond the left edge, its top side beyond the top edge;
    # the other orientations are this frame turned
    corners = np.array([[-30.0, -12.0], [180.0, -6.0], [196.0, 140.0], [14.0, 158.0]])
    turns = {"left": 0, "top": 1, "right": 2, "bottom": 3}[edge]
    shape = (h, w) if turns % 2 == 0 else (w, h)
    frame_shape = (h, w)
    for _ in range(turns):  # rotate the corners 90 degrees clockwise with the frame
        frame_shape = (frame_shape[1], frame_shape[0])
        corners = np.column_stack([frame_shape[1] - 1 - corners[:, 1], corners[:, 0]])
    assert frame_shape == shape
    frame, truth = _quad_frame(rng, shape, corners)
    illumination = None
    if with_flat:
        illumination = cv2.GaussianBlur(truth.astype(np.float32), (0, 0), 1.0) + 0.004
        frame = frame / illumination
    region = detect_screen(frame, illumination=illumination)
    assert region.detected, region.evidence
    # both frame edges that cut the screen are open sides (the next edge clockwise is the other)
    cut_too = {"left": "top", "top": "right", "right": "bottom", "bottom": "left"}[edge]
    assert {edge, cut_too} <= set(region.evidence["open_sides"]), region.evidence["open_sides"]
    # the screen away from its soft rim (the rim only where the frame did not cut it)
    away_from_rim = cv2.erode(truth.astype(np.uint8), np.ones((9, 9), np.uint8), borderType=cv2.BORDER_CONSTANT,
                              borderValue=1).astype(bool)
    blanked = (away_from_rim & ~region.mask).sum() / away_from_rim.sum()
    assert blanked < 0.002, blanked
    # the room the closing adds beside the cut corner is small, and gone where the flat saw it dark
    room = (region.mask & ~truth).sum() / truth.sum()
    assert room < (0.005 if with_flat else 0.03), room
    if with_flat:
        # nor the soft rim, even where it meets the frame's edge: there the flat-field division of
        # little light by little light lifts it to any level, which takes the display window
        assert not (region.mask & (illumination < 0.5)).any()



def test_of_two_accepted_screen_candidates_the_one_whose_surround_the_flat_saw_lit_loses(rng, monkeypatch):
    """Dense anatomy along a screen's edge, as dark as the room, puts the brighter candidate's
    side across the screen; the wedge beyond it is under 1 % of the surround (0.9 % on a corpus
    chest), so both candidates pass on evidence, and the screen is only a few per cent larger
    (not the 10 % that tells a real area from the blurred rim). The flat saw the wedge lit: the
    candidate whose surround it saw dark is the screen (the other blanked 1.4 % of the chest)."""
    from napari_dslrxr.core.stages import screen as screen_stage

    h, w = 180, 270
    corners = np.array([[58.0, 26.0], [184.0, 10.0], [194.0, 138.0], [84.0, 152.0]])
    cut = np.array([[58.0, 26.0], [184.0, 10.0], [194.0, 138.0], [80.0, 136.0]])
    screen = polygon_mask((h, w), corners)
    frame = np.where(screen, 500.0, 3.0).astype(np.float32) + rng.normal(0, 3.0, (h, w)).astype(np.float32)
    flat_light = screen.astype(np.float32) + 0.004
    candidates = iter([(cut, []), (corners, [])])
    monkeypatch.setattr(screen_stage, "_candidate_corners", lambda *args: next(candidates))

    def evidence(small, noise, quad, params, flat_lit=None, frame_cuts=()):
        # both pass on evidence; only the cut one leaves lit flat in its surround
        lit = 0.0088 if np.array_equal(quad, cut) else 0.0
        return {"open_sides": [], "open_side_index": [], "border_coverage": 0.8, "border_contrast_sigma": 20.0,
                "bright_surround": 0.0, "flat_lit_surround": lit, "accepted": True}

    monkeypatch.setattr(screen_stage, "screen_evidence", evidence)
    region = detect_screen(frame / flat_light, illumination=flat_light, params=RegionParams(shrink_fraction=0.0))
    assert region.detected and region.evidence["flat_lit_surround"] == 0.0, region.evidence
    inner = cv2.erode(screen.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert not (inner & ~region.mask).any()


def test_a_dark_defect_of_the_flat_inside_a_frame_cut_screen_is_not_taken_for_its_rim(rng):
    """The rule that keeps a frame-cut screen's region away from the flat's soft rim must not cut
    holes in the middle: dust or a marker that darkens the flat by 55 % inside the screen is
    anatomy's ground, not rim."""
    h, w = 180, 270
    corners = np.array([[-30.0, -12.0], [180.0, -6.0], [196.0, 140.0], [14.0, 158.0]])
    frame, truth = _quad_frame(rng, (h, w), corners)
    rows, cols = np.mgrid[0:h, 0:w]
    dust = 1.0 - 0.55 * np.exp(-((rows - 80) ** 2 + (cols - 100) ** 2) / (2 * 4.0**2))
    illumination = (cv2.GaussianBlur(truth.astype(np.float32), (0, 0), 1.0) + 0.004) * dust
    region = detect_screen(frame * dust / illumination, illumination=illumination)
    assert region.detected, region.evidence
    assert region.mask[70:91, 90:111].all(), (~region.mask[70:91, 90:111]).sum()


def _soft_blade(rng, shape=(600, 800), blade_x=160, tail_px=5.0, sigma_px=1.2, noise=0.004):
    """A left blade (bright, display orientation) whose edge has a steep step and then a long
    exponential tail into a dark field (like the NEMA CR leg's blades)."""
    h, w = shape
    xx = np.broadcast_to(np.arange(w, dtype=np.float64), shape)
    inside = xx - blade_x  # px into the field
    field_level, blade_level = 0.1, 0.9
    step = blade_level - field_level
    # 70 % of the step drops at the edge, the last 30 % decays with ``tail_px``
    edge = np.where(inside < 0, blade_level, field_level + 0.3 * step * np.exp(-np.maximum(inside, 0) / tail_px))
    # the edge's excess over the field level, as a share of the step, along a row (noise-free)
    excess = (cv2.GaussianBlur(edge.astype(np.float32), (0, 0), sigma_px)[0] - field_level) / step
    yy = np.arange(h)[:, None]
    # anatomy well inside the field (a blade is told from the field by the field's spread)
    image = np.where(((xx - 0.6 * w) / (0.2 * w)) ** 2 + ((yy - h / 2) / (0.4 * h)) ** 2 < 1, 0.5, edge)
    image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma_px)
    image += rng.normal(0, noise, shape).astype(np.float32)
    return image * 1000, excess


def test_drop_penumbra_moves_a_soft_blade_edge_past_its_tail(rng):
    from napari_dslrxr.core.stages.collimation import detect_collimation

    image, excess = _soft_blade(rng)
    at_edge = detect_collimation(image)
    dropped = detect_collimation(image, drop_penumbra=True)
    assert at_edge.detected and dropped.detected
    first_col = lambda region: int(np.argmax(region.mask[300]))  # first field column on a middle row
    # at the steepest point the field starts with ~30 % of the step still to fall
    assert excess[first_col(at_edge)] > 0.1
    # dropped: the field starts where the tail is within about 2 % of the step (3 % with the noise)
    assert excess[first_col(dropped)] < 0.03, (first_col(dropped), excess[first_col(dropped)])
    # and not far beyond it: within 3 px of where the tail reaches 2 %
    settles = int(np.argmax((excess < 0.02) & (np.arange(excess.size) > 160)))
    assert abs(first_col(dropped) - settles) <= 3, (first_col(dropped), settles)
    # the drop only moves edges inwards, and a configured inset larger than the tail still wins
    assert not (dropped.mask & ~at_edge.mask).any()
    wide = detect_collimation(image, inset_px=60.0, drop_penumbra=True)
    assert first_col(wide) == pytest.approx(first_col(at_edge) + 60, abs=1)


def test_drop_penumbra_barely_moves_a_sharp_blade(rng):
    from napari_dslrxr.core.stages.collimation import detect_collimation

    image, truth = _collimated_radiograph(rng, (400, 500), (60, 40, 80, 50), 3.0)
    at_edge = detect_collimation(image)
    dropped = detect_collimation(image, drop_penumbra=True)
    assert not (dropped.mask & ~at_edge.mask).any()
    # a 1.2 px blur settles to 2 % within about 2.5 px: no edge moves more than 5 px (with the noise and the mask's rounding)
    moved = at_edge.mask & ~dropped.mask
    distance = cv2.distanceTransform(dropped.mask.astype(np.uint8) ^ 1, cv2.DIST_L2, 5)
    assert moved.any() and distance[moved].max() <= 5.0, distance[moved].max()


@pytest.mark.realdata
def test_real_cr_leg_field_starts_past_the_blades_penumbra(shared_data):
    """NEMA CR leg (RG3): its two blades have soft edges whose faint tail, 20-30 px long, showed
    as a grey line beside the black shutter. With the penumbra dropped, the first field pixels
    along each blade are within a few % of the blade-to-field step of the field further in."""
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.stages.collimation import detect_collimation

    data = read_image(shared_data / "cr_dicom" / "RG3_UNCR.dcm").data.astype(np.float32)
    rows = range(200, 1600, 50)  # rows where direct beam lies beside both blades

    def excess_at_edges(region, reference):
        """Mean of the first 3 field pixels next to each blade, above the field level 60-70 px
        further in, as a share of the blade-to-field step (levels placed from ``reference``)."""
        out = []
        for row in rows:
            ref_cols, cols = np.nonzero(reference.mask[row])[0], np.nonzero(region.mask[row])[0]
            left, right = ref_cols[0], ref_cols[-1]
            for blade, inner, edge in (
                    (data[row, left - 40:left - 30], data[row, left + 60:left + 70], data[row, cols[0]:cols[0] + 3]),
                    (data[row, right + 31:right + 41], data[row, right - 69:right - 59],
                     data[row, cols[-1] - 2:cols[-1] + 1])):
                level, top = np.median(inner), np.median(blade)
                out.append((edge.mean() - level) / (top - level))
        return np.array(out)

    at_edge = detect_collimation(data, inset_px=9.0)  # the pipeline's 10 px per 2000 px
    dropped = detect_collimation(data, inset_px=9.0, drop_penumbra=True)
    assert at_edge.detected and dropped.detected
    assert np.median(excess_at_edges(at_edge, at_edge)) > 0.05
    assert np.median(excess_at_edges(dropped, at_edge)) < 0.03
    # the field loses only the penumbra: under 4 % of its width
    assert dropped.mask.sum() > 0.92 * at_edge.mask.sum()


def test_drop_penumbra_never_shutters_anatomy_along_a_blade(rng):
    """A limb lying along the blade (a plateau of tissue 10 px wide, then its skin line falling
    to the direct beam, less than half the blade's step) looks like a penumbra to a "distance
    to the field level" rule; its second edge tells it apart, and it stays in the field."""
    from napari_dslrxr.core.stages.collimation import detect_collimation

    h, w = 600, 800
    xx = np.broadcast_to(np.arange(w, dtype=np.float64), (h, w))
    yy = np.arange(h)[:, None]
    image = np.where(xx < 160, 0.9, np.where(xx < 170, 0.35, 0.1))  # blade, tissue band, beam
    image = np.where(((xx - 480) / 160.0) ** 2 + ((yy - 300) / 240.0) ** 2 < 1, 0.5, image)  # anatomy inside
    image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.2) + rng.normal(0, 0.004, (h, w)).astype(np.float32)
    at_edge = detect_collimation(image * 1000)
    dropped = detect_collimation(image * 1000, drop_penumbra=True)
    assert at_edge.detected and dropped.detected
    np.testing.assert_array_equal(dropped.mask, at_edge.mask)
    assert dropped.mask[300, 162:168].all()  # the tissue band is in the field
