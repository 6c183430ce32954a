"""The extreme views are filled once, with background, and every frame comes out complete."""

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
    nearest_depth,
    output_view,
    overshoot,
    working_view,
)
from kbbatch.inpaint import (
    build_extended_cloud,
    fill_background,
    layered_cloud,
    near_side_of_holes,
    snap_edge_depth,
)
from kbbatch.pipeline import PreparedScene, frame_at
from kbbatch.presets import load_preset, with_overrides
from kbbatch.render import back_project, render

from .conftest import textured_image

W, H = 320, 200
CARD = (slice(60, 140), slice(120, 200))
CARD_COLOUR = (255, 128, 0)
"""An orange that the texture behind the card never comes within 30 levels of (35 at the
nearest): a fill colour that close to it can only have come from the card. (A red card had
856 background pixels within 30 levels of it, in the texture's red stripe.)"""
COPIED_LEVELS = 30


def card_scene():
    image = textured_image(H, W, seed=7)
    image[CARD] = CARD_COLOUR
    disparity = np.full((H, W), 10.0, np.float32)
    disparity[CARD] = 40.0
    depth = depth_from_disparity(disparity, paper.focal_px(W))
    scene = SceneGeometry(W, H, nearest_depth(depth))
    start = Crop(W / 2, H / 2, 0.9 * W, 0.9 * H)
    end = Crop(W / 2 + 25, H / 2, 0.9 * W / 1.25, 0.9 * H / 1.25)
    return image, depth, scene, Plan(start, end)


def end_position(scene, plan):
    return overshoot(camera_position(plan, scene, 0.0), camera_position(plan, scene, 1.0),
                     paper.EXTREME_VIEW_OVERSHOOT)


def end_view_rendering(cloud, scene, plan):
    view = working_view(scene, end_position(scene, plan))
    return render(cloud, view, scene.focal_px * paper.DISPARITY_MAX_PX)


