import numpy as np

from kbbatch.camera import SceneGeometry, View, working_view
from kbbatch.render import (
    CRACK_DISPARITY_PX,
    MIN_SPLAT_WEIGHT,
    NEAR_PLANE,
    SOFT_Z_DISPARITY_PX,
    PointCloud,
    back_project,
    depth_edges,
    render,
    render_frame,
    to_uint8,
)

from .conftest import textured_image

H, W = 120, 160
SCENE = SceneGeometry(W, H, 80.0)
DISPARITY_SCALE = SCENE.focal_px * 40
NEAR, FAR = 80.0, 320.0


def card_scene():
    """A near square card (red) in front of a textured far plane."""
    image = textured_image(H, W, seed=3)
    image[40:80, 60:100] = (255, 0, 0)
    depth = np.full((H, W), FAR, np.float32)
    depth[40:80, 60:100] = NEAR
    return image, depth


def shifted_view(shift_x: float, focal_scale: float = 1.0) -> View:
    base = working_view(SCENE, (shift_x, 0.0, 0.0))
    return View(base.position, base.focal_px * focal_scale, base.principal_x_px,
                base.principal_y_px, W, H)


def test_fronto_parallel_plane_renders_back_to_input():
    image = textured_image(H, W)
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    cloud = back_project(image, np.full((H, W), FAR, np.float32), view)
    rendering = render(cloud, view, DISPARITY_SCALE)
    assert rendering.covered.all()
    np.testing.assert_array_equal(to_uint8(rendering.colour), image)
    np.testing.assert_allclose(rendering.depth, FAR, rtol=1e-5)


def test_near_card_occludes_far_plane_after_shift():
    image, depth = card_scene()
    cloud = back_project(image, depth, working_view(SCENE, (0.0, 0.0, 0.0)))
    # Camera moves right by 10 units: the card (depth 80, f 80) shifts left by 10 px, the far
    # plane by 2.5 px.
    rendering = render(cloud, shifted_view(10.0), DISPARITY_SCALE)
    colour = to_uint8(rendering.colour)
    card = colour[45:75, 52:88]
    assert (card == (255, 0, 0)).all(), "the near card must be drawn over the far plane"
    np.testing.assert_allclose(rendering.depth[45:75, 52:88], NEAR, rtol=1e-4)
    # Right of the moved card, the far plane is visible again (or a disocclusion hole).
    right = rendering.depth[45:75, 95:110]
    assert np.all(right[rendering.covered[45:75, 95:110]] > 0.9 * FAR)


def test_zoom_in_leaves_no_cracks_on_a_continuous_surface():
    image = textured_image(H, W, seed=5)
    rows = np.arange(H, dtype=np.float32)[:, None]
    depth = np.repeat(FAR / (1.0 + rows / H), W, axis=1)  # a slanted, continuous ground
    cloud = back_project(image, depth, working_view(SCENE, (0.0, 0.0, 0.0)))
    rendering = render(cloud, shifted_view(0.0, focal_scale=1.25), DISPARITY_SCALE)
    inner = rendering.covered[2:-2, 2:-2]
    assert inner.all(), f"{(~inner).sum()} cracks after a 1.25x zoom"


def test_depth_edge_points_leave_holes_not_sheets():
    image, depth = card_scene()
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    edges = depth_edges(depth)
    assert edges[60, 59] and edges[60, 60] and not edges[60, 30]
    cloud = back_project(image, depth, view, keep=~edges)
    rendering = render(cloud, shifted_view(10.0), DISPARITY_SCALE)
    # The card slid left by 10 px: its old right part shows unseen background, a hole.
    hole = ~rendering.covered[45:75, 88:97]
    assert hole.mean() > 0.5, "disocclusion must be reported by the coverage mask"
    between = rendering.covered & (rendering.depth > 1.2 * NEAR) & (rendering.depth < 0.8 * FAR)
    assert not between.any(), "no point may sit on a rubber sheet between card and plane"
    # The same cloud with edges kept would stretch a sheet: the test can tell the difference.
    sheet = render(back_project(image, depth, view), shifted_view(10.0), DISPARITY_SCALE)
    assert sheet.covered[45:75, 88:97].mean() > rendering.covered[45:75, 88:97].mean()


