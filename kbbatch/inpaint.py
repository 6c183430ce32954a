"""Fill disocclusions once, at the extreme views, and extend the point cloud (paper section 3.2).

Every frame is then rendered from the extended cloud, so the fill never flickers. The fill is
background by construction: depth grows in from the far side of each hole border, and colour
is inpainted from background pixels only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from kbbatch import paper
from kbbatch.camera import (
    Plan,
    SceneGeometry,
    View,
    camera_position,
    overshoot,
    widest_crop,
    working_view,
)
from kbbatch.layers import split_layers
from kbbatch.render import PointCloud, back_project, depth_edges, render

FOREGROUND_MARGIN = 0.05
"""A pixel beside a hole is foreground when it is this much (relatively) nearer than the
farthest surface around it; foreground pixels are never used as colour sources."""

INTERMEDIATE_TIMES = (0.5, 0.25, 0.75)
"""Times inside the move that are filled too, after the extreme views (once per clip)."""

SOURCE_MARGIN_FRACTION = 0.05
"""Photo points this far (fraction of the long side) outside every crop are still kept."""

EDGE_SNAP_RADIUS_PX = 2
"""Depth-edge pixels snap to the nearest or farthest depth within this radius (working px)."""

SOURCE_BAND_PX = 7
"""How far around a hole colour sources are screened for foreground, at the working size."""

FILL_SMOOTHING_SIGMA_PX = 1.5
"""The grown fill is softened by a Gaussian of this size, inside the holes only."""

ColourInpainter = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(RGB uint8 image, uint8 mask of pixels to fill) -> RGB uint8 image; e.g. an ONNX network.
It receives the background fill as a starting point, so it refines texture, not geometry."""


@dataclass(frozen=True)
class Extension:
    """What the extension added, for the benchmark and the tests."""

    cloud: PointCloud
    added_points: int
    hole_pixels_start: int
    """Pixels disoccluded at the start view (0 when it is the photo's own view)."""
    hole_pixels_end: int
    """Pixels disoccluded at the overshot end view before the fill."""
    hole_pixels_per_view: tuple[int, ...]
    """Pixels filled at each view, in the order filled (start, end, then inside the move)."""


def near_side_of_holes(depth: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """Known pixels beside a hole that belong to the nearer surface at its border.

    Each hole is judged on its own: pixels in its border band whose disparity lies above the
    midpoint of the band's disparity range are foreground, the rest are background sources.
    """
    count, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    band_kernel = cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * SOURCE_BAND_PX + 1, 2 * SOURCE_BAND_PX + 1)
    )
    band_labels = cv2.dilate(labels.astype(np.float32), band_kernel).astype(np.int64)
    band = (band_labels > 0) & ~hole & np.isfinite(depth) & (depth > 0)
    label_of = band_labels[band]
    disparity = 1.0 / depth[band]
    lowest = np.full(count, np.inf)
    highest = np.zeros(count)
    np.minimum.at(lowest, label_of, disparity)
    np.maximum.at(highest, label_of, disparity)
    midpoint = 0.5 * (lowest + highest)
    near = np.zeros_like(hole)
    near[band] = disparity > midpoint[label_of] * (1.0 + FOREGROUND_MARGIN)
    return near


