"""Do no harm: how broken a photo's clip may look, and how much parallax it can bear.

Before the fill, the photo's point cloud is rendered (small) at the overshot end view. A clip
looks broken when much of that view is invented (fill), when fill is enclosed by a nearer
surface (a tear inside an object, not background beside it), or when small depth islands
float in front of their surroundings (fragments). The photo's long straight lines are followed
to the end of the move too: a straight line in the world stays straight in every view and an
upright one stays upright, so one that bends or tilts shows the depth is wrong along it (a pole
or a tower laid on the ground plane of the no-network prior). Over a budget, the relief of the
depth is reduced, step by step down to none (the 2D move), rather than show the damage.
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
    project,
    unproject,
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

LINE_BEND_MAX = 0.01
"""Budget: how far a straight line of the photo may bow in the first or the last frame, as a
fraction of the frame's height (11 px at 1080p), from the chord between its ends (a pinhole
camera keeps every straight line of the world straight)."""

LINE_TILT_MAX_DEG = 4.0
"""Budget: how far an upright line (within LINE_UPRIGHT_DEG of vertical) may turn between the
first frame and the last (the camera does not turn: a real upright stays upright)."""

LINE_UPRIGHT_DEG = 10.0
"""Lines this close to vertical in the photo are taken for uprights. A line on the ground that
recedes straight ahead is near vertical too, and does turn as the camera moves sideways: kept
narrow, fewer of those are taken for uprights (those left may cost parallax for nothing)."""

LINE_MIN_FRACTION = 0.2
"""Only lines at least this long (fraction of the height) are followed: a viewer sees a long
straight line bend, not a short one."""

SEGMENT_MIN_FRACTION = 0.03
"""Line segments found shorter than this (fraction of the height) are not joined into lines."""

LINE_CONTRAST_CLIP = 4.0
"""Lines are also looked for in the photo with its local contrast equalised (CLAHE, this clip
limit): a white pot's tapered sides on a white wall are too faint for the segment detector,
and the ground plane of the no-network prior bent the pots' lower halves outward unseen. Each
image alone misses lines the other finds, so both are used."""

LINE_CONTRAST_TILES = 8
"""... over this many tiles across and down."""

SEGMENTS_MAX = 600
"""Only this many of the longest segments of each image are joined (the joining is quadratic
in their number; foliage gives thousands of short ones)."""

JOIN_ANGLE_DEG = 3.0
"""Two segments are one line when their directions differ by at most this, ..."""

JOIN_OFFSET_PX = 2.5
"""... each end of one lies within this (working px) of the other's line, ..."""

JOIN_GAP_FRACTION = 0.06
"""... and the gap between them is at most this fraction of the height: the bars of a lattice
tower cut its uprights into short pieces."""

LINE_SAMPLES = 64
"""Points followed along each line."""

RUN_MIN_SAMPLES = LINE_SAMPLES // 4
"""A run of a line (between depth edges, and in the frame) is followed if it keeps this many
samples."""

LINE_NEAR_WINDOW_PX = 5
"""A line's depth is the nearest within this window (working px): on an object's outline the
line is the object's."""

LINE_FRAME_HEIGHT_PX = 1000
"""Frames are projected at this height to measure lines (the measures are fractions of it)."""