def test_background_fill_uses_the_far_side_of_a_hole():
    image, depth = card_scene()
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    cloud = back_project(image, depth, view, keep=~depth_edges(depth))
    rendering = render(cloud, shifted_view(10.0), DISPARITY_SCALE)
    filled = render_frame(cloud, shifted_view(10.0), DISPARITY_SCALE)
    np.testing.assert_array_equal(filled[rendering.covered],
                                  to_uint8(rendering.colour)[rendering.covered])
    hole = ~rendering.covered
    assert hole.any()
    red = np.all(filled == (255, 0, 0), axis=-1)
    assert not (red & hole).any(), "foreground colour bled into a disocclusion"


def test_frames_rendered_concurrently_equal_the_serial_frame():
    """The batch renders frames in threads (the kernels release the GIL): no shared buffer may
    let one frame's splats leak into another's."""
    from concurrent.futures import ThreadPoolExecutor

    image, depth = card_scene()
    cloud = back_project(image, depth, working_view(SCENE, (0.0, 0.0, 0.0)))
    shifts = [(7.3, 1.1), (-4.0, 0.9), (2.5, 1.3), (0.0, 1.0)] * 3
    serial = [render(cloud, shifted_view(*s), DISPARITY_SCALE) for s in shifts]
    with ThreadPoolExecutor(max_workers=4) as pool:
        threaded = list(pool.map(lambda s: render(cloud, shifted_view(*s), DISPARITY_SCALE),
                                 shifts))
    for alone, together in zip(serial, threaded, strict=True):
        np.testing.assert_array_equal(alone.colour, together.colour)
        np.testing.assert_array_equal(alone.weight, together.weight)
    assert not np.array_equal(serial[0].colour, serial[1].colour)  # the views differ


def reference_rendering(cloud, view, disparity_scale):
    """The renderer written plainly, point by point in float64, to check the kernel against."""
    height, width = view.height_px, view.width_px
    soft = SOFT_Z_DISPARITY_PX / disparity_scale
    crack = CRACK_DISPARITY_PX / disparity_scale
    front = np.zeros((height, width))
    accumulator = np.zeros((height, width, 4))
    for x, y, z, colour in zip(cloud.x, cloud.y, cloud.z, cloud.colour, strict=True):
        depth = float(z) - view.position[2]
        if depth <= NEAR_PLANE:
            continue
        px = view.focal_px * (float(x) - view.position[0]) / depth + view.principal_x_px - 0.5
        py = view.focal_px * (float(y) - view.position[1]) / depth + view.principal_y_px - 0.5
        if not (-1 < px < width and -1 < py < height):
            continue
        x0, y0 = int(np.floor(px)), int(np.floor(py))
        for dy in (0, 1):
            for dx in (0, 1):
                xx, yy = x0 + dx, y0 + dy
                weight = (px - x0 if dx else 1 - (px - x0)) * (py - y0 if dy else 1 - (py - y0))
                if not (0 <= xx < width and 0 <= yy < height) or weight <= MIN_SPLAT_WEIGHT:
                    continue
                values = weight * np.array([*colour.astype(float), 1.0])
                if front[yy, xx] < 1 / depth - soft:  # clearly nearer: the pixel starts over
                    front[yy, xx] = 1 / depth
                    accumulator[yy, xx] = values
                elif front[yy, xx] <= 1 / depth + soft:  # the same surface: blend
                    front[yy, xx] = max(front[yy, xx], 1 / depth)
                    accumulator[yy, xx] += values
    unfiltered = front.copy()
    for yy in range(1, height - 1):
        for xx in range(1, width - 1):
            threshold = unfiltered[yy, xx] + crack
            pairs = (((0, -1), (0, 1)), ((-1, 0), (1, 0)), ((-1, -1), (1, 1)), ((-1, 1), (1, -1)))
            if any(min(unfiltered[yy + ay, xx + ax], unfiltered[yy + by, xx + bx]) > threshold
                   for (ay, ax), (by, bx) in pairs):
                accumulator[yy, xx] = 0.0
    return accumulator


