import cv2
import numpy as np
import pytest

from kbbatch import paper
from kbbatch.camera import (
    Crop,
    Plan,
    SceneGeometry,
    camera_position,
    depth_from_disparity,
    ease,
    fit_crop,
    nearest_depth,
    output_view,
    project,
    unproject,
    working_view,
    zoomed,
)
from kbbatch.inpaint import build_extended_cloud
from kbbatch.render import back_project, depth_edges, render, to_uint8

from .conftest import textured_image

W, H = 1024, 640
SCENE = SceneGeometry(W, H, nearest_depth=512.0)


def nearest_point(u: float, v: float):
    return unproject(SCENE, np.array([u]), np.array([v]), np.array([SCENE.nearest_depth]))


def test_depth_normalisation_puts_nearest_point_at_f():
    disparity = np.linspace(0.1, 3.0, 64, dtype=np.float32).reshape(8, 8)
    depth = depth_from_disparity(disparity, paper.focal_px(1024))
    assert depth.min() == pytest.approx(512.0)
    assert depth.max() == pytest.approx(512.0 * 3.0 / 0.1, rel=1e-5)


def test_nearest_surface_moves_by_the_crop_centre_offset():
    start = fit_crop(W, H, 16 / 9, paper.START_CROP_FRACTION)
    end = Crop(start.center_x_px + 37.0, start.center_y_px - 21.0, start.width_px,
               start.height_px)
    plan = Plan(start, end)
    point = nearest_point(600.0, 300.0)
    out_w, out_h = 1920, 1080
    u0, v0 = project(output_view(plan, SCENE, 0.0, out_w, out_h), *point)
    u1, v1 = project(output_view(plan, SCENE, 1.0, out_w, out_h), *point)
    to_working = start.width_px / out_w
    assert (u1 - u0)[0] * to_working == pytest.approx(-37.0, abs=1e-6)
    assert (v1 - v0)[0] * to_working == pytest.approx(21.0, abs=1e-6)


def test_far_surfaces_move_less_than_the_nearest_one():
    start = fit_crop(W, H, 16 / 9, 0.97)
    plan = Plan(start, Crop(start.center_x_px + 50, start.center_y_px, start.width_px,
                            start.height_px))
    far = unproject(SCENE, np.array([600.0]), np.array([300.0]), np.array([4 * 512.0]))
    u0, _ = project(output_view(plan, SCENE, 0.0, W, H), *far)
    u1, _ = project(output_view(plan, SCENE, 1.0, W, H), *far)
    moved_working = abs((u1 - u0)[0]) * start.width_px / W
    assert 0 < moved_working < 50 / 2


def test_zoom_magnifies_nearest_plane_by_crop_width_ratio():
    start = fit_crop(W, H, 16 / 9, 0.97)
    end = zoomed(start, 1.25, (start.center_x_px - 30, start.center_y_px + 10))
    plan = Plan(start, end)
    a, b = nearest_point(400.0, 300.0), nearest_point(700.0, 380.0)
    spans = []
    for t in (0.0, 1.0):
        view = output_view(plan, SCENE, t, 1280, 720)
        (ua, va), (ub, vb) = project(view, *a), project(view, *b)
        spans.append(np.hypot(ub - ua, vb - va)[0])
    assert spans[1] / spans[0] == pytest.approx(start.width_px / end.width_px, rel=1e-9)


def test_nearest_plane_follows_the_2d_crop_exactly():
    start = fit_crop(W, H, 4 / 3, 0.9)
    end = zoomed(start, 1.4, (start.center_x_px + 40, start.center_y_px - 25))
    plan = Plan(start, end, easing="ease-in-out")
    out_w, out_h = 800, 600
    u_src, v_src = np.array([300.0, 512.0, 800.0]), np.array([200.0, 320.0, 500.0])
    points = unproject(SCENE, u_src, v_src, np.full(3, SCENE.nearest_depth))
    for t in (0.0, 0.3, 1.0):
        s = ease(t, "ease-in-out")
        cx = start.center_x_px + s * (end.center_x_px - start.center_x_px)
        width = start.width_px + s * (end.width_px - start.width_px)
        u, _ = project(output_view(plan, SCENE, t, out_w, out_h), *points)
        np.testing.assert_allclose(u, (u_src - cx) * out_w / width + out_w / 2, atol=1e-6)


