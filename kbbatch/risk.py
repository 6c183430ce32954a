"""Do no harm: how broken a photo's clip may look, and how much parallax it can bear.

Before the fill, the photo's point cloud is rendered (small) at the overshot end view. A clip
looks broken when much of that view is invented (fill), when fill is enclosed by a nearer
surface (a tear inside an object, not background beside it), or when small depth islands
float in front of their surroundings (fragments). Over a budget, the relief of the depth is
reduced, step by step down to none (the 2D move), rather than show the damage.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch import paper
from kbbatch.camera import (
    Plan,
    SceneGeometry,
    camera_position,
    nearest_depth,
    output_view,
    overshoot,
    widest_crop,
    working_view,
)
from kbbatch.render import back_project, depth_edges, render
from kbbatch.segment import FRAGMENT_MIN_PX

FILL_FRACTION_MAX = 0.06
"""Budget: share of the end view that is fill (invented background)."""

ENCLOSED_FILL_FRACTION_MAX = 0.003
"""Budget: share of the end view that is fill enclosed by a nearer surface (tears)."""

ENCLOSED_BORDER_FRACTION = 0.8
"""A hole whose border is at least this share nearer surface lies inside an object."""

FRAGMENT_COUNT_MAX = 2
"""Budget: small depth islands floating in front of their surroundings."""

FRAGMENT_AREA_MIN_PX = 16
"""Depth islands smaller than this (working px) are noise, too small to see as a shard."""

FRAGMENT_NEARER_FRACTION = 0.05
"""An island floats when its disparity exceeds its surroundings' by this fraction."""

FRAGMENT_RELIEF_MAX = 0.5
"""Over the fragment budget, the relief is at most this."""

RELIEF_STEPS = (1.0, 0.5, 0.25, 0.0)
"""Reliefs tried in turn, from the full depth to none (the 2D move)."""

ASSESS_WIDTH_PX = 480
"""The end view is judged at this width: its shares, not its detail, matter."""


@dataclass(frozen=True)
class Risk:
    """What the clip of a photo risks, and the relief chosen for it (1 full, 0 the 2D move)."""

    fill_fraction: float
    enclosed_fill_fraction: float
    fragments: int
    relief: float
    reasons: tuple[str, ...]

    def summary(self) -> dict:
        return {"fill_fraction": round(self.fill_fraction, 4),
                "enclosed_fill_fraction": round(self.enclosed_fill_fraction, 5),
                "fragments": self.fragments, "relief": self.relief,
                "reasons": list(self.reasons)}


def relieved(depth: np.ndarray, relief: float) -> np.ndarray:
    """Depth with its relief scaled: disparity compressed toward the nearest surface.

    The nearest surface stays where it is (it follows the crops), farther ones come nearer,
    so every parallax shrinks by the factor; 0 makes the scene flat.
    """
    disparity = 1.0 / depth
    nearest = float(disparity.max())
    return (1.0 / (nearest - relief * (nearest - disparity))).astype(np.float32)


def count_fragments(depth: np.ndarray) -> int:
    """Small regions bounded by depth edges that are clearly nearer than their surroundings."""
    edges = depth_edges(depth)
    count, labels, stats, _ = cv2.connectedComponentsWithStats((~edges).astype(np.uint8),
                                                               connectivity=4)
    disparity = 1.0 / depth
    ring_kernel = np.ones((5, 5), np.uint8)
    fragments = 0
    for label in range(1, count):
        area = stats[label, cv2.CC_STAT_AREA]
        if not FRAGMENT_AREA_MIN_PX <= area < FRAGMENT_MIN_PX:
            continue
        x, y, w, h = (stats[label, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                 cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        top, left = max(0, y - 3), max(0, x - 3)
        window = labels[top:y + h + 3, left:x + w + 3] == label
        ring = cv2.dilate(window.astype(np.uint8), ring_kernel).astype(bool) & ~window
        around = disparity[top:y + h + 3, left:x + w + 3][ring & ~edges[top:y + h + 3,
                                                                           left:x + w + 3]]
        inside = disparity[top:y + h + 3, left:x + w + 3][window]
        if around.size and np.median(inside) > np.median(around) * (1 + FRAGMENT_NEARER_FRACTION):
            fragments += 1
    return fragments


def end_view_fill(photo: np.ndarray, depth: np.ndarray, plan: Plan, scene: SceneGeometry
                  ) -> tuple[float, float]:
    """Shares of the overshot end view (as framed in the output) that need fill, and that
    are fill enclosed by a nearer surface."""
    from kbbatch.inpaint import near_side_of_holes, snap_edge_depth

    cloud = back_project(photo, snap_edge_depth(depth), working_view(scene, (0.0, 0.0, 0.0)))
    start = camera_position(plan, scene, 0.0)
    end = overshoot(start, camera_position(plan, scene, 1.0), paper.EXTREME_VIEW_OVERSHOOT)
    widest = widest_crop(plan)
    height = max(1, round(ASSESS_WIDTH_PX * widest.height_px / widest.width_px))
    view = output_view(plan, scene, 1.0, ASSESS_WIDTH_PX, height, position=end)
    rendering = render(cloud, view, scene.focal_px * paper.DISPARITY_MAX_PX)
    hole = ~rendering.covered
    if not hole.any():
        return 0.0, 0.0
    near = near_side_of_holes(rendering.depth, hole)
    count, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    border_labels = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8))
    border = ~hole & (border_labels > 0)
    of = border_labels[border].astype(np.int64)
    nearer = np.bincount(of, weights=near[border], minlength=count)
    total = np.bincount(of, minlength=count)
    enclosed = nearer >= ENCLOSED_BORDER_FRACTION * np.maximum(total, 1)
    enclosed[0] = False
    return float(hole.mean()), float(enclosed[labels].mean())


def assess(photo: np.ndarray, depth: np.ndarray, plan: Plan, scene: SceneGeometry) -> Risk:
    """The photo's risk at full relief and the largest relief within every budget.

    photo and depth are at the working size.
    """
    if not plan.parallax:
        return Risk(0.0, 0.0, 0, 0.0, ())
    fragments = count_fragments(depth)
    reasons = []
    if fragments > FRAGMENT_COUNT_MAX:
        reasons.append(f"{fragments} depth fragments > {FRAGMENT_COUNT_MAX}")
    measured = None
    for relief in RELIEF_STEPS:
        if fragments > FRAGMENT_COUNT_MAX and relief > FRAGMENT_RELIEF_MAX:
            continue
        relief_depth = relieved(depth, relief)
        relief_scene = SceneGeometry(scene.width_px, scene.height_px,
                                     nearest_depth(relief_depth))
        fill, enclosed = end_view_fill(photo, relief_depth, plan, relief_scene)
        if measured is None:
            measured = (fill, enclosed)
        if relief == 0.0 or (fill <= FILL_FRACTION_MAX
                             and enclosed <= ENCLOSED_FILL_FRACTION_MAX):
            break
        if fill > FILL_FRACTION_MAX:
            reasons.append(f"fill {fill:.1%} of the end view > {FILL_FRACTION_MAX:.0%} "
                           f"at relief {relief}")
        if enclosed > ENCLOSED_FILL_FRACTION_MAX:
            reasons.append(f"fill inside objects {enclosed:.2%} of the end view > "
                           f"{ENCLOSED_FILL_FRACTION_MAX:.1%} at relief {relief}")
    return Risk(measured[0], measured[1], fragments, relief, tuple(reasons))