def test_kernel_matches_a_plain_reference_with_points_behind_and_beside_the_camera():
    rng = np.random.default_rng(11)
    count = 5000  # several projection chunks and a partial last one
    depth = rng.uniform(-20.0, FAR, count).astype(np.float32)  # some behind the camera
    view = shifted_view(3.0, 1.1)
    cols = rng.uniform(-40, W + 40, count)  # some project beside the frame
    rows = rng.uniform(-40, H + 40, count)
    # Points behind the camera sit where a clamped depth would project them into the frame.
    scale = np.maximum(depth - view.position[2], NEAR_PLANE) / view.focal_px
    cloud = PointCloud(
        ((cols - view.principal_x_px) * scale + view.position[0]).astype(np.float32),
        ((rows - view.principal_y_px) * scale + view.position[1]).astype(np.float32),
        depth,
        rng.integers(0, 256, (count, 3), dtype=np.uint8),
    )
    rendering = render(cloud, view, DISPARITY_SCALE)
    expected = reference_rendering(cloud, view, DISPARITY_SCALE)
    np.testing.assert_allclose(rendering.weight, expected[..., 3], atol=1e-4)
    covered = expected[..., 3] > 1e-3
    assert covered.mean() > 0.1
    np.testing.assert_allclose(
        rendering.colour[covered], expected[..., :3][covered] / expected[..., 3:][covered],
        atol=0.05,
    )


