"""The paper's automatic mode: search the tight crop that reveals the least unseen background.

Beyond the reference: candidates are scored on a coarse point cloud so that the whole search
costs well under a second; the camera is drawn toward the dominant salient object and away
from a move too small to see; ties break deterministically; a plan always comes back.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch import paper
from kbbatch.camera import (
    Crop,
    Plan,
    SceneGeometry,
    camera_position,
    fit_crop,
    nearest_depth,
    working_view,
    zoomed,
)  # fmt: skip
from kbbatch.inpaint import visible_region
from kbbatch.render import back_project, coverage, depth_edges
from planners import PlanRequest

SEARCH_LONG_SIDE_PX = 256
"""Candidates are rendered at this long side (a quarter of the working size)."""

SALIENCY_WEIGHT = 0.05
"""Score per unit of distance (in crop widths) between the tight crop and the salient object."""

MOTION_WEIGHT = 0.02
"""Score of a candidate that does not move sideways at all, fading out at MIN_VISIBLE_SHIFT."""

MIN_VISIBLE_SHIFT_FRACTION = 0.03
"""A lateral move under this fraction of the crop width reads as no move at all."""


@dataclass(frozen=True)
class Candidate:
    """One searched tight crop and what it scored, for the benchmark and previews."""

    crop: Crop
    disoccluded: float  # fraction of the output window left uncovered
    score: float


def wide_and_tight(request: PlanRequest) -> tuple[Crop, Crop]:
    """The widest crop of the output aspect inside 97 % of the image, and it zoomed."""
    height, width = request.depth.shape
    wide = fit_crop(width, height, request.preset.aspect, paper.START_CROP_FRACTION)
    return wide, zoomed(wide, request.preset.zoom)


def ordered(plan_wide: Crop, tight: Crop, zoom_direction: str, easing: str, name: str) -> Plan:
    start, end = (plan_wide, tight) if zoom_direction == "in" else (tight, plan_wide)
    return Plan(start=start, end=end, easing=easing, planner=name)  # type: ignore[arg-type]


def search_offsets(max_shift_px: float) -> np.ndarray:
    """The 16 x 16 grid of centre offsets, plus the centre itself (always a valid fallback)."""
    axis = np.linspace(-max_shift_px, max_shift_px, paper.AUTO_SEARCH_GRID)
    grid = np.array([(dx, dy) for dy in axis for dx in axis])
    return np.vstack([grid, [[0.0, 0.0]]])


def salient_target(request: PlanRequest) -> tuple[float, float] | None:
    """Centre of the dominant salient object (largest confident salient box), if any."""
    from kbbatch.segment import detect

    boxes = [
        d for d in detect(request.image)
        if d.class_name in paper.SALIENT_CLASSES and d.score >= paper.SALIENT_SCORE_MIN
    ]  # fmt: skip
    if not boxes:
        return None
    x0, y0, x1, y1 = max(boxes, key=lambda d: (d.box[2] - d.box[0]) * (d.box[3] - d.box[1])).box
    return (x0 + x1) / 2, (y0 + y1) / 2


def score_candidates(request: PlanRequest, use_saliency: bool = True, use_motion: bool = True
                     ) -> tuple[Crop, list[Candidate]]:  # fmt: skip
    """Score every tight-crop candidate; returns the wide crop and the candidates."""
    height, width = request.depth.shape
    wide, tight = wide_and_tight(request)
    scale = min(1.0, SEARCH_LONG_SIDE_PX / max(width, height))
    small_depth = cv2.resize(request.depth, (max(1, round(width * scale)),
                                             max(1, round(height * scale))),
                             interpolation=cv2.INTER_NEAREST)  # fmt: skip
    scene = SceneGeometry(width, height, nearest_depth(request.depth))
    colour = np.zeros((*small_depth.shape, 3), np.uint8)
    cloud = back_project(colour, small_depth, working_view(scene, (0.0, 0.0, 0.0), scale),
                         keep=~depth_edges(small_depth))  # fmt: skip
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    target = salient_target(request) if use_saliency else None
    # Every candidate shares the wide crop, hence the output window.
    region = visible_region(scene, ordered(wide, tight, "in", "linear", "auto"), scale)
    region_pixels = region.sum()
    candidates = []
    for dx, dy in search_offsets(request.preset.max_shift_px):
        crop = zoomed(tight, 1.0, (float(tight.center_x_px + dx), float(tight.center_y_px + dy)))
        if not crop.inside(width, height):
            continue
        plan = ordered(wide, crop, "in", "linear", "auto")
        view = working_view(scene, camera_position(plan, scene, 1.0), scale)
        uncovered = ~coverage(cloud, view, disparity_scale) & region
        disoccluded = float(uncovered.sum() / region_pixels)
        score = disoccluded
        if target is not None:
            distance = np.hypot(crop.center_x_px - target[0], crop.center_y_px - target[1])
            score += SALIENCY_WEIGHT * distance / crop.width_px
        if use_motion:
            shift = np.hypot(dx, dy) / crop.width_px
            score += MOTION_WEIGHT * max(0.0, 1.0 - shift / MIN_VISIBLE_SHIFT_FRACTION)
        candidates.append(Candidate(crop, disoccluded, score))
    return wide, candidates


def best(candidates: list[Candidate], tight: Crop) -> Crop:
    """Lowest score; ties go to the smaller move, then to the grid order (deterministic)."""
    def key(c: Candidate) -> tuple[float, float, float, float]:
        dx = c.crop.center_x_px - tight.center_x_px
        dy = c.crop.center_y_px - tight.center_y_px
        return (round(c.score, 9), round(np.hypot(dx, dy), 6), round(dy, 6), round(dx, 6))

    return min(candidates, key=key).crop if candidates else tight


class AutoPlanner:
    name = "auto"

    def __init__(self, use_saliency: bool = True, use_motion: bool = True) -> None:
        self.use_saliency = use_saliency
        self.use_motion = use_motion

    def plan(self, request: PlanRequest) -> Plan:
        wide, candidates = score_candidates(request, self.use_saliency, self.use_motion)
        _, tight = wide_and_tight(request)
        chosen = best(candidates, tight)
        return ordered(wide, chosen, request.preset.zoom_direction, request.preset.easing,
                       self.name)  # fmt: skip