@dataclass(frozen=True)
class Risk:
    """What the clip of a photo risks, and the relief chosen for it (1 full, 0 the 2D move)."""

    fill_fraction: float
    enclosed_fill_fraction: float
    fragments: int
    relief: float
    reasons: tuple[str, ...]
    line_bend: float = 0.0  # the worst bow of a straight line, fraction of the frame height
    line_tilt_deg: float = 0.0  # the worst turn of an upright line

    def summary(self) -> dict:
        return {"fill_fraction": round(self.fill_fraction, 4),
                "enclosed_fill_fraction": round(self.enclosed_fill_fraction, 5),
                "fragments": self.fragments, "line_bend": round(self.line_bend, 4),
                "line_tilt_deg": round(self.line_tilt_deg, 2), "relief": self.relief,
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


def end_view_fill(photo: np.ndarray, depth: np.ndarray, plan: Plan, scene: SceneGeometry,
                  relief: float = 1.0) -> tuple[float, float]:
    """Shares of the overshot end view (as framed in the output) that need fill, and that
    are fill enclosed by a nearer surface. relief: what depth's relief was scaled by, so that
    its edges are snapped as the clip's layers split them."""
    from kbbatch.inpaint import near_side_of_holes, snap_edge_depth

    cloud = back_project(photo, snap_edge_depth(depth, relief),
                         working_view(scene, (0.0, 0.0, 0.0)))
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


def straight_lines(photo: np.ndarray) -> np.ndarray:
    """The photo's long straight lines, (N, 2, 2) end points (x, y) in working px: OpenCV's
    line segment detector, with collinear segments joined."""
    grey = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    equalised = cv2.createCLAHE(clipLimit=LINE_CONTRAST_CLIP,
                                tileGridSize=(LINE_CONTRAST_TILES,) * 2).apply(grey)
    detector = cv2.createLineSegmentDetector()
    height = photo.shape[0]
    segments = np.concatenate([_longest_segments(detector.detect(image)[0], height)
                               for image in (grey, equalised)])
    lines = join_collinear(list(segments), JOIN_GAP_FRACTION * height)
    long = [line for line in lines
            if np.linalg.norm(line[1] - line[0]) >= LINE_MIN_FRACTION * height]
    return np.array(long, np.float32).reshape(-1, 2, 2)


def _longest_segments(found: np.ndarray | None, height: int) -> np.ndarray:
    """The SEGMENTS_MAX longest of the detector's segments that are long enough to join."""
    if found is None:
        return np.empty((0, 2, 2), np.float64)
    segments = found.reshape(-1, 2, 2).astype(np.float64)
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    longest = np.argsort(-lengths)[:SEGMENTS_MAX]
    return segments[longest[lengths[longest] >= SEGMENT_MIN_FRACTION * height]]


def join_collinear(segments: list[np.ndarray], gap_px: float) -> list[np.ndarray]:
    """Segments (of non-zero length) joined while any two lie on one line: each, longest
    first, takes in every other that lies on its line, until none does."""
    lines = sorted(segments, key=lambda s: -np.linalg.norm(s[1] - s[0]))
    changed = True
    while changed:
        changed = False
        kept: list[np.ndarray] = []
        pending = np.array(lines).reshape(-1, 2, 2)
        while len(pending):
            line, others = pending[0], pending[1:]
            joins = _on_line(line, others, gap_px)
            if joins.any():
                line = _spanning(line, others[joins])
                changed = True
            kept.append(line)
            pending = others[~joins]
        lines = kept
    return lines


def _on_line(line: np.ndarray, others: np.ndarray, gap_px: float) -> np.ndarray:
    """Which of the other segments (N, 2, 2) lie on the line of one: parallel, on it, and
    overlapping it or within gap_px of its ends."""
    if len(others) == 0:
        return np.zeros(0, bool)
    length = float(np.linalg.norm(line[1] - line[0]))
    direction = (line[1] - line[0]) / length
    normal = np.array([-direction[1], direction[0]])
    other = others[:, 1] - others[:, 0]
    cosine = np.abs(other @ direction) / np.linalg.norm(other, axis=1)
    offset = np.abs((others - line[0]) @ normal).max(axis=1)
    along = (others - line[0]) @ direction
    gap = np.maximum(along.min(axis=1) - length, -along.max(axis=1))
    return ((cosine >= np.cos(np.radians(JOIN_ANGLE_DEG))) & (offset <= JOIN_OFFSET_PX)
            & (gap <= gap_px))


def _spanning(line: np.ndarray, others: np.ndarray) -> np.ndarray:
    """The stretch of the line's direction through its start that covers it and the others."""
    direction = (line[1] - line[0]) / np.linalg.norm(line[1] - line[0])
    along = np.concatenate([[0.0, float((line[1] - line[0]) @ direction)],
                            ((others - line[0]) @ direction).ravel()])
    return np.array([line[0] + along.min() * direction, line[0] + along.max() * direction])


def line_runs(lines: np.ndarray, depth: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Sample points (x, y) along each line and their pixels (rows, cols), in runs of one
    surface: a line is cut where it crosses a depth edge (past it, it is another object's
    outline, and the two parts move apart as they should), and its samples near the edge are
    dropped."""
    window = np.ones((LINE_NEAR_WINDOW_PX, LINE_NEAR_WINDOW_PX), np.uint8)
    edges = cv2.dilate(depth_edges(depth).astype(np.uint8), window) > 0
    height, width = depth.shape
    steps = np.linspace(0.0, 1.0, LINE_SAMPLES)[:, None]
    runs = []
    for start, end in lines:
        points = start + steps * (end - start)
        rows = np.clip(points[:, 1].astype(int), 0, height - 1)
        cols = np.clip(points[:, 0].astype(int), 0, width - 1)
        on_edge = edges[rows, cols]
        cuts = np.flatnonzero(on_edge[1:] != on_edge[:-1]) + 1
        for run in np.split(np.arange(LINE_SAMPLES), cuts):
            if len(run) >= RUN_MIN_SAMPLES and not on_edge[run[0]]:
                runs.append((points[run], np.stack([rows[run], cols[run]])))
    return runs


def line_distortion(runs: list[tuple[np.ndarray, np.ndarray]], depth: np.ndarray, plan: Plan,
                    scene: SceneGeometry) -> tuple[float, float]:
    """The worst bow of the runs in the first or the last frame (fraction of its height: one of
    the two is the photo's own view, whichever crop is the wider) and the worst turn of an
    upright one between them (degrees), over their parts visible in both. (The frames shown,
    not the overshot view the fill is judged at.)"""
    height_px = LINE_FRAME_HEIGHT_PX
    widest = widest_crop(plan)
    width_px = max(1, round(height_px * widest.width_px / widest.height_px))
    frames = [output_view(plan, scene, t, width_px, height_px) for t in (0.0, 1.0)]
    window = np.ones((LINE_NEAR_WINDOW_PX, LINE_NEAR_WINDOW_PX), np.uint8)
    nearest = cv2.erode(depth, window)
    worst_bend, worst_tilt = 0.0, 0.0
    for points, (rows, cols) in runs:
        world = unproject(scene, points[:, 0], points[:, 1], nearest[rows, cols])
        seen_at = [np.stack(project(view, *world), axis=1) for view in frames]
        seen = np.ones(len(points), bool)
        for at in seen_at:
            seen &= ((at[:, 0] >= 0) & (at[:, 0] < width_px)
                     & (at[:, 1] >= 0) & (at[:, 1] < height_px))
        if seen.sum() < RUN_MIN_SAMPLES:
            continue
        chords = []
        for at in seen_at:
            at = at[seen]
            chord = at[-1] - at[0]
            normal = np.array([-chord[1], chord[0]]) / max(float(np.linalg.norm(chord)), 1e-9)
            worst_bend = max(worst_bend, float(np.abs((at - at[0]) @ normal).max()))
            chords.append(chord)
        photo_chord = points[-1] - points[0]
        if abs(np.degrees(np.arctan2(photo_chord[0], abs(photo_chord[1]) + 1e-9))) \
                <= LINE_UPRIGHT_DEG:
            (x0, y0), (x1, y1) = chords
            turn = np.degrees(np.arctan2(x1, y1) - np.arctan2(x0, y0))
            worst_tilt = max(worst_tilt, abs((turn + 90.0) % 180.0 - 90.0))
    return worst_bend / height_px, float(worst_tilt)


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
    runs = line_runs(straight_lines(photo), depth)
    measured = None
    for relief in RELIEF_STEPS:
        if fragments > FRAGMENT_COUNT_MAX and relief > FRAGMENT_RELIEF_MAX:
            continue
        relief_depth = relieved(depth, relief)
        relief_scene = SceneGeometry(scene.width_px, scene.height_px,
                                     nearest_depth(relief_depth))
        fill, enclosed = end_view_fill(photo, relief_depth, plan, relief_scene, relief)
        bend, tilt = line_distortion(runs, relief_depth, plan, relief_scene)
        if measured is None:
            measured = (fill, enclosed, bend, tilt)
        over = [message for value, budget, message in (
            (fill, FILL_FRACTION_MAX,
             f"fill {fill:.1%} of the end view > {FILL_FRACTION_MAX:.0%}"),
            (enclosed, ENCLOSED_FILL_FRACTION_MAX,
             f"fill inside objects {enclosed:.2%} of the end view > "
             f"{ENCLOSED_FILL_FRACTION_MAX:.1%}"),
            (bend, LINE_BEND_MAX,
             f"a straight line bows by {bend:.1%} of the frame height > {LINE_BEND_MAX:.1%}"),
            (tilt, LINE_TILT_MAX_DEG,
             f"an upright line tilts by {tilt:.1f} degrees > {LINE_TILT_MAX_DEG:g}"),
        ) if value > budget]
        if relief == 0.0 or not over:
            break
        reasons += [f"{message} at relief {relief}" for message in over]
    return Risk(measured[0], measured[1], fragments, relief, tuple(reasons), measured[2],
                measured[3])
