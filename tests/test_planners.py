"""Planners: valid crops for every aspect, auto beats center on disocclusion, manifests."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from kbbatch import paper
from kbbatch.batch import RunReport, plan_folder, run_folder
from kbbatch.camera import Crop, depth_from_disparity
from kbbatch.manifest import ManifestError, load_manifest, plan_to_entry
from kbbatch.outputs import OutputFolderError
from kbbatch.pipeline import ClipOptions
from kbbatch.planners import PlanRequest, get_planner
from kbbatch.planners.auto import plan_disocclusion
from kbbatch.presets import Preset, load_preset, with_overrides

from .conftest import shared_photos, textured_image


def request_for(width, height, preset_name, disparity=None, **overrides):
    if disparity is None:
        disparity = np.linspace(0.2, 1.0, height, dtype=np.float32)[:, None].repeat(width, 1)
    depth = depth_from_disparity(disparity, paper.focal_px(max(width, height)))
    preset = with_overrides(load_preset(preset_name), **overrides)
    return PlanRequest(textured_image(height, width), depth, preset)


@pytest.mark.parametrize("size", [(1024, 683), (683, 1024), (1024, 1024), (1024, 256)])
@pytest.mark.parametrize("preset_name", ["slideshow", "social", "square"])
@pytest.mark.parametrize("planner", ["auto", "center", "2d"])
def test_crops_lie_inside_and_keep_the_output_aspect(size, preset_name, planner):
    request = request_for(*size, preset_name)
    plan = get_planner(planner).plan(request)
    for crop in (plan.start, plan.end):
        assert crop.inside(*size), (crop, size)
        assert crop.width_px / crop.height_px == pytest.approx(request.preset.aspect, rel=1e-6)
    ratio = plan.start.width_px / plan.end.width_px
    assert ratio == pytest.approx(request.preset.zoom)


def subject_request(preset_name: str, subject: np.ndarray, asked: list | None = None,
                    known: bool = False) -> PlanRequest:
    """A flat scene of subject's size whose salient map is subject (a probability map),
    worked out when asked for (asked records it) or, with known, already there."""
    height, width = subject.shape
    request = request_for(width, height, preset_name,
                          disparity=np.full((height, width), 8.0, np.float32))

    def saliency() -> np.ndarray:
        if asked is not None:
            asked.append(True)
        return subject

    return PlanRequest(request.image, request.depth, request.preset, saliency,
                       (lambda: subject) if known else (lambda: None))


def test_a_vertical_clip_of_a_wide_photo_frames_its_salient_subject():
    """Centred, a vertical clip of a landscape photo showed a lantern's left edge beside a black
    wall (photo 20), a rooster's comb without its eye, a sign's words cut ("COME TO LORFUL");
    with no person, animal or vehicle detected, the crop now goes where ISNet's subject is."""
    lantern = np.zeros((576, 1024), np.float32)
    lantern[120:330, 120:260] = 0.9
    plan = get_planner("auto").plan(subject_request("social", lantern))
    for crop in (plan.start, plan.end):
        assert crop.left_px <= 120 and crop.right_px >= 260, crop
    # Without the subject weighed (--planner auto without saliency), centred as before.
    from kbbatch.planners.auto import AutoPlanner

    plain = AutoPlanner(use_saliency=False).plan(subject_request("social", lantern))
    assert plain.start.center_x_px == pytest.approx(512)


def test_a_subject_no_crop_can_hold_or_none_at_all_leaves_the_crop_centred():
    pots = np.zeros((576, 1024), np.float32)  # three pots in a row: no crop frames them whole
    for left in (200, 450, 700):
        pots[250:450, left:left + 150] = 0.9
    speck = np.zeros((576, 1024), np.float32)
    speck[10:20, 10:20] = 0.9  # under SUBJECT_MIN_FRACTION of the photo
    for subject in (pots, speck, np.zeros((576, 1024), np.float32)):
        plan = get_planner("auto").plan(subject_request("social", subject))
        assert plan.start.center_x_px == pytest.approx(512)


def test_a_subject_taller_than_the_crop_is_framed_from_its_top():
    """Centred, a landscape clip of a portrait photo of two dogs, one above the other, cut the
    upper one's eyes off in both end frames; a bottle's neck is its top, however thin."""
    bottle = np.zeros((1024, 576), np.float32)
    bottle[150:200, 270:282] = 0.9  # the neck
    bottle[200:800, 200:350] = 0.9
    bottle[20:24, 500:504] = 0.9  # a speck above it: no part of the subject's extent
    plan = get_planner("auto").plan(subject_request("slideshow", bottle))
    for crop in (plan.start, plan.end):
        assert crop.top_px + 0.05 * crop.height_px <= 150, crop
        assert crop.left_px <= 200 and crop.right_px >= 350, crop
    assert plan.start.top_px >= 150 - 0.2 * plan.start.height_px  # headroom, not the sky
    # Salient streaks over a texture are no subject with a top: centred as before.
    streaks = np.zeros((1024, 576), np.float32)
    streaks[:, 100:450:40] = 0.9
    streaks[:, 101:450:40] = 0.9
    plan = get_planner("auto").plan(subject_request("slideshow", streaks))
    assert plan.start.center_y_px == pytest.approx(512)


def test_a_subject_whose_top_the_centred_crop_cuts_is_framed_with_it():
    """The Middlebury Teddy scene: a bear on a box, which a centred 16:9 crop of the 6:5 photo
    holds but for the bear's head (a few % of the subject's area, under the 10 % gain that
    moves a crop): the start and the end frame cut the head off."""
    import cv2

    bear = np.zeros((853, 1024), np.float32)
    bear[160:630, 600:900] = 0.9  # the box and the bear's body
    cv2.ellipse(bear, (750, 118), (60, 42), 0, 0, 360, 0.9, -1)  # its head, top at 76
    plan = get_planner("auto").plan(subject_request("slideshow", bear))
    assert plan.start.top_px <= 77 and plan.start.bottom_px >= 629, plan.start  # to 1 px
    assert plan.end.top_px <= 76 + 0.01 * plan.end.height_px, plan.end
    # A subject reaching the photo's top (a face filling it) has no top to keep: the end crop
    # is not pinned to the photo's edge.
    face = np.zeros((853, 1024), np.float32)
    face[0:700, 200:900] = 0.9
    plan = get_planner("auto").plan(subject_request("slideshow", face))
    assert plan.end.top_px > 20, plan.end


def test_a_subject_the_centred_crop_cuts_at_its_side_is_framed_whole():
    """Photo 20 at `square`: centred, the crop held 98 % of the lantern (under the 10 % gain that
    moves a crop) and cut its left side by 8 px, in the first frame and more in the last."""
    lantern = np.zeros((683, 1024), np.float32)
    lantern[60:434, 173:404] = 0.9
    plan = get_planner("auto").plan(subject_request("square", lantern))
    for crop in (plan.start, plan.end):
        assert crop.left_px <= 174 and crop.right_px >= 403, crop  # to 1 px


def test_a_map_already_worked_out_keeps_a_subjects_top_where_the_crop_shows_most_of_it():
    """Photo 20 at `slideshow`: a 16:9 clip of the 3:2 photo is placed as before, and ISNet is
    not run for it; but the depth stage worked its map out, and the end crop, free to move
    down for less disocclusion, cut 31 px off the lantern's top (the cup's rim on photo 16)."""
    lantern = np.zeros((683, 1024), np.float32)
    lantern[50:434, 173:404] = 0.9  # the centred crop's top is at 62
    lantern[0:50, 288:290] = 0.9  # its string, to the photo's top: thin, no top of it
    asked: list = []
    plan = get_planner("auto").plan(subject_request("slideshow", lantern, asked, known=True))
    assert not asked
    for crop in (plan.start, plan.end):
        assert crop.top_px <= 50 + 0.01 * crop.height_px, crop
    # Framing is no freer than before: a crop holding 40 % more of a subject lower down,
    # whose top and sides it keeps, stays centred.
    low = np.zeros((683, 1024), np.float32)
    low[560:660, 300:700] = 0.9
    plan = get_planner("auto").plan(subject_request("slideshow", low, known=True))
    assert plan.start.center_x_px == pytest.approx(512) and plan.start.center_y_px == (
        pytest.approx(341.5))