def test_points_within_the_soft_range_blend_and_the_pixel_keeps_the_nearest_depth():
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    # Three points on pixel (10, 20), farthest first: two within the soft range, one far behind.
    depth = np.array([FAR, 100.5, 100.0, 100.2], np.float32)
    scale = depth / view.focal_px
    cloud = PointCloud(
        ((20.5 - view.principal_x_px) * scale).astype(np.float32),
        ((10.5 - view.principal_y_px) * scale).astype(np.float32),
        depth,
        np.array([[0, 0, 255], [200, 0, 0], [100, 0, 0], [0, 0, 0]], np.uint8),
    )
    rendering = render(cloud, view, DISPARITY_SCALE)
    assert 1 / 100.0 - 1 / 100.5 < SOFT_Z_DISPARITY_PX / DISPARITY_SCALE < 1 / 100.0 - 1 / FAR
    np.testing.assert_allclose(rendering.weight[10, 20], 3.0, rtol=1e-5)
    np.testing.assert_allclose(rendering.colour[10, 20], [100.0, 0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(rendering.depth[10, 20], 100.0, rtol=1e-5)


def test_cracks_in_a_magnified_ground_are_closed_from_the_ground_itself():
    """Seen closer, a slanted ground spreads its rows apart and the frame has one-pixel cracks
    across it. The finishing fill once took the farthest covered pixel along each crack's
    row, which was the sky beside the ground: thin light lines across a launch pad (a real
    photo). A crack is closed from the pixels above and below it."""
    rows = np.arange(H, dtype=np.float32)[:, None]
    disparity = np.broadcast_to(2.0 + 38.0 * rows / (H - 1), (H, W)).copy()  # near at the bottom
    image = np.full((H, W, 3), 60, np.uint8)  # the ground: dark
    disparity[:, :30] = 1.0  # a strip of far sky down the left side, bright
    image[:, :30] = 250
    depth = (SCENE.focal_px * 40 / disparity).astype(np.float32)
    cloud = back_project(image, depth, working_view(SCENE, (0.0, 0.0, 0.0)))
    closer = working_view(SCENE, (0.0, 0.0, 0.6 * float(depth.min())))
    ground = (slice(H // 2, H), slice(60, W))
    assert not render(cloud, closer, DISPARITY_SCALE).covered[ground].all(), "no crack to close"
    frame = render_frame(cloud, closer, DISPARITY_SCALE)
    assert frame[ground].max() < 120, "sky fetched into a crack of the ground"


def faint_veil_over_a_wall_with_gaps() -> tuple[PointCloud, View]:
    """A grey wall with pinholes (as a magnified surface has between its points) and a faint
    red veil (soft points of alpha 0.2) in front of it, seen head-on: each point lands on one
    pixel, so the veil's points land in the wall's gaps too."""
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    gaps = np.zeros((H, W), bool)
    gaps[3::5, 2::7] = True
    wall = back_project(np.full((H, W, 3), 200, np.uint8), np.full((H, W), FAR, np.float32),
                        view, keep=~gaps)
    veil = back_project(np.full((H, W, 3), (255, 0, 0), np.uint8),
                        np.full((H, W), 0.5 * FAR, np.float32), view,
                        alpha=np.full((H, W), 51, np.uint8))
    return wall.extended(veil), view


def test_a_faint_soft_point_in_a_gap_of_the_surface_behind_shows_faintly():
    """The giraffe's neck left short brown dashes on the sky at 1080p: a soft-edge point of
    the neck that landed where no point of the magnified sky did kept its own, full colour.
    Such a pixel is filled from the surface around it and the soft point composited over."""
    cloud, view = faint_veil_over_a_wall_with_gaps()
    wall = np.s_[:cloud.opaque_count]
    plain = render(PointCloud(cloud.x[wall], cloud.y[wall], cloud.z[wall], cloud.colour[wall]),
                   view, DISPARITY_SCALE)
    assert (~plain.covered).sum() > 100, "the wall must have gaps for this test"
    frame = render_frame(cloud, view, DISPARITY_SCALE).astype(int)
    # Over the wall, the veil makes red 0.2 x 255 + 0.8 x 200 = 211 and green 0.8 x 200 = 160.
    assert frame[..., 1].min() >= 158, "a gap shows the veil's own colour, not the wall's"
    assert np.abs(frame[..., 0] - 211).max() <= 2 and frame[..., 1].max() <= 162


def soft_rim_on_a_card() -> tuple[PointCloud, PointCloud, PointCloud, View]:
    """A red card with a soft rim (alpha 0.5) down its right side, before a grey wall whose
    points behind the card are not in the cloud (as behind a layer's opaque inside), seen
    zoomed out so that the rim's splats share pixels with the card's. Returns the cloud, the
    card, the rim and the view."""
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    inside = np.zeros((H, W), bool)
    inside[40:80, 60:100] = True
    rim = np.zeros((H, W), bool)
    rim[40:80, 100] = True
    red = np.full((H, W, 3), (255, 0, 0), np.uint8)
    near = np.full((H, W), NEAR, np.float32)
    wall = back_project(np.full((H, W, 3), 200, np.uint8), np.full((H, W), FAR, np.float32),
                        view, keep=~inside)
    card = back_project(red, near, view, keep=inside)
    edge = back_project(red, near, view, keep=rim, alpha=np.full((H, W), 128, np.uint8))
    return wall.extended(card).extended(edge), card, edge, shifted_view(0.0, 0.8)


def test_a_soft_edge_blended_into_its_objects_opaque_inside_keeps_the_objects_colour():
    """On the inner side of a soft edge the object's opaque points and its soft ones share
    pixels, with nothing behind (the object hides it). What such a pixel lacks of full alpha
    is the splats' blur; composited over the fill it showed the background through the
    object's rim (a paler inner edge on a synthetic cut-out)."""
    cloud, card, rim, view = soft_rim_on_a_card()
    frame = render_frame(cloud, view, DISPARITY_SCALE).astype(int)
    blended = (render(card, view, DISPARITY_SCALE).covered
               & (render(rim, view, DISPARITY_SCALE).weight > 0))
    assert blended.sum() >= 20, "the rim must share pixels with the card's inside"
    assert (frame[blended] == (255, 0, 0)).all(), "the object's rim took background colour"


def test_frames_of_several_sizes_in_one_thread_equal_frames_rendered_alone():
    """A clip's frames may be rendered at several sizes (kbbatch.pipeline.render_view); the
    per-thread buffers are reused across them and must carry nothing from one frame into the
    next."""
    from concurrent.futures import ThreadPoolExecutor

    cloud, _, _, view = soft_rim_on_a_card()
    veil, _ = faint_veil_over_a_wall_with_gaps()
    small = View(view.position, view.focal_px * 0.75, view.principal_x_px * 0.75,
                 view.principal_y_px * 0.75, 120, 90)
    jobs = [(cloud, view), (veil, small), (cloud, small), (veil, view), (cloud, view)]

    def alone(job):
        with ThreadPoolExecutor(max_workers=1) as fresh:  # a thread of its own: new buffers
            return fresh.submit(render_frame, job[0], job[1], DISPARITY_SCALE).result()

    in_turn = [render_frame(scene, seen, DISPARITY_SCALE) for scene, seen in jobs]
    for job, frame in zip(jobs, in_turn, strict=True):
        np.testing.assert_array_equal(frame, alone(job))