def test_fill_takes_the_far_plane_not_the_card():
    image, depth, scene, plan = card_scene()
    raw = back_project(image, snap_edge_depth(depth), working_view(scene, (0.0, 0.0, 0.0)))
    before = end_view_rendering(raw, scene, plan)
    hole = ~before.covered
    hole[:, : W // 3] = False  # the disocclusion beside the card, not the frame border
    hole[:, 2 * W // 3:] = False
    assert hole.sum() > 200, "the move must reveal unseen background"
    extended = build_extended_cloud(image, depth, plan, scene).cloud
    after = end_view_rendering(extended, scene, plan)
    assert after.covered[hole].all()
    far_depth_in_view = float(depth.max()) - end_position(scene, plan)[2]
    # The card's soft edge (its matte) may cover the first two pixels beside it.
    inner = cv2.erode(hole.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    np.testing.assert_allclose(after.depth[inner], far_depth_in_view, rtol=0.02)
    background = np.ones(image.shape[:2], bool)
    background[CARD] = False
    assert not np.all(np.abs(image[background].astype(int) - CARD_COLOUR) < COPIED_LEVELS,
                      axis=-1).any(), "the premise: no background pixel has the card's colour"
    copied = np.all(np.abs(after.colour[inner] - CARD_COLOUR) < COPIED_LEVELS, axis=-1)
    assert copied.mean() < 0.02, "the fill copied the card's colour"


def test_extension_adds_points_only_where_the_extreme_views_had_holes():
    image, depth, scene, plan = card_scene()
    extension = build_extended_cloud(image, depth, plan, scene)
    # The start view is the photo's own (centred widest crop): the end view and the views
    # inside the move add exactly one point per pixel they found empty, and nothing else.
    assert extension.hole_pixels_start == 0
    assert extension.hole_pixels_end > 0
    assert extension.added_points == sum(extension.hole_pixels_per_view)
    photo_points, _ = layered_cloud(image, depth, working_view(scene, (0.0, 0.0, 0.0)),
                                    np.ones((H, W), bool), scene.focal_px * paper.DISPARITY_MAX_PX)
    assert W * H < len(photo_points) < 1.1 * W * H, "edge pixels are two points, the rest one"
    assert len(extension.cloud) == len(photo_points) + extension.added_points
    assert extension.added_points < 0.1 * W * H
    again = build_extended_cloud(image, depth, plan, scene)
    np.testing.assert_array_equal(extension.cloud.x, again.cloud.x)
    np.testing.assert_array_equal(extension.cloud.colour, again.cloud.colour)


@pytest.mark.parametrize("shift_px", [25, -25])
def test_no_fill_shows_in_the_photos_own_view(shift_px):
    """Fill is what the photo does not show. Where three depths meet (a near cup, a farther
    one, the floor in a narrow gap between them: a photo of rows of cups nobody here tuned
    for), holes in the views inside the move were filled level with the farther cup's rim;
    from the photo's own view those points blended into the rim's soft edge and lay before
    the floor in the gap (190 to 1256 pixels of this scene changed by up to 246 levels), and
    the start frame showed lavender blocks on a white rim, a dark smear between two boats."""
    image = textured_image(H, W, seed=7)
    disparity = np.full((H, W), 10.0, np.float32)
    disparity[40:160, 60:150] = 40.0  # the near cup
    image[40:160, 60:150] = (230, 230, 235)
    disparity[30:170, 162:260] = 25.0  # the farther one, 12 px of floor between them
    image[30:170, 162:260] = (200, 120, 200)
    depth = depth_from_disparity(disparity, paper.focal_px(W))
    scene = SceneGeometry(W, H, nearest_depth(depth))
    plan = Plan(Crop(W / 2, H / 2, 0.9 * W, 0.9 * H),
                Crop(W / 2 + shift_px, H / 2, 0.9 * W / 1.25, 0.9 * H / 1.25))
    extension = build_extended_cloud(image, depth, plan, scene)
    assert extension.added_points > 1000, "the premise: the move reveals unseen background"
    own_view = working_view(scene, (0.0, 0.0, 0.0))
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    photo_points, _ = layered_cloud(image, depth, own_view, np.ones((H, W), bool),
                                    disparity_scale)
    seen = render(photo_points, own_view, disparity_scale).colour
    with_fill = render(extension.cloud, own_view, disparity_scale).colour
    changed = np.abs(with_fill - seen).max(axis=-1)
    assert (changed > 10).sum() == 0, f"fill showed at {np.argwhere(changed > 10)[:5]}"


def test_strong_move_leaves_no_empty_pixel_in_any_frame():
    image, depth, scene, plan = card_scene()
    preset = with_overrides(load_preset("preview"), width_px=320, height_px=200, fps=10.0,
                            duration_s=1.0)
    plan = Plan(plan.start, Crop(W / 2 + 40, H / 2 - 15, plan.end.width_px,
                                 plan.end.height_px))
    cloud = build_extended_cloud(image, depth, plan, scene).cloud
    prepared = PreparedScene(plan, scene, cloud, "test", 1.0 / depth)
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    for t in np.linspace(0, 1, preset.frames_forward):
        view = output_view(plan, scene, t, preset.width_px, preset.height_px)
        raw = render(cloud, view, disparity_scale)
        assert raw.covered.mean() > 0.99, "the extended cloud must cover nearly every pixel"
        frame = frame_at(prepared, preset, float(t))
        assert frame.shape == (200, 320, 3)
        assert (frame.sum(axis=-1) > 0).all(), "an empty (black) pixel reached the output"
        np.testing.assert_array_equal(frame, frame_at(prepared, preset, float(t)))


def test_depth_fill_grows_from_the_background_side_only():
    depth = np.full((20, 40), 100.0, np.float32)
    depth[:, :15] = 10.0  # near object on the left
    hole = np.zeros_like(depth, bool)
    hole[:, 15:25] = True  # a disocclusion between near object and far wall
    blocked = near_side_of_holes(np.where(hole, np.inf, depth), hole)
    assert blocked[:, 14].all() and not blocked[:, 26].any()
    colour = np.zeros((20, 40, 3), np.float32)
    colour[:, :15] = (255, 0, 0)
    colour[:, 25:] = (0, 0, 200)
    filled_colour, filled_depth = fill_background(colour, np.where(hole, 0, depth), hole, blocked)
    np.testing.assert_allclose(filled_depth[hole], 100.0)
    np.testing.assert_allclose(filled_colour[hole], np.broadcast_to((0, 0, 200), (200, 3)))


def tiny_inpainting_model() -> bytes:
    """LaMa convention: out = image * (1 - mask) + mask * (0.2, 0.4, 0.6), in 0..1."""
    from onnx import TensorProto, helper, numpy_helper

    colour = numpy_helper.from_array(np.array([0.2, 0.4, 0.6], np.float32).reshape(1, 3, 1, 1),
                                     "colour")
    one = numpy_helper.from_array(np.array(1.0, np.float32), "one")
    nodes = [
        helper.make_node("Sub", ["one", "mask"], ["keep"]),
        helper.make_node("Mul", ["image", "keep"], ["kept"]),
        helper.make_node("Mul", ["mask", "colour"], ["fill"]),
        helper.make_node("Add", ["kept", "fill"], ["output"]),
    ]
    graph = helper.make_graph(
        nodes, "tiny-inpaint",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 512, 512]),
         helper.make_tensor_value_info("mask", TensorProto.FLOAT, [1, 1, 512, 512])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 3, 512, 512])],
        initializer=[colour, one],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    return model.SerializeToString()