def test_where_framing_is_not_free_a_crop_moves_only_to_cut_less():
    """A bottle on a stand, its neck's top 22 px above the centred 16:9 crop: the crop moved to
    hold 1 % more of it, and cut 34 px."""
    from kbbatch.camera import fit_crop
    from kbbatch.planners.auto import Subject

    bottle = np.zeros((683, 1024), bool)
    bottle[40:140, 497:527] = True  # the neck
    bottle[140:560, 400:624] = True
    bottle[560:683, 480:544] = True  # the stand, to the photo's bottom
    subject = Subject(bottle, free=False)
    wide = fit_crop(1024, 683, 16 / 9, paper.START_CROP_FRACTION)
    assert subject.cut_px(wide.left_px, wide.top_px, wide.right_px) == pytest.approx(22.14)
    framed = subject.framed_by(wide)
    assert subject.cut_px(framed.left_px, framed.top_px, framed.right_px) == 0.0, framed


def test_a_side_at_the_photos_edge_or_of_scattered_specks_is_no_side_to_keep():
    """Photo 24 at `slideshow`: ISNet holds a launch tower standing at the photo's left edge
    and the rocket salient; keeping that side pulled the end crop into the top left corner,
    the rocket cut in half. A few of a rooster's feathers (photo 11) pulled it aside."""
    from kbbatch.planners.auto import Subject

    towers = np.zeros((683, 1024), bool)
    towers[150:683, 0:768] = True  # a solid subject, from the photo's left edge
    subject = Subject(towers, free=False)
    assert subject.cut_px(114.0, 118.0, 909.0) == 0.0  # the centred end crop
    feathers = np.zeros((683, 1024), bool)
    feathers[60:400:20, 620:905] = True
    assert Subject(feathers, free=False).cut_px(95.0, 50.0, 890.0) == 0.0
    whole = np.zeros((683, 1024), bool)
    whole[60:400, 620:905] = True  # a solid subject: its side is cut by 15 px
    assert Subject(whole, free=False).cut_px(95.0, 50.0, 890.0) == pytest.approx(15.0)


def test_an_animal_head_is_the_highest_point_of_its_outline(monkeypatch):
    """A walrus lying on a beach holds its head up at one end of its box: the box's top
    centre is its back. A person's head stays the box's top centre (raised arms are higher)."""
    from kbbatch.planners.auto import head_of
    from kbbatch.segment import Detection

    walrus = np.zeros((576, 1024), np.float32)
    walrus[300:420, 100:700] = 0.9  # the body
    walrus[220:300, 560:680] = 0.9  # the head, raised at the right end
    walrus[280:300, 120:200] = 0.9  # a flipper, lower than the head
    box = (100.0, 220.0, 700.0, 420.0)
    social = subject_request("social", walrus)
    head = head_of(social, Detection("dog", 0.9, box))
    assert 560 <= head.x_px <= 680 and 220 <= head.y_px <= 300
    assert head.half_width_px == pytest.approx(60)
    assert head_of(social, Detection("person", 0.9, box)).x_px == pytest.approx(400)
    # The camera leans toward it too, not toward the box's centre (the walrus's back).
    monkeypatch.setattr("kbbatch.segment.detect", lambda image: [Detection("dog", 0.9, box)])
    plan = get_planner("auto").plan(social)
    assert abs(plan.end.center_x_px - head.x_px) < 20, plan.end  # leaning to the box: 60 px off


def test_the_end_crop_keeps_the_most_heads_of_a_group(monkeypatch):
    """Five people side by side (YOLOX's boxes given: the detector itself runs in the real
    photo tests): zooming in, the end crop keeps four heads (no crop of its size keeps five),
    where it kept only the dominant one's, cutting a neighbour's face for a smaller move."""
    from kbbatch.planners.auto import head_of, keeps
    from kbbatch.segment import Detection

    boxes = [(x - 90.0, 30.0, x + 90.0, 530.0) for x in (100, 300, 700, 900)]
    boxes.append((390.0, 30.0, 610.0, 560.0))  # the dominant one, in the middle
    people = [Detection("person", 0.9, box) for box in boxes]
    people.append(Detection("person", 0.9, (20.0, 500.0, 60.0, 560.0)))  # far too small
    monkeypatch.setattr("kbbatch.segment.detect", lambda image: people)
    request = request_for(1024, 576, "slideshow", disparity=np.full((576, 1024), 8.0, np.float32))
    plan = get_planner("auto").plan(request)
    heads = [head_of(request, person) for person in people[:5]]
    assert keeps(plan.end, heads[-1])
    assert sum(keeps(plan.end, head) for head in heads) == 4, plan.end
    # A vertical end crop two heads apart would keep the middle one's centre, not its face.
    plan = get_planner("auto").plan(request_for(1024, 576, "social",
                                                disparity=np.full((576, 1024), 8.0, np.float32)))
    face = heads[-1].half_width_px
    assert face == pytest.approx(220 / 6)
    assert plan.end.left_px <= 500 - face and plan.end.right_px >= 500 + face, plan.end


def test_people_are_the_subject_beside_a_larger_vehicle(monkeypatch):
    """Two men in front of a minibus (Ultralytics' sample photo): framed by the bus, the largest
    box, the vertical end crop's edge went through one man's face."""
    from kbbatch.planners.auto import head_of, keeps
    from kbbatch.segment import Detection

    bus = Detection("bus", 0.9, (100.0, 100.0, 900.0, 500.0))
    men = [Detection("person", 0.9, (150.0, 150.0, 300.0, 560.0)),
           Detection("person", 0.8, (320.0, 160.0, 450.0, 560.0))]
    monkeypatch.setattr("kbbatch.segment.detect", lambda image: [bus, *men])
    request = request_for(1024, 576, "social", disparity=np.full((576, 1024), 8.0, np.float32))
    plan = get_planner("auto").plan(request)
    for man in men:
        assert keeps(plan.end, head_of(request, man)), plan.end
    # A man far smaller than a ship beside him (under a tenth of its box) is not its subject.
    ship = Detection("boat", 0.9, (0.0, 50.0, 1024.0, 576.0))
    speck = Detection("person", 0.9, (800.0, 400.0, 830.0, 470.0))
    monkeypatch.setattr("kbbatch.segment.detect", lambda image: [ship, speck])
    plan = get_planner("auto").plan(request)
    assert keeps(plan.end, head_of(request, ship), whole=False)  # wider than any crop
    assert not keeps(plan.end, head_of(request, speck))


def test_a_crop_showing_most_of_the_photo_never_asks_for_the_salient_map():
    """A 16:9 clip of a 16:9 photo (or a 3:2 one): placed as before, and ISNet is not run for
    it after a depth cache hit."""
    asked: list = []
    off_centre = np.zeros((576, 1024), np.float32)
    off_centre[100:300, 20:200] = 0.9
    get_planner("auto").plan(subject_request("slideshow", off_centre, asked))
    assert not asked


def real_social_plan(monkeypatch, pattern: str, what: str, working_shape: tuple[int, int],
                     preset_name: str = "social"):
    """The depth stage's result and the auto plan at `social` (or preset_name) of a shared
    photo, with the real segmentation models (skips without them or the photo)."""
    from kbbatch.images import read_image
    from kbbatch.pipeline import plan_photo, working_depth

    from .test_crowds import real_models_or_skip

    real_models_or_skip(monkeypatch)
    [path] = [p for p in shared_photos(1)[0].parent.glob(pattern)] or [None]
    if path is None:
        pytest.skip(f"{what} not found in ../shared/photos")
    photo = read_image(path)
    working, depth_result, depth = working_depth(photo, path, ClipOptions(cache_depth=False))
    assert working.shape[:2] == working_shape
    return depth_result, plan_photo(working, depth_result, depth, load_preset(preset_name),
                                    "auto")


def test_real_lantern_is_framed_whole_in_a_vertical_clip(monkeypatch):
    depth_result, plan = real_social_plan(monkeypatch, "20_*lantern*", "photo 20 (the lantern)",
                                          (683, 1024))
    salient = depth_result.segmentation.saliency >= 0.5
    for crop in (plan.start, plan.end):
        inside = salient[:, int(crop.left_px):int(crop.right_px) + 1].sum() / salient.sum()
        assert inside > 0.95, f"{inside:.2f} of the lantern in the {crop}"


def test_real_lantern_top_is_in_both_crops_of_a_landscape_clip(monkeypatch):
    """Photo 20 at `slideshow`: the lantern's top is at 107 (working px), its string above it
    reaches the photo's top; the end crop's top was at 138."""
    _, plan = real_social_plan(monkeypatch, "20_*lantern*", "photo 20 (the lantern)",
                               (683, 1024), "slideshow")
    for crop in (plan.start, plan.end):
        assert crop.top_px <= 107, crop


