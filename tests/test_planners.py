"""Planners: valid crops for every aspect, auto beats center on disocclusion, manifests."""

import json
import shutil

import numpy as np
import pytest

from kbbatch import paper
from kbbatch.batch import ClipOptions, plan_folder, run_folder
from kbbatch.camera import Crop, depth_from_disparity
from kbbatch.manifest import ManifestError, load_manifest
from kbbatch.planners import PlanRequest, get_planner
from kbbatch.planners.auto import plan_disocclusion
from kbbatch.presets import load_preset, with_overrides

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


def test_search_is_deterministic():
    request = request_for(1024, 576, "slideshow", disparity=card_scene())
    plans = [get_planner("auto").plan(request) for _ in range(3)]
    assert plans[0] == plans[1] == plans[2]


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
])
def test_schema_errors_name_the_manifest_image_and_field(tmp_path, data, message):
    path = write(tmp_path / "m.json", data)
    with pytest.raises(ManifestError, match="m.json") as caught:
        load_manifest(path)
    assert message in str(caught.value)


def test_crop_outside_the_photo_is_refused(tmp_path):
    path = write(tmp_path / "m.json", {"images": {"a.jpg": {
        "units": "px", "start": {"center_x": 100, "center_y": 100, "width": 400},
        "end": {"center_x": 500, "center_y": 300, "width": 320}}}})
    entry = load_manifest(path).entry("a.jpg")
    with pytest.raises(ManifestError, match=r"image 'a.jpg': field 'start': crop .* outside"):
        entry.plan(1000, 600, 1024, 16 / 9, "linear")


def test_manifest_round_trip_renders_those_exact_crops(tmp_path, quick_preset):
    folder = tmp_path / "photos"
    folder.mkdir()
    [photo] = shared_photos(1)
    shutil.copy(photo, folder / photo.name)
    manifest_path = tmp_path / "plan" / "manifest.json"
    options = ClipOptions(planner="auto", threads=2)
    [planned] = plan_folder(folder, manifest_path, quick_preset, options, show_progress=False)
    assert planned.status == "done"
    assert (tmp_path / "plan" / "manifest-contact.jpg").is_file()
    assert (tmp_path / "plan" / "manifest-previews" / f"{photo.stem}.jpg").is_file()
    # A person edits the end crop, then renders with the manifest.
    data = json.loads(manifest_path.read_text())
    entry = data["images"][photo.name]
    entry["end"]["center_x"] = round(entry["end"]["center_x"] + 7.5, 2)
    data["images"]["missing.jpg"] = {"duration_s": 1.0}
    manifest_path.write_text(json.dumps(data))
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False,
                        manifest=load_manifest(manifest_path))
    done = [r for r in report.results if r.status == "done"]
    [missing] = report.failed
    assert "missing.jpg" in missing.error and "no such photo" in missing.error
    [result] = done
    assert result.plan["planner"] == "manifest"
    from kbbatch.images import read_image

    source = read_image(photo)
    to_working = 1024 / max(source.shape[:2])
    for field in ("start", "end"):
        crop = entry[field]
        expected = Crop(crop["center_x"], crop["center_y"], crop["width"], crop["height"])
        expected = expected.scaled(to_working)
        got = result.plan[field]
        assert got["center_x_px"] == pytest.approx(expected.center_x_px, abs=1e-6)
        assert got["width_px"] == pytest.approx(expected.width_px, abs=1e-6)
