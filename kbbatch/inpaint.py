"""Fill disocclusions once, at the extreme views, and extend the point cloud (paper section 3.2).

Every frame is then rendered from the extended cloud, so the fill never flickers. The fill is
background by construction: depth grows in from the far side of each hole border, and colour
is inpainted from background pixels only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch import paper
from kbbatch.camera import Plan, SceneGeometry, View, camera_position, overshoot, working_view
from kbbatch.render import PointCloud, back_project, depth_edges, render

FOREGROUND_MARGIN = 0.05
"""A pixel beside a hole is foreground when it is this much (relatively) nearer than the
farthest surface around it; foreground pixels are never used as colour sources."""

SOURCE_BAND_PX = 7
"""How far around a hole colour sources are screened for foreground, at the working size."""

TELEA_RADIUS_PX = 5
"""Neighbourhood of OpenCV's Telea inpainting, at the working size."""

ColourInpainter = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(RGB uint8 image, uint8 mask of pixels to fill) -> RGB uint8 image; e.g. an ONNX network."""


@dataclass(frozen=True)
class Extension:
    """What the extension added, for the benchmark and the tests."""

    cloud: PointCloud
    added_points: int
    hole_pixels_photo: int
    """Pixels left empty at the photo's own view by the removed depth-edge points."""
    hole_pixels_end: int
    """Pixels disoccluded at the overshot end view before the fill."""


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


def fill_depth_background(
    depth: np.ndarray, hole: np.ndarray, blocked: np.ndarray | None = None
) -> np.ndarray:
    """Fill holes by growing the farthest source depth inward, one ring at a time.

    Blocked pixels (the near side of a hole border) are never sources, so a hole takes the
    depth of the surface behind it, not of the object beside it.
    """
    sources = ~hole if blocked is None else ~hole & ~blocked
    filled = np.where(sources, depth, 0.0).astype(np.float32)
    known = sources.copy()
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(max(filled.shape)):
        reached = cv2.dilate(known.astype(np.uint8), kernel).astype(bool) & hole & ~known
        if not reached.any():
            break
        grown = cv2.dilate(filled, kernel)
        filled[reached] = grown[reached]
        known |= reached
    unreached = hole & ~known
    if unreached.any():
        filled[unreached] = float(np.max(filled))
    return np.where(hole, filled, depth).astype(np.float32)


def inpaint_colour(
    colour: np.ndarray,
    hole: np.ndarray,
    blocked: np.ndarray,
    inpainter: ColourInpainter | None = None,
) -> np.ndarray:
    """Fill holes with background colour: blocked (foreground) pixels are hidden first."""
    mask = (hole | blocked).astype(np.uint8) * 255
    if inpainter is not None:
        filled = inpainter(colour, mask)
    else:
        filled = cv2.inpaint(colour, mask, TELEA_RADIUS_PX, cv2.INPAINT_TELEA)
    return np.where(hole[..., None], filled, colour)


def extend_at_view(
    cloud: PointCloud,
    view: View,
    disparity_scale: float,
    region: np.ndarray,
    working_scale: float,
    known_colour: np.ndarray | None = None,
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
                          np.empty((0, 3), np.uint8)), 0  # fmt: skip
    height, width = hole.shape
    small_size = (max(1, round(width * working_scale)), max(1, round(height * working_scale)))
    small_hole = cv2.resize(hole.astype(np.uint8), small_size, interpolation=cv2.INTER_AREA) > 0
    small_covered = cv2.resize(
        rendering.covered.astype(np.uint8), small_size, interpolation=cv2.INTER_AREA
    ).astype(bool) & ~small_hole
    small_depth = cv2.resize(rendering.depth, small_size, interpolation=cv2.INTER_NEAREST)
    small_hole = ~small_covered
    blocked = near_side_of_holes(small_depth, small_hole)
    small_depth = fill_depth_background(small_depth, small_hole, blocked)
    depth_full = cv2.resize(small_depth, (width, height), interpolation=cv2.INTER_NEAREST)
    if known_colour is not None:
        colour_full = known_colour
    else:
        small_colour = cv2.resize(
            np.clip(rendering.colour, 0, 255).astype(np.uint8), small_size,
            interpolation=cv2.INTER_AREA,
        )  # fmt: skip
        small_filled = inpaint_colour(small_colour, small_hole, blocked, inpainter)
        colour_full = cv2.resize(small_filled, (width, height), interpolation=cv2.INTER_LINEAR)
    return back_project(colour_full, depth_full, view, keep=hole), hole_count


def visible_region(scene: SceneGeometry, plan: Plan, scale: float) -> np.ndarray:
    """Pixels of a full working view (times scale) that some output frame can show."""
    width = round(scene.width_px * scale)
    height = round(scene.height_px * scale)
    widest_w = max(plan.start.width_px, plan.end.width_px) * scale
    widest_h = max(plan.start.height_px, plan.end.height_px) * scale
    margin = 2.0 * scale
    region = np.zeros((height, width), bool)
    left = max(0, int(np.floor(width / 2 - widest_w / 2 - margin)))
    top = max(0, int(np.floor(height / 2 - widest_h / 2 - margin)))
    right = min(width, int(np.ceil(width / 2 + widest_w / 2 + margin)))
    bottom = min(height, int(np.ceil(height / 2 + widest_h / 2 + margin)))
    region[top:bottom, left:right] = True
    return region


def build_extended_cloud(
    photo: np.ndarray,
    depth: np.ndarray,
    plan: Plan,
    scene: SceneGeometry,
    inpainter: ColourInpainter | None = None,
) -> Extension:
    """The photo as a point cloud (edges removed), extended at the start and end views.

    photo is RGB at the cloud density (any size of the working aspect); depth is at the
    working size. At the photo's own view the removed edge pixels come back with their own
    colour, pushed to the background depth; at the start view (when it moved) and the
    overshot end view the disocclusions are inpainted.
    """
    cloud_scale = photo.shape[1] / scene.width_px
    cloud_depth = cv2.resize(depth, (photo.shape[1], photo.shape[0]),
                             interpolation=cv2.INTER_NEAREST)  # fmt: skip
    edges_small = depth_edges(depth).astype(np.float32)
    edges = cv2.resize(edges_small, (photo.shape[1], photo.shape[0]),
                       interpolation=cv2.INTER_LINEAR) > 0  # fmt: skip
    photo_view = working_view(scene, (0.0, 0.0, 0.0), cloud_scale)
    cloud = back_project(photo, cloud_depth, photo_view, keep=~edges)
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    region = visible_region(scene, plan, cloud_scale)
    start_position = camera_position(plan, scene, 0.0)
    end_position = overshoot(
        start_position, camera_position(plan, scene, 1.0), paper.EXTREME_VIEW_OVERSHOOT
    )
    views: list[tuple[tuple[float, float, float], np.ndarray | None]] = [
        ((0.0, 0.0, 0.0), photo)
    ]
    if start_position != (0.0, 0.0, 0.0):
        views.append((start_position, None))
    views.append((end_position, None))
    added = 0
    holes = []
    for position, known_colour in views:
        view = working_view(scene, position, cloud_scale)
        points, hole_count = extend_at_view(
            cloud, view, disparity_scale, region, 1.0 / cloud_scale,
            known_colour=known_colour, inpainter=inpainter,
        )  # fmt: skip
        holes.append(hole_count)
        added += len(points)
        cloud = cloud.extended(points)
    return Extension(cloud, added, holes[0], holes[-1])