def test_real_walrus_face_is_in_both_crops_of_a_vertical_clip(monkeypatch):
    """Photo 09: the big walrus (YOLOX: "elephant") holds its head up at the right end of its
    box; framed by the box's top centre, the vertical clip cut its face in half."""
    _, plan = real_social_plan(monkeypatch, "09_*walrus*", "photo 09 (the walruses)",
                               (731, 1024))
    face = (785, 190, 900, 300)  # working px, looked up on the photo: brow to tusks' roots
    for crop in (plan.start, plan.end):
        assert crop.left_px <= face[0] and crop.right_px >= face[2], crop
        assert crop.top_px <= face[1] and crop.bottom_px >= face[3], crop


def test_real_hairline_is_in_both_crops_of_a_vertical_clip(monkeypatch):
    """Photo 02: a portrait whose hair reaches 28 px from the top and whose forehead begins at
    about 62 (working px). The end crop kept the head's centre and cut through the forehead
    (its top edge at 81), for less disocclusion."""
    _, plan = real_social_plan(monkeypatch, "02_*obama*", "photo 02 (the portrait)", (1024, 820))
    for crop in (plan.start, plan.end):
        assert crop.top_px <= 55, crop  # some hair above the hairline stays in


def test_of_end_crops_keeping_a_head_those_cutting_least_off_its_top_are_searched():
    from kbbatch.planners.auto import Candidate, Head, head_top_cut_px, least_cut

    # 100 px tall (its centre 50 below its top at 40): 10 px may go (the top of the hair)
    head = Head(x_px=400.0, y_px=90.0, half_width_px=60.0, top_px=40.0)
    other = Head(x_px=900.0, y_px=50.0, half_width_px=60.0, top_px=0.0)  # not in any crop

    def kept_tops(tops: list[float]) -> list[float]:
        candidates = [Candidate(Crop(400.0, top + 200.0, 360.0, 400.0), 0.0, 0.0)
                      for top in tops]
        kept = least_cut(candidates, lambda crop: head_top_cut_px(crop, [head, other]))
        return [c.crop.top_px for c in kept]

    # None cuts more than 10 px; 4 px more (1 % of the crop's 400) are as good.
    assert kept_tops([0.0, 30.0, 48.0, 52.0, 54.0, 58.0, 90.0]) == [0.0, 30.0, 48.0, 52.0, 54.0]
    # Where every crop cuts more, the least cut is searched (10 px more, and 12 within slack).
    assert kept_tops([60.0, 62.0, 70.0]) == [60.0, 62.0]
    assert least_cut([], lambda crop: 0.0) == []


def test_zoom_out_swaps_the_ends():
    plan = get_planner("auto").plan(request_for(1024, 683, "slideshow", zoom_direction="out"))
    assert plan.start.width_px < plan.end.width_px


def card_scene():
    """A near card left of centre in front of a far plane."""
    disparity = np.full((576, 1024), 8.0, np.float32)
    disparity[150:450, 250:450] = 40.0
    return disparity


def test_auto_reveals_less_than_center_on_a_card_scene():
    request = request_for(1024, 576, "slideshow", disparity=card_scene())
    auto = get_planner("auto").plan(request)
    center = get_planner("center").plan(request)
    center_value = plan_disocclusion(request, center)
    assert center_value > 0, "the centred dolly must reveal something behind the card"
    assert plan_disocclusion(request, auto) < center_value



def test_the_search_scores_the_same_in_parallel_threads(monkeypatch):
    """Candidates are rendered in threads: each must score as it does alone (no buffer shared
    between two candidates' renders)."""
    from kbbatch.planners import auto as auto_module
    from kbbatch.planners.auto import score_candidates

    request = request_for(1024, 576, "slideshow", disparity=card_scene())
    monkeypatch.setattr(auto_module, "search_threads", lambda: 1)
    _, alone, _ = score_candidates(request)
    monkeypatch.setattr(auto_module, "search_threads", lambda: 4)
    _, threaded, _ = score_candidates(request)
    assert len(alone) > 50
    assert len({c.disoccluded for c in alone}) > 5, "the card must reveal more in some crops"
    assert threaded == alone

def test_a_wide_preset_on_a_tall_thin_photo_still_plans():
    plan = get_planner("auto").plan(request_for(200, 1024, "slideshow", max_shift_px=300))
    assert plan.end.inside(200, 1024) and plan.start.inside(200, 1024)


def write(path, data):
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


CROP = {"center_x": 0.5, "center_y": 0.5, "width": 0.9}


@pytest.mark.parametrize("data, message", [
    ("{ not json", "malformed JSON at line 1"),
    ({"images": {"a.jpg": {"start": {**CROP, "width": "wide"}, "end": CROP}}},
     "image 'a.jpg': field 'start.width': 'wide' is not of type 'number'"),
    ({"images": {"a.jpg": {"start": CROP}}}, "image 'a.jpg'"),
    ({"images": {"a.jpg": {"zoom": 2}}}, "image 'a.jpg'"),
    ({"imagez": {}}, "top level"),
    ({"images": {"a.jpg": {"depth": ""}}},  # was taken for no map at all, without a word
     "image 'a.jpg': field 'depth': '' should be non-empty"),
    ({"images": {"a.jpg": {"depth": "  "}}}, "image 'a.jpg': field 'depth': '  ' does not match"),
])
def test_schema_errors_name_the_manifest_image_and_field(tmp_path, data, message):
    path = write(tmp_path / "m.json", data)
    with pytest.raises(ManifestError, match="m.json") as caught:
        load_manifest(path)
    assert message in str(caught.value)


def test_fraction_units_are_of_the_photos_width_and_height(tmp_path):
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "units": "fraction", "start": {"center_x": 0.5, "center_y": 0.5, "width": 0.9},
        "end": {"center_x": 0.25, "center_y": 0.75, "width": 0.4, "height": 0.4}}}})
    # A 2000 x 2000 photo at working width 1024; a square output.
    plan = load_manifest(path).entry("a.jpg").plan(2000, 2000, 1024, 1.0, "linear")
    to_working = 1024 / 2000
    assert plan.start == Crop(1000 * to_working, 1000 * to_working, 1800 * to_working,
                              1800 * to_working)
    assert plan.end == Crop(500 * to_working, 1500 * to_working, 800 * to_working,
                            800 * to_working)
    assert plan.parallax


def test_pixel_numbers_under_fraction_units_are_named_as_such(tmp_path):
    """Pixel crops left under "units": "fraction" were refused as a wrong aspect."""
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "units": "fraction", "start": {"center_x": 800, "center_y": 450, "width": 882.7},
        "end": {"center_x": 0.5, "center_y": 0.5, "width": 0.5}}}})
    with pytest.raises(ManifestError, match=r"image 'a.jpg'.*'start'.*center_x 800 is no "
                                            r"fraction of the photo .*\"units\": \"px\""):
        load_manifest(path).entry("a.jpg").plan(1600, 900, 1024, 16 / 9, "linear")


def test_crops_with_a_planner_are_refused_except_2d_which_drops_parallax(tmp_path):
    crops = {"start": CROP, "end": {**CROP, "width": 0.6}, "units": "fraction"}
    with pytest.raises(ManifestError, match=r"image 'a.jpg': field 'planner': the entry gives "
                                            r"crops and planner 'auto'.*'2d'"):
        load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": {**crops,
                                                                        "planner": "auto"}}}))
    with pytest.raises(ManifestError, match=r"unknown planner 'fancy'; available: auto, center"):
        load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": {"planner": "fancy"}}}))
    entry = load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": {
        **crops, "planner": "2d"}}})).entry("a.jpg")
    plan = entry.plan(1600, 900, 1024, 16 / 9, "linear")
    assert not plan.parallax
    assert plan.start.width_px == pytest.approx(0.9 * 1024)
    # What `kbbatch plan --planner 2d` writes renders as 2D again.
    request = request_for(1024, 576, "slideshow")
    flat = get_planner("2d").plan(request)
    written = plan_to_entry(flat, 1024, 576, 1024)
    assert written["planner"] == "2d"
    assert "planner" not in plan_to_entry(get_planner("center").plan(request), 1024, 576, 1024)
    reread = load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": written}}))
    assert not reread.entry("a.jpg").plan(1024, 576, 1024, 16 / 9, "linear").parallax