def fill_background(
    colour: np.ndarray, depth: np.ndarray, hole: np.ndarray, blocked: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fill holes jointly in colour and depth, growing inward from background sources only.

    Each ring of hole pixels takes the mean colour and the farthest depth of its already
    known neighbours; blocked pixels (the near side of a hole border) are never sources, so
    the fill continues the surface behind the hole, never the object beside it.
    """
    filled_colour = colour.astype(np.float32).copy()
    filled_depth = depth.astype(np.float32).copy()
    known = ~hole & ~blocked
    rows, cols = np.nonzero(hole)
    _grow_fill(filled_colour, filled_depth, known, rows.astype(np.int32), cols.astype(np.int32))
    return filled_colour, filled_depth


@numba.njit(cache=True, nogil=True)
def _grow_fill(colour, depth, known, rows, cols):
    # Ring by ring from a frontier (hole pixels touching known ones), so each hole pixel is
    # visited a bounded number of times, however wide the hole.
    height, width = known.shape
    total = rows.shape[0]
    in_hole = np.zeros((height, width), np.bool_)
    queued = np.zeros((height, width), np.bool_)
    frontier_y = np.empty(total, np.int64)
    frontier_x = np.empty(total, np.int64)
    next_y = np.empty(total, np.int64)
    next_x = np.empty(total, np.int64)
    values = np.empty((total, 4), np.float32)
    for k in range(total):
        in_hole[rows[k], cols[k]] = True
    size = 0
    for k in range(total):
        y, x = rows[k], cols[k]
        touches = False
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if 0 <= yy < height and 0 <= xx < width and known[yy, xx]:
                    touches = True
        if touches:
            queued[y, x] = True
            frontier_y[size] = y
            frontier_x[size] = x
            size += 1
    while size > 0:
        for k in range(size):
            y, x = frontier_y[k], frontier_x[k]
            count = 0
            red = green = blue = far = np.float32(0.0)
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < height and 0 <= xx < width and known[yy, xx]:
                        count += 1
                        red += colour[yy, xx, 0]
                        green += colour[yy, xx, 1]
                        blue += colour[yy, xx, 2]
                        far = max(far, depth[yy, xx])
            values[k, 0] = red / count
            values[k, 1] = green / count
            values[k, 2] = blue / count
            values[k, 3] = far
        for k in range(size):
            y, x = frontier_y[k], frontier_x[k]
            for c in range(3):
                colour[y, x, c] = values[k, c]
            depth[y, x] = values[k, 3]
            known[y, x] = True
        following = 0
        for k in range(size):
            y, x = frontier_y[k], frontier_x[k]
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy, xx = y + dy, x + dx
                    if (0 <= yy < height and 0 <= xx < width and in_hole[yy, xx]
                            and not queued[yy, xx]):
                        queued[yy, xx] = True
                        next_y[following] = yy
                        next_x[following] = xx
                        following += 1
        frontier_y, next_y = next_y, frontier_y
        frontier_x, next_x = next_x, frontier_x
        size = following
    # A hole fenced in by foreground alone: take the farthest depth seen and mid grey.
    farthest = np.float32(0.0)
    for y in range(height):
        for x in range(width):
            if known[y, x] and depth[y, x] > farthest and depth[y, x] < np.inf:
                farthest = depth[y, x]
    for k in range(total):
        y, x = rows[k], cols[k]
        if not known[y, x]:
            depth[y, x] = farthest
            for c in range(3):
                colour[y, x, c] = 127.5


def smooth_fill(colour: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """Soften the ring-growth streaks inside holes only (the border colours stay put)."""
    blurred = cv2.GaussianBlur(colour, (0, 0), FILL_SMOOTHING_SIGMA_PX)
    return np.where(hole[..., None], blurred, colour)


def extend_at_view(
    cloud: PointCloud,
    view: View,
    disparity_scale: float,
    region: np.ndarray,
    working_scale: float,
    inpainter: ColourInpainter | None = None,
) -> tuple[PointCloud, int]:
    """Render a view, fill its holes inside region, and return the filled pixels as points.

    The fill is computed at the working size (working_scale = working / view size) and applied
    at the view's own density, so added points are as dense as the photo's.
    """
    rendering = render(cloud, view, disparity_scale)
    hole = ~rendering.covered & region
    hole_count = int(hole.sum())
    if hole_count == 0:
        return PointCloud(*(np.empty(0, np.float32) for _ in range(3)),
                          np.empty((0, 3), np.uint8)), 0
    height, width = hole.shape
    small_size = (max(1, round(width * working_scale)), max(1, round(height * working_scale)))
    # A working-size pixel is a hole if any of its view pixels is, so that no source colour
    # or depth is averaged with empty pixels.
    uncovered = (~rendering.covered).astype(np.float32)
    small_hole = cv2.resize(uncovered, small_size, interpolation=cv2.INTER_AREA) > 0
    small_depth = cv2.resize(rendering.depth, small_size, interpolation=cv2.INTER_NEAREST)
    small_colour = cv2.resize(rendering.colour, small_size, interpolation=cv2.INTER_AREA)
    blocked = near_side_of_holes(small_depth, small_hole)
    if rendering.fringe is not None:  # a soft edge's colour is part object: never a source
        blocked |= cv2.resize(rendering.fringe.astype(np.float32), small_size,
                              interpolation=cv2.INTER_AREA) > 0
        blocked &= ~small_hole
    small_colour, small_depth = fill_background(small_colour, small_depth, small_hole, blocked)
    small_colour = smooth_fill(small_colour, small_hole)
    if inpainter is not None:
        image = np.clip(small_colour + 0.5, 0, 255).astype(np.uint8)
        mask = (small_hole | blocked).astype(np.uint8) * 255
        small_colour = inpainter(image, mask).astype(np.float32)
    depth_full = cv2.resize(small_depth, (width, height), interpolation=cv2.INTER_NEAREST)
    colour_full = cv2.resize(small_colour, (width, height), interpolation=cv2.INTER_LINEAR)
    colour_full = np.clip(colour_full + 0.5, 0, 255).astype(np.uint8)
    return back_project(colour_full, depth_full, view, keep=hole), hole_count


def visible_region(scene: SceneGeometry, plan: Plan, scale: float) -> np.ndarray:
    """Pixels of a full working view (times scale) that some output frame can show: the
    widest crop's window, where the output frames are cut from."""
    width = round(scene.width_px * scale)
    height = round(scene.height_px * scale)
    widest = widest_crop(plan)
    margin = 2.0
    region = np.zeros((height, width), bool)
    left = max(0, int(np.floor((widest.left_px - margin) * scale)))
    top = max(0, int(np.floor((widest.top_px - margin) * scale)))
    right = min(width, int(np.ceil((widest.right_px + margin) * scale)))
    bottom = min(height, int(np.ceil((widest.bottom_px + margin) * scale)))
    region[top:bottom, left:right] = True
    return region


def source_window(scene: SceneGeometry, plan: Plan, scale: float) -> np.ndarray:
    """Photo pixels (at working size times scale) that some frame may show.

    The nearest surface follows the crops and the farthest stays within the widest crop, so
    the union of the two crops bounds what is seen; the margin covers surfaces nearer than
    the anchor depth (which move a little more than the crop).
    """
    windows = [plan.start, plan.end]
    margin = SOURCE_MARGIN_FRACTION * max(scene.width_px, scene.height_px)
    left = max(0, int((min(c.left_px for c in windows) - margin) * scale))
    top = max(0, int((min(c.top_px for c in windows) - margin) * scale))
    right = int(np.ceil((max(c.right_px for c in windows) + margin) * scale))
    bottom = int(np.ceil((max(c.bottom_px for c in windows) + margin) * scale))
    height, width = round(scene.height_px * scale), round(scene.width_px * scale)
    window = np.zeros((height, width), bool)
    window[top:bottom, left:right] = True
    return window


def snap_edge_depth(depth: np.ndarray) -> np.ndarray:
    """Depth with every depth-edge pixel moved to the nearer or farther side of its edge.

    Points are splatted independently, so a rubber sheet only comes from in-between depths
    on a blurred edge; snapping each edge pixel to the side it is closest to (in disparity)
    removes the sheet while keeping every pixel of the photo, rim colours included.
    """
    edges = depth_edges(depth)
    window = np.ones((2 * EDGE_SNAP_RADIUS_PX + 1,) * 2, np.uint8)
    nearest = cv2.erode(depth, window)
    farthest = cv2.dilate(depth, window)
    to_near = np.abs(1 / depth - 1 / nearest) <= np.abs(1 / depth - 1 / farthest)
    snapped = np.where(to_near, nearest, farthest)
    return np.where(edges, snapped, depth).astype(np.float32)


def layered_cloud(photo: np.ndarray, depth: np.ndarray, view: View, keep: np.ndarray
                  ) -> PointCloud:
    """The photo as soft layers (kbbatch.layers): one opaque point per pixel away from depth
    edges; within their band a far opaque point with the background's colour and a near point
    with the object's colour and its alpha matte."""
    layers = split_layers(photo, depth)
    alpha = np.clip(layers.alpha * 255 + 0.5, 1, 255).astype(np.uint8)
    whole_depth = np.where(layers.alpha >= 0.5, layers.near_depth, layers.far_depth)
    return (
        back_project(photo, layers.depth, view, keep=keep & ~layers.band)
        .extended(back_project(photo, whole_depth, view, keep=keep & layers.unsplit))
        .extended(back_project(layers.background, layers.far_depth, view,
                               keep=keep & layers.far))
        .extended(back_project(layers.foreground, layers.near_depth, view,
                               keep=keep & layers.near, alpha=alpha))
    )


def build_extended_cloud(
    photo: np.ndarray,
    depth: np.ndarray,
    plan: Plan,
    scene: SceneGeometry,
    inpainter: ColourInpainter | None = None,
) -> Extension:
    """The photo as a point cloud in soft layers, extended at the extreme views.

    photo is RGB at the cloud density (any size of the working aspect); depth is at the
    working size. At the start view (when it is not the photo's own) and at the overshot end
    view, the disocclusions are filled with background and appended to the cloud.
    """
    cloud_scale = photo.shape[1] / scene.width_px
    cloud_height = round(scene.height_px * cloud_scale)
    if photo.shape[0] != cloud_height:  # a rounding apart: conform, views are sized this way
        photo = cv2.resize(photo, (photo.shape[1], cloud_height), interpolation=cv2.INTER_LINEAR)
    photo_view = working_view(scene, (0.0, 0.0, 0.0), cloud_scale)
    cloud = layered_cloud(photo, depth, photo_view, source_window(scene, plan, cloud_scale))
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    region = visible_region(scene, plan, cloud_scale)
    start_position = camera_position(plan, scene, 0.0)
    end_position = overshoot(
        start_position, camera_position(plan, scene, 1.0), paper.EXTREME_VIEW_OVERSHOOT
    )
    # The end view first (it reveals the most), then views inside the move: a lateral move
    # can reveal background mid-way that the dolly covers again by the end.
    positions = [end_position] + [camera_position(plan, scene, t) for t in INTERMEDIATE_TIMES]
    if start_position != (0.0, 0.0, 0.0):
        positions.insert(0, start_position)
    added = 0
    holes = []
    for position in positions:
        view = working_view(scene, position, cloud_scale)
        points, hole_count = extend_at_view(
            cloud, view, disparity_scale, region, 1.0 / cloud_scale, inpainter=inpainter
        )
        holes.append(hole_count)
        added += len(points)
        cloud = cloud.extended(points)
    end_index = 1 if start_position != (0.0, 0.0, 0.0) else 0
    return Extension(cloud, added, sum(holes[:end_index]), holes[end_index], tuple(holes))


class OnnxInpainter:
    """A colour inpainting network with the LaMa / MI-GAN convention (image + mask in, image out).

    Inputs by position: RGB image (1, 3, S, S) in 0..1 and mask (1, 1, S, S), 1 where to fill;
    the output is RGB in 0..1 or 0..255. It sees our background fill as its starting point,
    with the foreground rim beside each hole masked too, so it refines texture, not geometry.
    """

    def __init__(self, model: str = "lama") -> None:
        from kbbatch import models

        self.spec = models.REGISTRY[model]
        self.session = models.load(model)

    def __call__(self, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
        size = self.spec.input_size
        height, width = image.shape[:2]
        small = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
        small_mask = cv2.resize(mask, (size, size), interpolation=cv2.INTER_NEAREST) > 0
        inputs = self.session.get_inputs()
        feed = {
            inputs[0].name: (small.astype(np.float32) / 255).transpose(2, 0, 1)[None],
            inputs[1].name: small_mask.astype(np.float32)[None, None],
        }
        output = self.session.run(None, feed)[0][0].transpose(1, 2, 0)
        if float(output.max()) <= 1.5:
            output = output * 255
        filled = cv2.resize(np.clip(output, 0, 255).astype(np.float32), (width, height),
                            interpolation=cv2.INTER_LINEAR)
        return np.where(mask[..., None] > 0, filled, image.astype(np.float32))


def colour_inpainter() -> ColourInpainter | None:
    """The registered colour network when it is cached, else None (the classical fill)."""
    from kbbatch import models

    return OnnxInpainter() if models.cached_path("lama") else None