def test_t0_with_the_full_crop_reproduces_the_input():
    image = textured_image(H, W)
    disparity = np.full((H, W), 8.0, np.float32)
    disparity[200:420, 300:600] = 30.0  # a near card: depth edges get removed and restored
    depth = depth_from_disparity(disparity, paper.focal_px(W))
    scene = SceneGeometry(W, H, nearest_depth(depth))
    full = Crop(W / 2, H / 2, W, H)
    plan = Plan(full, zoomed(full, 1.25))
    cloud = build_extended_cloud(image, depth, plan, scene).cloud
    frame = render(cloud, output_view(plan, scene, 0.0, W, H), scene.focal_px * 40)
    assert frame.covered.all()
    error = np.abs(to_uint8(frame.colour).astype(int) - image).max(axis=-1)
    # Away from depth edges the photo comes back exactly. Pixels at an edge are two layers
    # (object over background) composited; where the object's un-mixed colour would leave
    # the 8-bit range it is clipped, so such a pixel may differ a little. This card is the
    # hardest case for that: one texture continues across the depth step, so what the layers
    # read as the object's faint tail beside the edge, or as the background's texture, is
    # neither, and what neither layer takes is dropped. Measured: 0.18 % of pixels off by more
    # than 2 levels before this session's edge allowance (kbbatch.layers.EDGE_SLACK) and the
    # texture discount of the matte, 0.77 % now, all within 7 px of the edge, at most 57 levels
    # (a faint seam along the card's outline; on the start frame of photo 03, where the
    # objects' colours differ from what is behind them, none shows).
    edge_band = cv2.dilate(depth_edges(depth).astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    assert error[~edge_band].max() == 0
    assert error.max() <= 64 and (error > 2).mean() < 0.01


def test_plain_cloud_at_the_photo_view_is_the_photo():
    image = textured_image(60, 80)
    scene = SceneGeometry(80, 60, 40.0)
    view = working_view(scene, (0.0, 0.0, 0.0))
    cloud = back_project(image, np.full((60, 80), 40.0, np.float32), view)
    np.testing.assert_array_equal(to_uint8(render(cloud, view, 40 * 40).colour), image)


def test_easing_ends_and_symmetry():
    for easing in ("linear", "ease-in-out"):
        assert ease(0.0, easing) == 0.0 and ease(1.0, easing) == 1.0
        assert ease(0.5, easing) == pytest.approx(0.5)
    assert ease(0.1, "ease-in-out") < 0.1
    with pytest.raises(ValueError, match="unknown easing"):
        ease(0.5, "bounce")  # type: ignore[arg-type]


def test_fit_crop_keeps_aspect_inside_image():
    for aspect in (16 / 9, 9 / 16, 1.0):
        crop = fit_crop(W, H, aspect, 0.97)
        assert crop.width_px / crop.height_px == pytest.approx(aspect)
        assert crop.inside(W, H)
        assert max(crop.width_px / W, crop.height_px / H) == pytest.approx(0.97)


def test_off_centre_framing_is_a_lens_shift_not_a_camera_move():
    start = Crop(330.0, 250.0, 560.0, 350.0)  # the widest crop, well off the image centre
    end = zoomed(start, 1.25, (start.center_x_px + 30, start.center_y_px + 12))
    plan = Plan(start, end)
    assert camera_position(plan, SCENE, 0.0) == (0.0, 0.0, 0.0), "t=0 is the photo, framed"
    far = unproject(SCENE, np.array([start.center_x_px]), np.array([start.center_y_px]),
                    np.array([1e9]))
    for t in (0.0, 0.5, 1.0):
        u, v = project(output_view(plan, SCENE, t, 1120, 700), *far)
        assert (u[0], v[0]) == (pytest.approx(560.0, abs=1e-3), pytest.approx(350.0, abs=1e-3))
    u_src, v_src = np.array([250.0, 400.0]), np.array([200.0, 300.0])
    points = unproject(SCENE, u_src, v_src, np.full(2, SCENE.nearest_depth))
    u, v = project(output_view(plan, SCENE, 1.0, 1120, 700), *points)
    np.testing.assert_allclose(u, (u_src - end.center_x_px) * 1120 / end.width_px + 560,
                               atol=1e-6)