def test_a_second_cards_photo_of_the_same_name_and_size_is_told_from_the_first(
        tmp_path, quick_preset):
    """Two cards planned into one manifest.json: the second card's IMG_0001.JPG (same name,
    same size) kept the first one's hand-edited crops without a word, and was rendered with
    them. `plan` writes the photo's sha256 with its crops; another photo under the entry is
    said when planned and when rendered."""
    card1, card2 = tmp_path / "card1", tmp_path / "card2"
    for card, seed in ((card1, 1), (card2, 2)):
        card.mkdir()
        Image.fromarray(textured_image(300, 450, seed)).save(card / "IMG_0001.JPG")
    manifest_path = tmp_path / "manifest.json"
    options = ClipOptions(planner="center", threads=2)
    plan_folder(card1, manifest_path, quick_preset, options, show_progress=False)
    document = json.loads(manifest_path.read_text())
    entry = document["images"]["IMG_0001.JPG"]
    assert len(entry["photo_sha256"]) == 64
    entry["start"]["center_y"] = entry["end"]["center_y"] = 160.0  # edited by hand
    manifest_path.write_text(json.dumps(document))
    # the photo it was planned on: no note, in plan or render
    [kept] = plan_folder(card1, manifest_path, quick_preset, options, show_progress=False)
    assert kept.status == "kept" and kept.note is None
    same = run_folder(card1, tmp_path / "out1", quick_preset, options, show_progress=False,
                      manifest=load_manifest(manifest_path))
    assert same.results[0].status == "done" and same.results[0].note is None
    [kept] = plan_folder(card2, manifest_path, quick_preset, options, show_progress=False)
    assert kept.status == "kept"
    assert "were planned on another photo of this name" in kept.note and \
        "kept as they were" in kept.note
    other = run_folder(card2, tmp_path / "out2", quick_preset, options, show_progress=False,
                       manifest=load_manifest(manifest_path))
    assert other.results[0].status == "done"
    assert "card2/IMG_0001.JPG: its crops in" in other.results[0].note
    assert "planned on another photo of this name" in other.results[0].note


def test_crops_planned_for_a_photo_follow_it_when_resized_and_refuse_it_when_cropped(
        tmp_path, quick_preset):
    """`plan` writes pixel crops; the photo was then resized (a smaller export) and rendered
    with the old crops: a close-up of its top-left corner, without a word."""
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(300, 450, 1)).save(folder / "cat.png")
    manifest_path = tmp_path / "m.json"
    options = ClipOptions(planner="center", threads=2)
    plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    entry = load_manifest(manifest_path).entry("cat.png")
    assert entry.data["photo_size"] == {"width": 450, "height": 300}
    before = entry.plan(450, 300, 1024, quick_preset.aspect, "linear")
    after = entry.plan(900, 600, 1024, quick_preset.aspect, "linear")  # the same in working px
    for old, new in ((before.start, after.start), (before.end, after.end)):
        assert new.center_x_px == pytest.approx(old.center_x_px, abs=0.01)
        assert new.center_y_px == pytest.approx(old.center_y_px, abs=0.01)
        assert new.width_px == pytest.approx(old.width_px, abs=0.01)
    with pytest.raises(ManifestError, match=r"'photo_size': its crops were made for the photo "
                                            r"at 450x300 px; it is 300x450 px now"):
        entry.plan(300, 450, 1024, quick_preset.aspect, "linear")

    Image.fromarray(textured_image(600, 900, 1)).save(folder / "cat.png")  # resized
    results = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    assert [r.status for r in results] == ["kept"]  # kept, and said
    assert "made for the photo at 450x300 px; it is 900x600 px now: the render scales" in \
        results[0].note
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    assert [r.status for r in report.results] == ["done"]
    assert report.results[0].plan["start"]["width_px"] == pytest.approx(
        2 * entry.data["start"]["width"], rel=0.01)
    Image.fromarray(textured_image(600, 600, 1)).save(folder / "cat.png")  # cropped
    report = run_folder(folder, tmp_path / "out2", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    assert [r.status for r in report.results] == ["failed"]
    assert "made for the photo at 450x300 px; it is 600x600 px now" in report.results[0].error


def test_keys_naming_no_photo_of_the_folder_are_reported_not_ignored(tmp_path, quick_preset):
    """Entries apply by plain file name: a key with a folder, or naming a file that is no
    photo, would otherwise be dropped in silence (the photo rendered with defaults)."""
    folder = tmp_path / "in"
    (folder / "sub").mkdir(parents=True)
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    Image.fromarray(textured_image(180, 320)).save(folder / "sub" / "x.jpg")
    (folder / "notes.txt").write_text("hi")
    manifest = tmp_path / "m.json"
    keys = ["./a.jpg", "sub/x.jpg", "notes.txt", "a.jpg"]
    manifest.write_text(json.dumps({"version": 1, "images": {k: {"planner": "2d"} for k in keys}}))
    options = ClipOptions(planner="center", threads=2)
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest))
    assert [r.status for r in report.results if r.status == "done"] == ["done"]
    errors = sorted(r.error for r in report.failed)
    assert len(errors) == 3
    for key in keys[:3]:
        assert any(f"image {key!r}: no photo of that file name" in e and "m.json" in e
                   for e in errors), (key, errors)


def test_a_key_naming_a_photo_but_for_case_or_spaces_points_to_it(tmp_path, quick_preset):
    """A key in another case (a camera's IMG_0001.JPG typed in lower case) or with a space
    around it failed as "no photo of that file name" while the photo beside it was planned
    without the entry's crops, and nothing said which photo it nearly named."""
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("IMG_0001.JPG", "b.jpg"):
        Image.fromarray(textured_image(180, 320)).save(folder / name)
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {
        "img_0001.jpg": {"planner": "2d"}, " b.jpg ": {"planner": "2d"},
        "c.jpg": {"planner": "2d"}}}))
    report = run_folder(folder, tmp_path / "out", quick_preset,
                        ClipOptions(planner="center", threads=2), show_progress=False,
                        manifest=load_manifest(manifest))
    errors = {r.error.split("image ")[1].split(":")[0]: r.error for r in report.failed}
    assert "'IMG_0001.JPG' is there: a key must be its photo's exact file name" in \
        errors["'img_0001.jpg'"]
    assert "'b.jpg' is there" in errors["' b.jpg '"]
    assert " is there" not in errors["'c.jpg'"]


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_nan_and_infinity_in_a_manifest_are_refused_by_name(tmp_path, value):
    path = tmp_path / "m.json"
    path.write_text('{"version": 1, "images": {"a.jpg": {"duration_s": ' + value + "}}}")
    with pytest.raises(ManifestError, match=rf"m.json: {value} is (not a|too large a) number"):
        load_manifest(path)


@pytest.mark.parametrize("text, reason", [
    ('{"version": 1, "images": {"a.jpg": {"exclude": true}, "a.jpg": {"planner": "center"}}}',
     r"key 'a.jpg' appears twice"),  # the exclude was dropped without a word
    ('{"version": 1, "images": {"a.jpg": {"duration_s": 1' + "0" * 5000 + "}}}",
     r"10000000000000000000\.\.\. is too large a number"),  # Python's reader: traceback
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),  # RecursionError
    ('{"version": 1, "images": {"a.jpg": {"start": ' + "[" * 975 + "]" * 975 + "}}}",
     "nested too deeply"),  # read, then a RecursionError in the schema's message
])
def test_json_a_manifest_cannot_hold_is_refused_naming_it(tmp_path, text, reason):
    path = tmp_path / "m.json"
    path.write_text(text)
    with pytest.raises(ManifestError, match=rf"m.json: {reason}"):
        load_manifest(path)


def run_with_depth_of_a(folder: Path, depth: str, preset: Preset) -> tuple[RunReport, Path]:
    """The folder's batch under a manifest (beside the folder) whose a.jpg names depth."""
    manifest = folder.parent / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"depth": depth}}}))
    report = run_folder(folder, folder.parent / "out", preset, ClipOptions(threads=2),
                        show_progress=False, manifest=load_manifest(manifest))
    return report, manifest


def test_a_missing_depth_file_of_an_entry_names_the_manifest_image_and_field(tmp_path,
                                                                          quick_preset):
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    report, _ = run_with_depth_of_a(folder, "maps/a.depth.png", quick_preset)
    [failed] = report.failed
    assert "m.json: image 'a.jpg': field 'depth'" in failed.error
    assert "maps/a.depth.png is not a file" in failed.error