def test_cached_colour_network_fills_the_holes(tmp_path, monkeypatch):
    from kbbatch.inpaint import colour_inpainter

    monkeypatch.setenv("KBBATCH_MODELS", str(tmp_path))
    assert colour_inpainter() is None, "no network cached: the classical fill is used"
    (tmp_path / "lama_fp32.onnx").write_bytes(tiny_inpainting_model())
    inpainter = colour_inpainter()
    assert inpainter is not None
    image, depth, scene, plan = card_scene()
    extended = build_extended_cloud(image, depth, plan, scene, inpainter).cloud
    plain = back_project(image, snap_edge_depth(depth), working_view(scene, (0.0, 0.0, 0.0)))
    before = end_view_rendering(plain, scene, plan)
    after = end_view_rendering(extended, scene, plan)
    hole = ~before.covered
    hole[:, : W // 3] = False
    hole[:, 2 * W // 3:] = False
    inner = hole & (cv2.erode(hole.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
    assert inner.sum() > 50
    np.testing.assert_allclose(after.colour[inner].mean(axis=0), (51, 102, 153), atol=8)


def test_a_cloud_whose_height_rounds_differently_still_builds():
    image, depth, scene, plan = card_scene()
    # 1.93 x 320 = 617.6 -> 618 wide; 200 x 618 / 320 = 386.25, while a photo resized on its
    # own may come out 1 px taller or shorter.
    photo = cv2.resize(image, (618, 387), interpolation=cv2.INTER_LINEAR)
    extension = build_extended_cloud(photo, depth, plan, scene)
    assert len(extension.cloud) >= 618 * 386


def test_fill_of_a_textured_background_is_textured_and_never_blocked_coloured():
    rng = np.random.default_rng(3)
    height, width = 80, 120
    # A background of vertical stripes with grain (a curtain), a red object on the left.
    stripes = 90 + 60 * np.sin(np.arange(width) * 2 * np.pi / 6.0)
    colour = np.repeat(stripes[None, :, None], height, 0).repeat(3, 2)
    colour = (colour + rng.normal(0, 8, colour.shape)).astype(np.float32)
    depth = np.full((height, width), 100.0, np.float32)
    depth[:, :40] = 20.0
    colour[:, :40] = (255, 0, 0)
    hole = np.zeros((height, width), bool)
    hole[10:70, 40:70] = True
    blocked = near_side_of_holes(np.where(hole, np.inf, depth), hole)
    filled_colour, filled_depth = fill_background(colour, np.where(hole, 0, depth), hole, blocked)
    np.testing.assert_allclose(filled_depth[hole], 100.0)
    fill = filled_colour[hole]
    assert (np.abs(fill - (255, 0, 0)).max(axis=-1) > 60).all(), "red came from the blocked side"
    # Texture: the horizontal detail inside the fill is of the background's order, not flat.
    grey = filled_colour.mean(axis=-1)
    detail = np.abs(np.diff(grey, axis=1))
    inside = detail[20:60, 45:65].mean()
    around = detail[20:60, 80:110].mean()
    assert inside > 0.5 * around, f"flat fill: detail {inside:.1f} against {around:.1f} around"
    old_style = np.abs(np.diff(cv2.GaussianBlur(grey, (0, 0), 3.0), axis=1))[20:60, 45:65].mean()
    assert inside > 2 * old_style


def test_a_hole_down_a_post_into_a_field_is_filled_with_field_not_sky():
    """A disocclusion beside a post runs from the horizon down into a field whose ground comes
    nearer towards the bottom. Judged over the whole hole, the near end of the field was taken
    for foreground, and the horizon's depth ran down the hole from pixel to pixel: the field
    beside the post was filled with sky (a real photo)."""
    height, width = 80, 40
    rows = np.arange(height, dtype=np.float32)[:, None]
    depth = np.broadcast_to(4000.0 / (1.0 + rows / 8.0), (height, width)).copy()  # the ground
    depth[:8] = 20000.0  # the sky above the horizon
    colour = np.zeros((height, width, 3), np.float32)
    colour[:] = (190, 150, 110)  # field
    colour[:8] = (200, 220, 245)  # sky
    depth[:, 25:] = 300.0  # the post, nearer than anything
    colour[:, 25:] = (90, 50, 30)
    hole = np.zeros((height, width), bool)
    hole[4:, 15:25] = True
    known = np.where(hole, np.inf, depth)
    blocked = near_side_of_holes(known, hole)
    assert blocked[:, 25].any() and not blocked[20:, 14].any()  # the post, never the field
    filled_colour, filled_depth = fill_background(colour, np.where(hole, 0, depth), hole,
                                                  blocked)
    lower = hole.copy()
    lower[:30] = False
    assert np.abs(filled_colour[lower] - (190, 150, 110)).max() < 10
    field_depth = np.broadcast_to(depth[:, :1], depth.shape)[lower]
    assert np.all(filled_depth[lower] <= 2 * field_depth)  # the ground, never the sky (20000)


def test_a_hole_fenced_in_by_soft_edges_is_filled_from_the_background_around_it():
    """Small holes inside a wide soft edge (blocked: its colour is part object) had no known
    pixel within any patch, so no patch distance ranked their candidates: they took a
    neighbour mean of nothing, mid grey, and showed as grey dashes beside a shoulder. They
    take the background around them, at its depth, not the scene's farthest."""
    height, width = 120, 160
    depth = np.full((height, width), 1000.0, np.float32)  # the wall
    depth[:20] = 50000.0  # a far sky at the top, the scene's farthest
    colour = np.zeros((height, width, 3), np.float32)
    colour[:] = (200, 170, 120)  # the wall's colour
    colour[:20] = (235, 240, 250)
    blocked = np.zeros((height, width), bool)
    blocked[40:100, 60:100] = True  # a soft edge, 40 px wide
    hole = np.zeros_like(blocked)
    hole[60:80, 78:80] = True  # a crack inside it, no known pixel within 18 px
    blocked &= ~hole
    filled_colour, filled_depth = fill_background(colour, np.where(hole, 0, depth), hole,
                                                  blocked)
    assert np.abs(filled_colour[hole] - (200, 170, 120)).max() < 1
    np.testing.assert_allclose(filled_depth[hole], 1000.0)


def test_an_edge_running_into_a_thick_hole_continues_straight():
    """A blue drape beside a gold one, a shoulder below, and the band above the shoulder
    revealed (30 px thick). Filled ring by ring at its own size alone, the inner rings
    followed what the outer rings had copied: the drapes' border drifted sideways into a
    step (3.4 % of the hole on the wrong side; photo 02's window and curtain, 03's drapes).
    Matched coarse to fine, the border runs on straight and the folds stay textured."""
    rng = np.random.default_rng(5)
    height, width = 160, 200
    colour = np.zeros((height, width, 3), np.float32)
    colour[:, :100] = (40, 90, 200)
    colour[:, 100:] = (210, 160, 50)
    colour += 25 * np.sin(np.arange(width) * 2 * np.pi / 9.0)[None, :, None]  # folds
    colour = np.clip(colour + rng.normal(0, 10, colour.shape), 0, 255).astype(np.float32)
    depth = np.full((height, width), 100.0, np.float32)
    rows, cols = np.mgrid[0:height, 0:width]
    shoulder = (rows > 120) | (((cols - 100) / 70.0) ** 2 + ((rows - 150) / 60.0) ** 2 < 1)
    depth[shoulder] = 20.0
    colour[shoulder] = (20, 20, 20)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (61, 61))
    hole = (cv2.dilate(shoulder.astype(np.uint8), disk) > 0) & ~shoulder
    blocked = near_side_of_holes(np.where(hole, np.inf, depth), hole)
    known = np.where(hole[..., None], 0, colour).astype(np.float32)
    filled, filled_depth = fill_background(known, np.where(hole, 0, depth), hole, blocked)
    np.testing.assert_allclose(filled_depth[hole], 100.0)
    blue = filled[..., 2] > filled[..., 0]
    wrong_side = hole & (blue != (cols < 100))
    assert wrong_side.sum() <= 0.005 * hole.sum(), f"{wrong_side.sum()} of {hole.sum()} px"
    assert (np.abs(filled[hole] - (20, 20, 20)).max(axis=-1) > 60).all(), "shoulder copied"
    # the folds go on: the fill's detail across the columns is of the drapes' own order
    detail = np.abs(np.diff(filled.mean(axis=-1), axis=1))
    inner = hole[:, 1:] & hole[:, :-1]
    assert detail[inner].mean() > 0.6 * detail[:60].mean()


def test_fill_points_along_the_visible_regions_edge_have_a_finite_depth(tmp_path):
    """Zooming out over a ground plane (near at the bottom edge), the view's holes along the
    edge of the region frames can show took infinite depth: the region, resized to the
    working size as uint8, rounded the working pixels it only partly covers to 0, the fill
    left them alone, and their points were lost (NumPy warned of NaN on the console)."""
    from kbbatch.depth import DepthOptions
    from kbbatch.pipeline import ClipOptions, prepare_scene

    photo = textured_image(427, 640, seed=3)
    cv2.imwrite(str(tmp_path / "p.png"), photo[..., ::-1])
    rows = np.linspace(0, 1, 427)[:, None]
    ground = np.broadcast_to((60000 - 56000 * rows).astype(np.uint16), (427, 640))
    cv2.imwrite(str(tmp_path / "p.depth.png"), np.ascontiguousarray(ground))
    preset = with_overrides(load_preset("slideshow"), zoom_direction="out")
    scene = prepare_scene(photo, tmp_path / "p.png", preset,
                          ClipOptions(planner="center", depth=DepthOptions(backend="file")), {})
    assert np.isfinite(scene.cloud.z).all()


@pytest.mark.parametrize("relief", [1.0, 0.25])
def test_the_start_view_is_the_photo_where_a_card_meets_the_ground(relief):
    """A card stands at the ground's depth where it touches it, so near its foot the band's
    two layers lie within the renderer's blend of each other: its soft edge blended into the
    ground behind as one surface, and the start frame took blocks 100 levels off the photo
    (grey blocks along a lantern's lower edge, at a quarter of the relief)."""
    from kbbatch.risk import relieved

    rows = np.arange(H, dtype=np.float32)[:, None]
    disparity = np.repeat(12 + 28 * rows / (H - 1), W, axis=1)  # a ground plane
    card = np.zeros((H, W), np.float32)
    cv2.fillConvexPoly(card, np.array([[100, 40], [220, 40], [220, 120], [160, 160],
                                       [100, 160]]), 1.0)
    disparity = np.where(card > 0, 12 + 28 * 160 / (H - 1), disparity).astype(np.float32)
    ground = np.random.default_rng(1).normal(30, 6, (H, W, 1)).repeat(3, axis=2)
    alpha = cv2.GaussianBlur(card, (0, 0), 1.2)[..., None]
    image = np.clip(ground * (1 - alpha) + np.array([225, 222, 210]) * alpha, 0, 255)
    image = image.astype(np.uint8)
    depth = relieved(depth_from_disparity(disparity, paper.focal_px(W)), relief)
    scene = SceneGeometry(W, H, nearest_depth(depth))
    view = working_view(scene, (0.0, 0.0, 0.0))
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    points, _ = layered_cloud(image, depth, view, np.ones((H, W), bool), disparity_scale,
                              relief=relief)
    error = np.abs(render(points, view, disparity_scale).colour - image).max(axis=-1)
    assert (error > 10).sum() <= 2, f"the start view is off at {np.argwhere(error > 10)[:5]}"