def test_an_entrys_depth_naming_a_colour_photo_fails_that_entry_naming_it(tmp_path,
                                                                          quick_preset):
    """`"depth": "photos/b.jpg"`, another photo: the failure read `FAILED .../b.jpg: is a
    colour picture`, as if b.jpg had failed; a.jpg failed, for its entry's field."""
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, seed=1)).save(folder / "a.jpg")
    Image.fromarray(textured_image(180, 320, seed=2)).save(folder / "b.jpg")
    report, manifest = run_with_depth_of_a(folder, "photos/b.jpg", quick_preset)
    [failed] = report.failed
    assert Path(failed.source).name == "a.jpg"
    assert failed.error.startswith(f"{manifest}: image 'a.jpg': field 'depth': "
                                   f"{folder / 'b.jpg'}: is a colour picture"), failed.error
    assert f"{folder / 'b.jpg'}: the depth map of a.jpg in {manifest}; not rendered as " \
           "a photo" in report.notes


def test_a_photo_with_its_own_entry_named_as_a_depth_map_is_still_rendered(tmp_path,
                                                                          quick_preset):
    """`"b.jpg": {"depth": "c.png"}, "c.png": {...}`: c.png was dropped as b.jpg's map, and
    its own entry failed with "no photo of that file name"; `"depth": "b.jpg"` in b.jpg's
    own entry likewise dropped b.jpg, the photo being there."""
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, seed=1)).save(folder / "b.jpg")
    Image.fromarray(textured_image(180, 320, seed=2)).save(folder / "c.png")
    manifest = folder / "m.json"
    for depth_of_b, failing in (("c.png", "c.png: is a colour picture"),
                                ("b.jpg", "names the photo itself")):
        manifest.write_text(json.dumps({"version": 1, "images": {
            "b.jpg": {"depth": depth_of_b}, "c.png": {"planner": "center"}}}))
        report = run_folder(folder, tmp_path / f"out-{depth_of_b}", quick_preset,
                            ClipOptions(threads=2), show_progress=False,
                            manifest=load_manifest(manifest))
        [failed] = report.failed
        assert Path(failed.source).name == "b.jpg", failed
        assert failed.error.startswith(f"{manifest}: image 'b.jpg': field 'depth': "), failed
        assert failing in failed.error
        assert [Path(r.source).name for r in report.results if r.status == "done"] == ["c.png"]
        assert not [note for note in report.notes if "not rendered as a photo" in note]
    # `plan` likewise: it planned the photo with itself as its depth map
    planned = {Path(r.source).name: r for r in plan_folder(
        folder, manifest, quick_preset, ClipOptions(threads=2), show_progress=False)}
    assert planned["b.jpg"].status == "failed"
    assert "field 'depth': names the photo itself" in planned["b.jpg"].error


def test_pixel_crops_of_a_pixel_or_less_are_taken_for_fractions_missing_their_units(tmp_path):
    """Crops of 0.9 and 0.6 "px" (fractions without `"units": "fraction"`) warned that the
    clip was a still picture, then failed on a crop too small to render, with no word on
    the units."""
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "start": {"center_x": 0.5, "center_y": 0.5, "width": 0.9},
        "end": {"center_x": 0.5, "center_y": 0.5, "width": 0.6}}}})
    with pytest.raises(ManifestError, match=r"image 'a.jpg': field 'start': a crop 0.9 px "
                                            r"wide.*need \"units\": \"fraction\""):
        load_manifest(path).entry("a.jpg").plan(1600, 900, 1024, 16 / 9, "linear")
    entry = load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": {
        "start": {"center_x": 1.5, "center_y": 1.5, "width": 1.6},
        "end": {"center_x": 1.5, "center_y": 1.5, "width": 1.2}}}})).entry("a.jpg")
    plan = entry.plan(1600, 900, 1024, 16 / 9, "linear")  # pixel crops: taken as such
    assert plan.end.width_px == pytest.approx(1.2 * 1024 / 1600)


def test_a_manifest_that_is_not_utf8_is_a_clear_error_and_a_bom_is_fine(tmp_path):
    document = '{"version": 1, "images": {"a.jpg": {"planner": "2d"}}}'
    (tmp_path / "u16.json").write_bytes(document.encode("utf-16"))
    with pytest.raises(ManifestError, match=r"u16.json: is not UTF-8 text"):
        load_manifest(tmp_path / "u16.json")
    (tmp_path / "bom.json").write_bytes(document.encode("utf-8-sig"))
    assert load_manifest(tmp_path / "bom.json").entry("a.jpg") is not None


def test_a_manifest_that_is_a_pipe_a_device_or_too_large_is_refused_at_once(tmp_path,
                                                                          monkeypatch):
    """`--manifest` naming a named pipe waited for a writer without a word (render and
    review), and `/dev/zero` filled the memory (10 GB in 13 s) before any error."""
    import threading

    from kbbatch import manifest as manifest_module

    pipe = tmp_path / "pipe.json"
    os.mkfifo(pipe)
    outcome: list[BaseException] = []

    def load() -> None:
        try:
            load_manifest(pipe)
        except ManifestError as error:
            outcome.append(error)

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(10)
    if reader.is_alive():  # let the blocked reader go before failing
        with open(pipe, "w"):  # noqa: PTH123 - the writer end of the pipe
            pass
        pytest.fail("reading a manifest that is a named pipe waited for a writer")
    assert "pipe.json: is not a regular file (a named pipe" in str(outcome[0])
    with pytest.raises(ManifestError, match="/dev/zero: is not a regular file"):
        load_manifest(Path("/dev/zero"))
    with pytest.raises(ManifestError, match="is a folder"):
        load_manifest(tmp_path)
    big = tmp_path / "big.json"
    big.write_text('{"version": 1, "images": {}}' + " " * 100)
    monkeypatch.setattr(manifest_module, "MANIFEST_BYTES_MAX", 64)
    with pytest.raises(ManifestError, match="big.json: is larger than any manifest"):
        load_manifest(big)


def test_a_manifest_key_names_its_photo_in_either_unicode_form(tmp_path):
    """`café.jpg` typed in a manifest (composed) and the photo a Mac wrote (decomposed) look
    the same: the entry was unused and the key reported as naming no photo."""
    import unicodedata

    composed = unicodedata.normalize("NFC", "café.jpg")
    decomposed = unicodedata.normalize("NFD", composed)
    assert composed != decomposed
    manifest = load_manifest(write(tmp_path / "m.json",
                                   {"images": {composed: {"planner": "center"}}}))
    assert manifest.entry(decomposed) is manifest.entry(composed) is not None
    assert manifest.unmatched_images({decomposed}) == []
    assert manifest.unmatched_images({"other.jpg"}) == [composed]


def test_twin_photos_whose_names_differ_only_in_unicode_form_keep_their_own_entries(
        tmp_path, quick_preset):
    """Linux keeps `café.jpg` composed and decomposed as two files. The decomposed one took
    the composed one's entry: it was skipped when the other was excluded, and `plan` wrote
    its plan over the other's hand-made crops."""
    import unicodedata

    composed = unicodedata.normalize("NFC", "café.jpg")
    decomposed = unicodedata.normalize("NFD", composed)
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, 2)).save(folder / decomposed)
    hand_crop = {"center_x": 150.0, "center_y": 90.0, "width": 200.0}
    mine = {"start": hand_crop, "end": hand_crop | {"width": 160.0}}
    manifest_path = write(tmp_path / "m.json", {"version": 1, "images": {composed: mine}})
    manifest = load_manifest(manifest_path)
    assert manifest.entry(decomposed, folder) is manifest.entries[composed]  # as a Mac saves
    Image.fromarray(textured_image(180, 320, 1)).save(folder / composed)
    assert manifest.entry(decomposed, folder) is None  # its twin's entry is not its own
    assert manifest.entry(composed, folder) is manifest.entries[composed]

    options = ClipOptions(planner="center", threads=2)
    results = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    assert sorted(r.status for r in results) == ["done", "kept"]
    written = json.loads(manifest_path.read_text())["images"]
    assert written[composed] == mine
    assert written[decomposed]["start"]["width"] > 0

    write(manifest_path, {"version": 1, "images": {composed: {"exclude": True}}})
    out = tmp_path / "out"
    report = run_folder(folder, out, quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    made = [Path(r.source).name for r in report.results if r.status == "done"]
    assert made == [decomposed]


def test_a_crop_too_small_for_floating_point_is_refused_by_name(tmp_path):
    """Its height underflowed to 0 and the error blamed the crop's aspect."""
    entry = load_manifest(write(tmp_path / "m.json", {"images": {"a.jpg": {
        "start": {"center_x": 500, "center_y": 300, "width": 400},
        "end": {"center_x": 500, "center_y": 300, "width": 5e-324}}}})).entry("a.jpg")
    with pytest.raises(ManifestError, match=r"field 'end': crop 4.941e-324 wide is too small"):
        entry.plan(1000, 600, 1024, 16 / 9, "linear")


def test_crop_outside_the_photo_is_refused(tmp_path):
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "units": "px", "start": {"center_x": 100, "center_y": 100, "width": 400},
        "end": {"center_x": 500, "center_y": 300, "width": 320}}}})
    entry = load_manifest(path).entry("a.jpg")
    with pytest.raises(ManifestError, match=r"image 'a.jpg': field 'start': crop .* outside"):
        entry.plan(1000, 600, 1024, 16 / 9, "linear")


def test_plan_into_an_existing_file_never_loses_what_is_there(tmp_path, quick_preset):
    """`plan -o` replaced a photo, and a manifest's excludes, presets, durations and hand-made
    crops, with its own plans (the default -o is manifest.json in the current folder)."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg", "c.jpg", "d.jpg")):
        Image.fromarray(textured_image(180, 320, seed)).save(folder / name)
    options = ClipOptions(planner="center", threads=2)
    photo_before = (folder / "a.jpg").read_bytes()
    with pytest.raises(OutputFolderError, match=r"a.jpg: exists and is not a manifest kbbatch "
                                                r"can update .*not replaced"):
        plan_folder(folder, folder / "a.jpg", quick_preset, options, show_progress=False)
    assert (folder / "a.jpg").read_bytes() == photo_before
    hand_crop = {"center_x": 150.0, "center_y": 90.0, "width": 200.0}
    kept = {"a.jpg": {"exclude": True},
            "b.jpg": {"start": hand_crop, "end": hand_crop | {"width": 160.0}},
            "c.jpg": {"preset": "square", "duration_s": 2.0},
            "gone.jpg": {"planner": "2d"}}
    repository = tmp_path / "repo"
    repository.mkdir()
    (repository / "m.json").write_text(json.dumps({"version": 1, "images": kept}))
    manifest_path = tmp_path / "m.json"
    manifest_path.symlink_to(repository / "m.json")  # kept in a repository, linked in
    results = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    assert [r.status for r in results] == ["kept", "kept", "done", "done", "note"]
    assert "image 'gone.jpg': no photo of that file name" in results[-1].note
    assert manifest_path.is_symlink()  # written through the link, not over it
    written = json.loads((repository / "m.json").read_text())["images"]
    for name in ("a.jpg", "b.jpg", "gone.jpg"):
        assert written[name] == kept[name], name
    c_entry = written["c.jpg"]
    assert (c_entry["preset"], c_entry["duration_s"]) == ("square", 2.0)
    assert c_entry["end"]["width"] == pytest.approx(c_entry["end"]["height"])  # square's plan
    assert written["d.jpg"]["start"]["width"] > 0
    results = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False,
                          replan=True)
    assert [r.status for r in results] == ["kept", "done", "done", "done", "note"]  # exclude stays
    written = json.loads((repository / "m.json").read_text())["images"]
    assert written["b.jpg"]["start"] != hand_crop and written["c.jpg"]["duration_s"] == 2.0
    os.mkfifo(tmp_path / "pipe.json")  # reading it to merge blocked for good
    with pytest.raises(OutputFolderError, match=r"pipe.json: not a regular file; not replaced"):
        plan_folder(folder, tmp_path / "pipe.json", quick_preset, options, show_progress=False)
    # a link to a manifest not made yet is made through, as `review` does ("not a regular
    # file" before); one whose target cannot be made says why
    (tmp_path / "new.json").symlink_to(repository / "new.json")
    plan_folder(folder, tmp_path / "new.json", quick_preset, options, show_progress=False)
    assert (tmp_path / "new.json").is_symlink()
    assert set(json.loads((repository / "new.json").read_text())["images"]) >= {"a.jpg"}
    (tmp_path / "nowhere.json").symlink_to(tmp_path / "no-folder" / "m.json")
    with pytest.raises(OutputFolderError, match=r"nowhere.json: a link to .*no-folder/m.json, "
                       r"which cannot be made"):
        plan_folder(folder, tmp_path / "nowhere.json", quick_preset, options,
                    show_progress=False)


def test_a_manifest_keeps_its_permissions_and_a_read_only_one_is_not_replaced(
        tmp_path, quick_preset):
    """Every save made the manifest 0644 (a private 0600 one became world-readable), and a
    read-only one was replaced all the same."""
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, 1)).save(folder / "a.jpg")
    options = ClipOptions(planner="center", threads=2)
    private = tmp_path / "private.json"
    private.write_text(json.dumps({"version": 1, "images": {}}))
    private.chmod(0o600)
    plan_folder(folder, private, quick_preset, options, show_progress=False)
    assert "a.jpg" in json.loads(private.read_text())["images"]
    assert private.stat().st_mode & 0o777 == 0o600
    kept = tmp_path / "kept.json"
    kept.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"planner": "2d"}}}))
    kept.chmod(0o444)
    before = kept.read_text()
    with pytest.raises(OutputFolderError, match=r"kept.json: read-only .* not replaced"):
        plan_folder(folder, kept, quick_preset, options, show_progress=False)
    assert kept.read_text() == before and kept.stat().st_mode & 0o777 == 0o444


def test_plan_keeps_an_edit_saved_while_it_plans_and_skips_the_maps_it_names(
        tmp_path, quick_preset, monkeypatch):
    """plan wrote back the manifest it read at the start: an exclude saved from `kbbatch
    review` meanwhile was lost. And it planned a depth map the manifest names as a photo,
    so the render then failed on an entry for a photo that is no photo."""
    from click.testing import CliRunner

    from kbbatch import pipeline
    from kbbatch.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg", "c.jpg")):
        Image.fromarray(textured_image(180, 320, seed)).save(folder / name)
    Image.fromarray(textured_image(180, 320, 7)[..., 0]).save(folder / "a_map.png")
    manifest_path = tmp_path / "m.json"
    manifest_path.write_text(json.dumps({"version": 1, "images": {
        "a.jpg": {"depth": "photos/a_map.png"}}}))
    real_get_planner = pipeline.get_planner

    def planner_while_the_user_saves(name):  # the user's save lands during the planning
        document = json.loads(manifest_path.read_text())
        document["images"]["c.jpg"] = {"exclude": True}
        manifest_path.write_text(json.dumps(document))
        return real_get_planner(name)

    monkeypatch.setattr(pipeline, "get_planner", planner_while_the_user_saves)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["plan", "photos", "-o", "m.json", "--planner", "center",
                                       "--preset", "preview"])
    assert result.exit_code == 0, result.output
    written = json.loads(manifest_path.read_text())["images"]
    assert sorted(written) == ["a.jpg", "b.jpg", "c.jpg"]  # no entry for the map
    assert written["c.jpg"] == {"exclude": True}
    assert written["a.jpg"]["depth"] == "photos/a_map.png" and "start" in written["a.jpg"]
    again = CliRunner().invoke(main, ["plan", "photos", "-o", "m.json", "--planner", "center",
                                      "--preset", "preview"])
    assert "3 entries with crops or excluded kept" in again.output
    assert "FAILED" not in again.output and again.exit_code == 0  # it printed "FAILED None"


def test_replan_keeps_crops_saved_while_it_plans_and_draws_no_preview_of_its_own_plan(
        tmp_path, quick_preset, monkeypatch):
    """`plan --replan` wrote its new plan over crops saved from `kbbatch review` while it
    planned, without a word; without --replan the save stayed, but the previews and the
    contact sheet drew the plan dropped."""
    from click.testing import CliRunner

    from kbbatch import pipeline
    from kbbatch.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg")):
        Image.fromarray(textured_image(180, 320, seed)).save(folder / name)
    manifest_path = tmp_path / "m.json"
    monkeypatch.chdir(tmp_path)
    plan = ["plan", "photos", "-o", "m.json", "--planner", "center", "--preset", "preview"]
    assert CliRunner().invoke(main, plan).exit_code == 0
    first = json.loads(manifest_path.read_text())["images"]
    saved = {"units": "fraction", "start": {"center_x": 0.5, "center_y": 0.5, "width": 0.9},
             "end": {"center_x": 0.3, "center_y": 0.3, "width": 0.3}}
    before = {"units": "fraction", "start": {"center_x": 0.5, "center_y": 0.5, "width": 0.8},
              "end": {"center_x": 0.6, "center_y": 0.6, "width": 0.4}}
    manifest_path.write_text(json.dumps({"version": 1, "images": {"a.jpg": before,
                                                                   "b.jpg": before}}))
    real_get_planner = pipeline.get_planner

    def planner_while_the_user_saves(name):  # the user's save lands during the planning
        document = json.loads(manifest_path.read_text())
        document["images"]["a.jpg"] = saved
        manifest_path.write_text(json.dumps(document))
        return real_get_planner(name)

    previews = tmp_path / "m-previews"
    for old in previews.iterdir():
        old.unlink()
    monkeypatch.setattr(pipeline, "get_planner", planner_while_the_user_saves)
    result = CliRunner().invoke(main, [*plan, "--replan"])
    assert result.exit_code == 0, result.output
    written = json.loads(manifest_path.read_text())["images"]
    assert written["a.jpg"] == saved
    assert written["b.jpg"] == first["b.jpg"]  # crops from before the run: planned again
    assert "a.jpg: its entry was saved while it was planned" in result.output
    assert "1 entry with crops or excluded kept as they were (saved while planning)" in \
        result.output
    assert "1 plan(s) written" in result.output
    assert sorted(p.name for p in previews.iterdir()) == ["b.jpg", "contact-sheet.png"]


def test_replan_keeps_crops_saved_meanwhile_under_a_renamed_photos_new_name(
        tmp_path, quick_preset, monkeypatch):
    """A photo renamed since it was planned, its crops saved under the new name while `plan
    --replan` ran: the plan was written over them (looked for under the old name), and the
    old name's entry stayed, naming no photo."""
    from click.testing import CliRunner

    from kbbatch import pipeline
    from kbbatch.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, 3)).save(folder / "a.jpg")
    manifest_path = tmp_path / "m.json"
    monkeypatch.chdir(tmp_path)
    plan = ["plan", "photos", "-o", "m.json", "--planner", "center", "--preset", "preview"]
    assert CliRunner().invoke(main, plan).exit_code == 0
    (folder / "a.jpg").rename(folder / "c.jpg")
    saved = {"units": "fraction", "start": {"center_x": 0.5, "center_y": 0.5, "width": 0.9},
             "end": {"center_x": 0.3, "center_y": 0.3, "width": 0.3}}
    real_get_planner = pipeline.get_planner

    def planner_while_the_user_saves(name):
        document = json.loads(manifest_path.read_text())
        document["images"]["c.jpg"] = saved
        manifest_path.write_text(json.dumps(document))
        return real_get_planner(name)

    monkeypatch.setattr(pipeline, "get_planner", planner_while_the_user_saves)
    result = CliRunner().invoke(main, [*plan, "--replan"])
    assert result.exit_code == 0, result.output
    assert json.loads(manifest_path.read_text())["images"] == {"c.jpg": saved}


def test_plan_fails_a_kept_entry_whose_crops_the_preset_cannot_render(tmp_path, quick_preset):
    """Planned at 16:9, then planned again at 9:16 (kept, as crops of its own), `plan` said
    all was well and printed a render command that failed on every such photo."""
    from click.testing import CliRunner

    from kbbatch.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    plan = ["plan", str(folder), "-o", str(tmp_path / "m.json"), "--planner", "center"]
    assert CliRunner().invoke(main, [*plan, "--preset", "preview"]).exit_code == 0
    before = (tmp_path / "m.json").read_text()
    again = CliRunner().invoke(main, [*plan, "--preset", "social"])
    assert again.exit_code == 1
    assert "FAILED" in again.output and "image 'a.jpg': field 'start': its crops are 1.778 " \
        "wide to high, the preset's clips 0.562; kept" in again.output, again.output
    assert (tmp_path / "m.json").read_text() == before
    assert CliRunner().invoke(main, [*plan, "--preset", "preview"]).exit_code == 0


def test_manifest_round_trip_renders_those_exact_crops(tmp_path, quick_preset):
    folder = tmp_path / "photos"
    folder.mkdir()
    [photo] = shared_photos(1)
    shutil.copy(photo, folder / photo.name)
    manifest_path = tmp_path / "plan" / "manifest.json"
    options = ClipOptions(planner="auto", threads=2)
    [planned] = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    assert planned.status == "done"
    assert (tmp_path / "plan" / "manifest-previews" / "contact-sheet.png").is_file()
    assert (tmp_path / "plan" / "manifest-previews" / f"{photo.stem}.jpg").is_file()
    # A person edits the end crop, then renders with the manifest.
    data = json.loads(manifest_path.read_text())
    entry = data["images"][photo.name]
    entry["end"]["center_x"] = round(entry["end"]["center_x"] + 7.5, 2)
    data["images"]["missing.jpg"] = {"duration_s": 1.0}
    data["images"]["rejected.jpg"] = {"exclude": True}  # rejected, then deleted: no failure
    manifest_path.write_text(json.dumps(data))
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    done = [r for r in report.results if r.status == "done"]
    [missing] = report.failed
    assert "missing.jpg" in missing.error and "no photo of that file name" in missing.error
    assert any("'rejected.jpg' is excluded and not in" in note for note in report.notes)
    [result] = done
    assert result.plan["planner"] == "manifest"

    for field in ("start", "end"):  # the report gives crops in the photo's pixels too
        crop = entry[field]
        expected = Crop(crop["center_x"], crop["center_y"], crop["width"], crop["height"])
        got = result.plan[field]
        assert got["center_x_px"] == pytest.approx(expected.center_x_px, abs=1e-6)
        assert got["width_px"] == pytest.approx(expected.width_px, abs=1e-6)


def test_a_depth_map_the_manifest_names_in_the_photo_folder_is_no_photo(tmp_path, quick_preset):
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    ramp = (np.linspace(0, 255, 180)[:, None] * np.ones((1, 320))).astype(np.uint8)
    Image.fromarray(ramp).save(folder / "a_map.png")  # not named <stem>.depth.png
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1,
                                    "images": {"a.jpg": {"depth": "photos/a_map.png"}}}))
    report = run_folder(folder, tmp_path / "out", quick_preset, ClipOptions(threads=2),
                        show_progress=False, manifest=load_manifest(manifest))
    assert [Path(r.source).name for r in report.results] == ["a.jpg"]
    assert report.results[0].status == "done"
    assert f"{folder / 'a_map.png'}: the depth map of a.jpg in {manifest}; not rendered as " \
           "a photo" in report.notes


def test_an_empty_output_path_is_refused_not_the_current_folder(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from kbbatch.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "photos").mkdir()
    Image.fromarray(textured_image(180, 320)).save(tmp_path / "photos" / "a.jpg")
    for command in (["photos", "-o", ""], ["plan", "photos", "-o", ""], ["status", ""]):
        result = CliRunner().invoke(main, command)
        assert result.exit_code == 2 and "an empty path" in result.output, command
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_a_duration_out_of_bounds_is_blamed_on_duration_s(tmp_path, quick_preset):
    from kbbatch.pipeline import apply_entry

    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"duration_s": 1e6}}}))
    with pytest.raises(ManifestError, match=r"m.json: image 'a.jpg': field 'duration_s': "):
        apply_entry(load_manifest(manifest).entry("a.jpg"), quick_preset, ClipOptions())


def test_plan_says_a_photo_is_too_small_as_the_render_would(tmp_path, quick_preset):
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.new("RGB", (5000, 5), (100, 150, 200)).save(folder / "strip.png")
    [result] = plan_folder(folder, tmp_path / "m.json", quick_preset, ClipOptions(),
                           show_progress=False)
    assert result.status == "failed" and "strip.png: too small for" in result.error


def test_plan_in_a_folder_whose_name_is_not_utf8_prints_a_command_that_works(tmp_path):
    """plan crashed (OpenCV's writer, a segfault) on such a manifest path; then its render
    command printed the name with a replacement character, not to be pasted."""
    import subprocess
    import sys

    folder = tmp_path / os.fsdecode(b"caf\xe9")
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    run = subprocess.run([sys.executable, "-m", "kbbatch", "plan", os.fsencode(folder), "-o",
                          os.fsencode(folder / "m.json"), "--preset", "preview", "--depth",
                          "ramp", "--quiet"], capture_output=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (folder / "m.json").is_file() and (folder / "m-previews" / "a.jpg").is_file()
    assert b"--manifest '" + os.fsencode(folder / "m.json") + b"'" in run.stdout


def test_plan_on_a_folder_without_photos_says_so_and_writes_nothing(tmp_path):
    """It wrote `{"images": {}}` and a render command, and exited 0; the batch says exit 3."""
    from click.testing import CliRunner

    from kbbatch.cli import EXIT_NOTHING_TO_DO, main

    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "IMG_1.HEIC").write_bytes(b"\0\0\0\x18ftypheic")
    result = CliRunner().invoke(main, ["plan", str(tmp_path / "photos"), "-o",
                                       str(tmp_path / "m.json")])
    assert result.exit_code == EXIT_NOTHING_TO_DO, result.output
    assert "no photos here" in result.output and "IMG_1.HEIC" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_an_entrys_easing_applies_to_the_planners_crops_too(tmp_path, quick_preset):
    """An entry with an easing and no crops (the review page sets one on any photo) was
    rendered with the preset's easing, silently."""
    from kbbatch.depth import DepthOptions

    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"easing": "ease-in-out"}}}))
    assert quick_preset.easing == "linear"
    options = ClipOptions(planner="center", threads=2, depth=DepthOptions(backend="ramp"))
    [result] = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                          manifest=load_manifest(manifest)).results
    assert result.status == "done" and result.plan["easing"] == "ease-in-out"


def test_previews_that_cannot_be_written_are_a_note_not_failed_photos(tmp_path, quick_preset):
    """A file holding the previews folder's name: every photo was reported FAILED
    (FileExistsError) and '0 plan(s) written', exit 1, while the manifest held every plan."""
    import subprocess
    import sys

    folder = tmp_path / "in"
    folder.mkdir()
    for seed in range(2):
        Image.fromarray(textured_image(180, 320, seed=seed)).save(folder / f"p{seed}.jpg")
    (tmp_path / "m-previews").write_text("the user's notes")
    run = subprocess.run([sys.executable, "-m", "kbbatch", "plan", str(folder), "-o",
                          str(tmp_path / "m.json"), "--depth", "ramp", "--planner", "center",
                          "--preset", "preview", "--quiet"], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert "2 plan(s) written" in run.stdout and "FAILED" not in run.stderr, run.stderr
    assert "preview not written" in run.stderr and "m-previews" in run.stderr, run.stderr
    assert set(load_manifest(tmp_path / "m.json").entries) == {"p0.jpg", "p1.jpg"}
    assert (tmp_path / "m-previews").read_text() == "the user's notes"


def test_excluding_a_photo_made_earlier_says_its_clip_is_kept(tmp_path, quick_preset):
    """A photo excluded after its clip was made: the clip stayed, without a word, and the
    output folder no longer matched the manifest."""
    from kbbatch.depth import DepthOptions

    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    options = ClipOptions(planner="center", threads=2, depth=DepthOptions(backend="ramp"))
    run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False)
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"exclude": True}}}))
    [result] = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                          manifest=load_manifest(manifest)).results
    assert result.status == "excluded"
    assert result.note and "a.mp4, made earlier, is kept" in result.note
    assert (tmp_path / "out" / "a.mp4").is_file()


def test_plan_refuses_previews_that_would_go_into_the_photo_folder(tmp_path, quick_preset):
    """`plan holiday-previews -o holiday.json`: the previews folder of holiday.json is the
    photo folder, so the contact sheet landed among the photos and the next render made a
    clip of it."""
    folder = tmp_path / "holiday-previews"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    options = ClipOptions(planner="center")
    with pytest.raises(OutputFolderError, match=r"holiday-previews: .* is the photo folder"):
        plan_folder(folder, tmp_path / "holiday.json", quick_preset, options,
                    show_progress=False)
    assert sorted(p.name for p in folder.iterdir()) == ["a.jpg"]
    assert not (tmp_path / "holiday.json").exists()


def test_the_ramp_prior_runs_no_network_to_frame_a_subject(monkeypatch):
    """`--depth ramp` is chosen to run no network: ISNet ran for the framing of every photo the
    preset's shape could not show whole (2.5 minutes more of the test suite, where the models
    are present). Any other depth source asks for it there."""
    from kbbatch import segment
    from kbbatch.depth import DepthResult
    from kbbatch.pipeline import plan_photo

    asked: list = []
    monkeypatch.setattr(segment, "salient_mask", lambda image: asked.append(True))
    request = request_for(1024, 576, "social")
    disparity = np.ones((576, 1024), np.float32)
    for backend, expected in (("ramp", []), ("popup", [True])):
        plan_photo(request.image, DepthResult(disparity, backend, "test"), request.depth,
                   request.preset, "auto")
        assert asked == expected, backend


@pytest.mark.parametrize("depth_file", [False, True])
def test_a_depth_cache_hit_frames_without_running_isnet_again(monkeypatch, tmp_path, depth_file):
    """Rendering a folder with a second preset (social after slideshow) ran ISNet again for
    every photo the new shape frames; its map now comes from the depth cache: the same plan.
    Also where the depth stage ran no ISNet (a depth map beside the photo, no object found):
    the planner's map joins the entry."""
    from kbbatch import segment
    from kbbatch.images import read_image
    from kbbatch.pipeline import plan_photo, working_depth

    from .test_crowds import real_models_or_skip

    real_models_or_skip(monkeypatch)
    [path] = [p for p in shared_photos(1)[0].parent.glob("20_*lantern*")] or [None]
    if path is None:
        pytest.skip("photo 20 (the lantern) not found in ../shared/photos")
    if depth_file:  # a copy of the photo with a user's depth map beside it
        photo_copy = tmp_path / path.name
        shutil.copyfile(path, photo_copy)
        width, height = Image.open(path).size
        ramp = np.linspace(1.0, 2.0, height, dtype=np.float32)[:, None].repeat(width, 1)
        np.save(tmp_path / f"{path.stem}.depth.npy", ramp)
        path = photo_copy
    runs: list = []
    real_salient_mask = segment.salient_mask
    monkeypatch.setattr(segment, "salient_mask",
                        lambda image: runs.append(1) or real_salient_mask(image))
    photo = read_image(path)
    plans = []
    for _ in range(2):
        working, depth_result, depth = working_depth(photo, path, ClipOptions())
        assert depth_result.backend == ("file" if depth_file else "popup")
        plans.append(plan_photo(working, depth_result, depth, load_preset("social"), "auto"))
    assert len(runs) == 1, f"ISNet ran {len(runs)} times"
    assert plans[0] == plans[1]
    assert plans[0].start.center_x_px != pytest.approx(depth.shape[1] / 2)  # it was framed


def test_a_crop_of_huge_numbers_is_said_in_readable_numbers(tmp_path):
    """1e300 as a crop's centre was printed as its 301 digits, four times, in one line."""
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "start": {"center_x": 1e300, "center_y": 500, "width": 1e300},
        "end": {"center_x": 400, "center_y": 500, "width": 300}}}})
    entry = load_manifest(path).entry("a.jpg")
    with pytest.raises(ManifestError) as caught:
        entry.plan(910, 1137, 819, 16 / 9, "linear")
    message = str(caught.value)
    assert "image 'a.jpg': field 'start': crop [" in message and len(message) < 300, message
    assert "e+300" in message and "lies outside the 910x1137 photo" in message


def test_a_rejected_photo_renamed_stays_excluded(tmp_path, quick_preset):
    """Excluded in the manifest (with the bytes `plan` saw), then renamed: the photo was made
    under its new name, the run ended 0, and a note said the excluded one was gone."""
    from kbbatch.depth import DepthOptions

    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320, seed=1)).save(folder / "a.jpg")
    Image.fromarray(textured_image(180, 320, seed=2)).save(folder / "b.png")
    options = ClipOptions(planner="center", depth=DepthOptions(backend="ramp"), threads=2)
    manifest_path = tmp_path / "m.json"
    plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    data = json.loads(manifest_path.read_text())
    data["images"]["b.png"]["exclude"] = True
    manifest_path.write_text(json.dumps(data))
    (folder / "b.png").rename(folder / "b_renamed.png")
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    statuses = {Path(r.source).name: r.status for r in report.results}
    assert statuses == {"a.jpg": "done", "b_renamed.png": "excluded"}, statuses
    assert not report.failed
    assert any("b_renamed.png: has the bytes of 'b.png'" in note for note in report.notes)
    assert not (tmp_path / "out" / "b_renamed.mp4").exists()
