"""The paper's automatic mode: search the tight crop that reveals the least unseen background.

Beyond the reference: candidates are scored on a coarse point cloud so that the whole search
costs well under a second; the camera is drawn toward the dominant salient object and away
from a move too small to see; ties break deterministically; a plan always comes back.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch import models, paper
from kbbatch.camera import (
    Crop,
    Plan,
    SceneGeometry,
    camera_position,
    clamp_inside,
    fit_crop,
    nearest_depth,
    working_view,
    zoomed,
)
from kbbatch.inpaint import visible_region
from kbbatch.planners import PlanRequest
from kbbatch.render import PointCloud, back_project, coverage, depth_edges
from kbbatch.segment import SALIENT_THRESHOLD, Detection

SEARCH_LONG_SIDE_PX = 256
"""Candidates are rendered at this long side (a quarter of the working size)."""


def search_threads() -> int:
    """Candidates rendered at once: this process's share of the cores (as its ONNX sessions
    get; the daemon's --jobs workers share them). The splatting kernels release the GIL, and
    each candidate's view is independent of the others."""
    return models.session_threads()


SALIENCY_WEIGHT = 0.05
"""Score per unit of distance (in crop widths) between the tight crop and the salient object."""

SALIENT_TARGET_HEIGHT = 0.3
"""The camera leans toward this height of the salient object's box (0 is its top): its upper
part, where faces and heads usually are; the box centre would frame a person's torso."""

HEAD_HEIGHT = 0.12
"""This height of the salient box (its head) must stay in the tight crop when any candidate
allows it: the least-disocclusion objective alone likes to crop heads off."""

HEAD_MARGIN_FRACTION = 0.05

HEAD_TOP_CUT_FRACTION = 0.1
"""An end crop may cut this share of a head's height (twice its centre's depth below its top:
a person's box top, an animal's highest outline point) off its top, the top of the hair, as a
close-up does; no more where another searched crop cuts less. Keeping the head's centre
alone, the end crops of photos 01 to 03 cut through the hairline or the forehead at every
preset (02 at `slideshow`: 63 of its head's 234 working px)."""

CUT_SLACK_FRACTION = 0.01
"""End crops cutting up to this share of their height more than the least cut (off the heads'
tops, or into a subject) are as good (the rest of the search, disocclusion first, chooses
among them)."""

HEAD_HALF_WIDTH_FRACTION = 1 / 6
"""A person's head is about a third of its box's width (the shoulders' width or more): a
crop keeps the whole of it, not its centre alone (a vertical end crop kept a man's head
centre and cut his face in half)."""

PERSON_FIRST_FRACTION = 0.1
"""A person is the subject beside a larger animal or vehicle, down to this share of its box's
area: the minibus behind two men (Ultralytics' sample photo) placed the vertical end crop's
edge through one man's face; a man with his dog and a grazing horse framed the horse."""

GROUP_AREA_FRACTION = 0.3
"""Objects of the dominant one's class whose box has at least this share of its area are its
group: of end crops that keep the dominant head, those keeping the most of the group's heads
are searched (zooming in on five people standing side by side, the end crop cut one's eyes
and another's face for less disocclusion)."""

ANIMAL_CLASSES = ("bird", "cat", "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra",
                  "giraffe")
"""An animal's head is where its salient outline is highest, not its box's top centre: a
walrus lying on a beach holds its head up at one end of its box (framed by the top centre,
a vertical clip cut its face in half)."""

ANIMAL_OUTLINE_MIN_FRACTION = 0.2
"""ISNet's outline inside the box is used when it covers at least this share of the box."""

FRAMING_FREE_FRACTION = 0.8
"""Where the widest crop of the preset's shape shows at most this share of the photo's width
(or height), and no person, animal or vehicle places it, it is placed on what ISNet holds
salient: centred, a vertical clip of a landscape photo showed a lantern's left edge beside
a black wall. (A 3:2 photo in a 16:9 clip keeps 82 % of its height: centred as before.)"""

SUBJECT_MIN_FRACTION = 0.005
"""Less salient area than this share of the photo is no subject to frame."""

SUBJECT_GAIN_FRACTION = 0.1
"""The crop leaves the centre only for at least this share of the salient area more in it..."""

SUBJECT_WHOLE_FRACTION = 0.9
"""... and only where it then holds at least this share of it: a subject it can frame whole.
Three flower pots in a row it cannot, nor a rocket with the towers beside it (at 0.8 the
square crop went to a tower and put the rocket at its edge): centred, they stay balanced."""

SUBJECT_TIE_FRACTION = 0.02
"""Placements within this share of the salient area of the best one are as good: the one
that centres the subject best is taken."""

SUBJECT_STEP_PX = 4
"""Placements are tried this far apart (working px)."""

SUBJECT_CUT_TOLERANCE_PX = 1.0
"""Placements cutting within this of each other into the subject cut it alike (their edges
are rounded to whole pixels)."""

SUBJECT_PIECE_FRACTION = 0.01
"""The subject's extent (top, bottom, sides) is that of its pieces of at least this share of
its area: a stray salient speck does not stretch it (a quantile of its rows would cut a
bottle's neck)."""

SUBJECT_THIN_PX = 5
"""A subject's top is that of its parts at least this wide (working px): a lantern's string
reaching the photo's top is not its top."""

SUBJECT_HEADROOM_FRACTION = 0.1
"""A subject taller than the crop (and no wider) is framed from its top, this share of the
crop's height below the crop's top edge: centred, a landscape clip of two dogs looking out
of a window, one above the other, cut the upper dog's eyes off in both end frames."""

SUBJECT_SOLID_FRACTION = 0.25
"""... if it covers at least this share of its extent's box: salient streaks scattered over
a wood texture, or a few of a rooster's feathers, are no subject with a top or sides (two
dogs cover 0.43 of theirs, a table with a bottle and a drum on a beanbag 0.54)."""

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


@dataclass(frozen=True)
class Head:
    """Where an object's head is, in working px: its centre, half its width and its top."""

    x_px: float
    y_px: float
    half_width_px: float
    top_px: float


def wide_and_tight(request: PlanRequest, head: Head | None = None,
                   subject: Subject | None = None) -> tuple[Crop, Crop]:
    """The widest crop of the output aspect inside 97 % of the image, and it zoomed.

    When the crop cannot show the whole photo (a tall photo, a wide preset), it is placed so
    that the salient object's head sits a third of the way down it, not cut off by centring;
    with no such object, over the subject ISNet holds salient (Subject.framed_by).
    """
    height, width = request.depth.shape
    wide = aspect_crop(request)
    if subject is not None:
        wide = subject.framed_by(wide)
    if head is not None:
        head_x, head_y = head.x_px, head.y_px
        # Kept inside the same 97 % area: moved within the margin box, then shifted back.
        margin_x, margin_y = crop_margins(width, height)
        placed = zoomed(wide, 1.0, (head_x - margin_x, head_y + wide.height_px / 6 - margin_y))
        placed = clamp_inside(placed, width - 2 * margin_x, height - 2 * margin_y)
        wide = zoomed(placed, 1.0, (placed.center_x_px + margin_x,
                                    placed.center_y_px + margin_y))
    return wide, zoomed(wide, request.preset.zoom)


def aspect_crop(request: PlanRequest) -> Crop:
    """The widest crop of the output aspect inside START_CROP_FRACTION of the photo, centred."""
    height, width = request.depth.shape
    return fit_crop(width, height, request.preset.aspect, paper.START_CROP_FRACTION)


def crop_margins(width: float, height: float) -> tuple[float, float]:
    """The margins (x, y) that START_CROP_FRACTION leaves around a crop."""
    return ((1 - paper.START_CROP_FRACTION) / 2 * width,
            (1 - paper.START_CROP_FRACTION) / 2 * height)


def framing_mask(request: PlanRequest) -> np.ndarray | None:
    """What ISNet holds salient, at the depth's size, where the map is there: worked out if
    the widest crop shows at most FRAMING_FREE_FRACTION of the photo's width or height, else
    only where it already is (request.known_saliency)."""
    height, width = request.depth.shape
    saliency = request.saliency() if framing_free(request) else request.known_saliency()
    if saliency is None:
        return None
    if saliency.shape != (height, width):  # a map of another size: brought to the depth's
        saliency = cv2.resize(saliency.astype(np.float32), (width, height),
                              interpolation=cv2.INTER_LINEAR)
    return np.nan_to_num(saliency) >= SALIENT_THRESHOLD


def framing_free(request: PlanRequest) -> bool:
    """Whether the widest crop shows at most FRAMING_FREE_FRACTION of the photo's width or
    height: where to place it is a choice."""
    height, width = request.depth.shape
    wide = aspect_crop(request)
    return min(wide.width_px / width, wide.height_px / height) <= FRAMING_FREE_FRACTION


class Subject:
    """What ISNet holds salient, for framing a photo the preset's shape cannot show whole;
    where it shows most of it (not free), only the subject's top and sides are kept."""

    def __init__(self, salient: np.ndarray, free: bool = True) -> None:
        self.free = free  # framing_free
        self.shape = salient.shape
        self.area = float(salient.sum())
        self.summed = cv2.integral(salient.astype(np.uint8)).astype(np.float64)
        ys, xs = np.nonzero(salient)
        self.centre = (float(xs.mean()), float(ys.mean())) if len(xs) else (0.0, 0.0)
        self.top = self.bottom = self.left = self.right = self.top_x = 0.0
        if len(xs):
            count, labels, stats, _ = cv2.connectedComponentsWithStats(
                salient.astype(np.uint8), connectivity=8)
            kept = 1 + np.flatnonzero(stats[1:, cv2.CC_STAT_AREA]
                                      >= SUBJECT_PIECE_FRACTION * self.area)
            if not kept.size:  # only specks: all of them
                kept = np.arange(1, count)
            pieces = stats[kept]
            self.left = float(pieces[:, cv2.CC_STAT_LEFT].min())
            self.right = float((pieces[:, cv2.CC_STAT_LEFT] + pieces[:, cv2.CC_STAT_WIDTH]).max())
            self.bottom = float((pieces[:, cv2.CC_STAT_TOP] + pieces[:, cv2.CC_STAT_HEIGHT]).max())
            body = np.isin(labels, kept).astype(np.uint8)
            solid = cv2.morphologyEx(body, cv2.MORPH_OPEN, np.ones((1, SUBJECT_THIN_PX), np.uint8))
            if solid.any():  # its top is where it is no thin string
                body = solid
            top = int(np.flatnonzero(body.any(axis=1))[0])
            self.top, self.top_x = float(top), float(np.flatnonzero(body[top]).mean())

    @classmethod
    def of(cls, request: PlanRequest) -> Subject | None:
        """The subject, where ISNet's map is there (framing_mask) and holds at least
        SUBJECT_MIN_FRACTION of the photo."""
        salient = framing_mask(request)
        if salient is None:
            return None
        subject = cls(salient, framing_free(request))
        return subject if subject.area >= SUBJECT_MIN_FRACTION * salient.size else None

    def held(self, left: np.ndarray, top: np.ndarray, right: np.ndarray, bottom: np.ndarray
             ) -> np.ndarray:
        """The salient area inside windows (edges in pixels, rounded and clipped)."""
        height, width = self.shape

        def edge(value: np.ndarray, extent: int) -> np.ndarray:
            return np.clip(np.round(value), 0, extent).astype(int)

        left, right = edge(left, width), edge(right, width)
        top, bottom = edge(top, height), edge(bottom, height)
        summed = self.summed
        return summed[bottom, right] - summed[top, right] - summed[bottom, left] + summed[top, left]

    def held_by(self, crop: Crop) -> float:
        return float(self.held(*(np.array(v) for v in (crop.left_px, crop.top_px,
                                                          crop.right_px, crop.bottom_px))))

    def is_solid(self) -> bool:
        """Whether the subject is solid enough to have a top and sides
        (SUBJECT_SOLID_FRACTION)."""
        height, width = self.bottom - self.top, self.right - self.left
        return self.area >= SUBJECT_SOLID_FRACTION * height * width

    def shows_own_top(self) -> bool:
        """Whether the subject is_solid, its top inside the margin a start crop keeps from
        the photo's edge: a cat's face filling the photo reaches the photo's top; kept, that
        top put the end crop at the photo's edge (the cat's nose cut)."""
        return self.is_solid() and self.top > crop_margins(*self.shape[::-1])[1]

    def cut_px(self, left: np.ndarray | float, top: np.ndarray | float,
               right: np.ndarray | float) -> np.ndarray:
        """How far windows (edges in working px) cut into a solid subject's extent: its top
        where it shows_own_top, into its sides where the extent is no wider than they are (a
        lantern's side, by 8 px, centred in a square clip) and, like its top, inside the
        start crop's margin (a launch tower standing at the photo's edge is no side to keep:
        kept, it pulled a 16:9 end crop into the corner, the rocket cut in half)."""
        cut = np.zeros(np.broadcast(left, top, right).shape)
        if self.shows_own_top():
            cut = np.maximum(cut, np.asarray(top) - self.top)
        margin_x = crop_margins(*self.shape[::-1])[0]
        fits = (np.asarray(right) - np.asarray(left) >= self.right - self.left) & self.is_solid()
        sides = np.maximum(np.asarray(left) - self.left if self.left > margin_x else 0.0,
                           self.right - np.asarray(right)
                           if self.right < self.shape[1] - margin_x else 0.0)
        return np.maximum(cut, np.where(fits, sides, 0.0))

    def too_tall_for(self, crop: Crop) -> bool:
        """Whether the subject fits the crop's width but not its height (a person, an animal,
        a tower in a portrait photo under a landscape preset), where framing is free: it is
        framed from its top."""
        return (self.free and self.bottom - self.top > crop.height_px
                and self.right - self.left <= crop.width_px and self.is_solid())

    def top_head(self) -> Head:
        """The subject's top: what a crop that cannot hold it all keeps."""
        return Head(self.top_x, self.top, 0.0, self.top)

    def framed_by(self, wide: Crop) -> Crop:
        """wide moved, within START_CROP_FRACTION of the photo, to where it holds the most of
        the subject, if that is most of it and clearly more than where it is, or cuts less
        into its top or sides (cut_px; the Middlebury Teddy scene: centred, a 16:9 clip cut the
        bear's head, 8 % of what ISNet held salient); of such places, those cutting least into
        it, and of them the one nearest to centring the subject (its edge, at the nearest
        place to the photo's centre, is cut first when the crop zooms in). A subject too tall
        for it is framed from its top (SUBJECT_HEADROOM_FRACTION)."""
        if self.area <= 0:
            return wide
        height, width = self.shape
        margin_x, margin_y = crop_margins(width, height)

        def centres(margin: float, size: float, extent: int, now: float) -> np.ndarray:
            low, high = margin + size / 2, extent - margin - size / 2
            return np.unique(np.append(np.arange(low, high, SUBJECT_STEP_PX), [high, now]))

        xs = centres(margin_x, wide.width_px, width, wide.center_x_px)
        ys = centres(margin_y, wide.height_px, height, wide.center_y_px)
        grid_x, grid_y = np.meshgrid(xs, ys)
        held = self.held(grid_x - wide.width_px / 2, grid_y - wide.height_px / 2,
                         grid_x + wide.width_px / 2, grid_y + wide.height_px / 2)
        too_tall = self.too_tall_for(wide)
        if too_tall:
            top_y = self.top - SUBJECT_HEADROOM_FRACTION * wide.height_px + wide.height_px / 2
            row = int(np.argmin(np.abs(ys - np.clip(top_y, ys.min(), ys.max()))))
            held, ys = held[row:row + 1], ys[row:row + 1]
            grid_x, grid_y = grid_x[row:row + 1], grid_y[row:row + 1]
        cuts = self.cut_px(grid_x - wide.width_px / 2, grid_y - wide.height_px / 2,
                           grid_x + wide.width_px / 2)
        # moved for clearly more of the subject, or to cut less into its top or sides
        cut_now = self.cut_px(wide.left_px, wide.top_px, wide.right_px)
        cuts_less = ((cuts < cut_now - SUBJECT_CUT_TOLERANCE_PX)
                     & (held >= SUBJECT_WHOLE_FRACTION * self.area))
        gains = self.free and held.max() >= self.held_by(wide) + SUBJECT_GAIN_FRACTION * self.area
        if not too_tall and (held.max() < SUBJECT_WHOLE_FRACTION * self.area
                             or not (gains or cuts_less.any())):
            return wide
        # where framing is not free, moved only to cut less
        good = (held >= held.max() - SUBJECT_TIE_FRACTION * self.area) if self.free else cuts_less
        good &= cuts <= cuts[good].min() + SUBJECT_CUT_TOLERANCE_PX  # of those, the least cut
        distance = np.hypot(grid_x - self.centre[0], grid_y - self.centre[1])
        row, column = np.unravel_index(np.argmin(np.where(good, distance, np.inf)), held.shape)
        return zoomed(wide, 1.0, (float(xs[column]), float(ys[row])))


def ordered(plan_wide: Crop, tight: Crop, zoom_direction: str, easing: str, name: str) -> Plan:
    start, end = (plan_wide, tight) if zoom_direction == "in" else (tight, plan_wide)
    return Plan(start=start, end=end, easing=easing, planner=name)  # type: ignore[arg-type]


def search_offsets(max_shift_px: float) -> np.ndarray:
    """The 16 x 16 grid of centre offsets, plus the centre itself (always a valid fallback)."""
    axis = np.linspace(-max_shift_px, max_shift_px, paper.AUTO_SEARCH_GRID)
    grid = np.array([(dx, dy) for dy in axis for dx in axis])
    return np.vstack([grid, [[0.0, 0.0]]])


def salient_objects(request: PlanRequest) -> list[Detection]:
    """The dominant salient object first (the largest confident person, unless it is under
    PERSON_FIRST_FRACTION of the largest object's area; else the largest object), then the
    others of its class with at least GROUP_AREA_FRACTION of its area: the group whose heads
    the end crop keeps."""
    from kbbatch.segment import detect

    def area(d: Detection) -> float:
        return (d.box[2] - d.box[0]) * (d.box[3] - d.box[1])

    found = sorted((
        d for d in detect(request.image)
        if d.class_name in paper.SALIENT_CLASSES and d.score >= paper.SALIENT_SCORE_MIN
    ), key=area, reverse=True)
    if not found:
        return []
    people = [d for d in found if d.class_name == "person"]
    first = found[0]
    if people and area(people[0]) >= PERSON_FIRST_FRACTION * area(first):
        first = people[0]
    return [first] + [d for d in found if d is not first and d.class_name == first.class_name
                      and area(d) >= GROUP_AREA_FRACTION * area(first)]


def head_of(request: PlanRequest, found: Detection) -> Head:
    """Where the object's head is: HEAD_HEIGHT down its box, at the centre; for an animal,
    where framing is free (framing_mask), below the highest point of its salient outline,
    as wide as the piece of the outline there."""
    x0, y0, x1, y1 = found.box
    centre = Head(*box_point(found.box, HEAD_HEIGHT), HEAD_HALF_WIDTH_FRACTION * (x1 - x0), y0)
    salient = (framing_mask(request) if found.class_name in ANIMAL_CLASSES
               and framing_free(request) else None)
    if salient is None:
        return centre
    left, top = max(0, int(x0)), max(0, int(y0))
    inside = salient[top:int(np.ceil(y1)), left:int(np.ceil(x1))]
    if inside.sum() < ANIMAL_OUTLINE_MIN_FRACTION * max(inside.size, 1):
        return centre
    highest = int(np.flatnonzero(inside.any(axis=1))[0])
    band = inside[highest:highest + max(1, int(HEAD_HEIGHT * (y1 - y0)))].astype(np.uint8)
    _, pieces = cv2.connectedComponents(band, connectivity=8)
    head = pieces == pieces[0, np.flatnonzero(band[0])[0]]  # the piece the highest point is in
    columns = np.nonzero(head)[1]
    return Head(left + float(columns.mean()), top + highest + HEAD_HEIGHT * (y1 - y0),
                (columns.max() - columns.min() + 1) / 2, float(top + highest))


def box_point(box: tuple[float, float, float, float], height_fraction: float
              ) -> tuple[float, float]:
    x0, y0, x1, y1 = box
    return (x0 + x1) / 2, y0 + height_fraction * (y1 - y0)


def keeps(crop: Crop, head: Head, whole: bool = True) -> bool:
    """Whether a crop shows a head whole (else its centre), with a margin around it."""
    margin_x = HEAD_MARGIN_FRACTION * crop.width_px
    if whole:
        margin_x = max(margin_x, head.half_width_px)
    margin_y = HEAD_MARGIN_FRACTION * crop.height_px
    return (crop.left_px + margin_x <= head.x_px <= crop.right_px - margin_x
            and crop.top_px + margin_y <= head.y_px <= crop.bottom_px - margin_y)


@dataclass(frozen=True)
class CoarseScene:
    """The photo's raw point cloud (depth-edge points removed, no fill) at the search size."""

    scene: SceneGeometry
    cloud: PointCloud
    scale: float

    @classmethod
    def of(cls, depth: np.ndarray) -> CoarseScene:
        height, width = depth.shape
        scale = min(1.0, SEARCH_LONG_SIDE_PX / max(width, height))
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        small_depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        scene = SceneGeometry(width, height, nearest_depth(depth))
        colour = np.zeros((*small_depth.shape, 3), np.uint8)
        cloud = back_project(colour, small_depth, working_view(scene, (0.0, 0.0, 0.0), scale),
                             keep=~depth_edges(small_depth))
        return cls(scene, cloud, scale)

    def region(self, wide: Crop, tight: Crop) -> np.ndarray:
        return visible_region(self.scene, ordered(wide, tight, "in", "linear", "auto"),
                              self.scale)

    def disoccluded(self, wide: Crop, tight: Crop, region: np.ndarray | None = None) -> float:
        """Fraction of the output window left uncovered at the tight crop's view."""
        region = self.region(wide, tight) if region is None else region
        plan = ordered(wide, tight, "in", "linear", "auto")
        view = working_view(self.scene, camera_position(plan, self.scene, 1.0), self.scale)
        disparity_scale = self.scene.focal_px * paper.DISPARITY_MAX_PX
        uncovered = ~coverage(self.cloud, view, disparity_scale) & region
        return float(uncovered.sum() / max(int(region.sum()), 1))  # an empty region: none


def plan_disocclusion(request: PlanRequest, plan: Plan) -> float:
    """How much unseen background a plan's tight view reveals (the paper's objective)."""
    wide, tight = ((plan.start, plan.end) if plan.start.width_px >= plan.end.width_px
                   else (plan.end, plan.start))
    return CoarseScene.of(request.depth).disoccluded(wide, tight)


def score_candidates(request: PlanRequest, use_saliency: bool = True, use_motion: bool = True
                     ) -> tuple[Crop, list[Candidate], Crop]:
    """Score every tight-crop candidate; returns the wide crop, the candidates, and the
    unshifted tight crop they were searched around."""
    height, width = request.depth.shape
    group = salient_objects(request) if use_saliency else []
    found = group[0] if group else None
    heads = [head_of(request, d) for d in group]
    head = heads[0] if heads else None
    subject = Subject.of(request) if use_saliency and found is None else None
    wide, tight = wide_and_tight(request, head, subject)
    coarse = CoarseScene.of(request.depth)
    # leaning toward the subject's upper part, below its head (a walrus's, not its back's)
    target = (head.x_px, box_point(found.box, SALIENT_TARGET_HEIGHT)[1]) if found else None
    # Every candidate shares the wide crop, hence the output window.
    region = coarse.region(wide, tight)
    searched = []
    for dx, dy in search_offsets(request.preset.max_shift_px):
        crop = zoomed(tight, 1.0, (float(tight.center_x_px + dx), float(tight.center_y_px + dy)))
        if crop.inside(width, height):
            searched.append((crop, dx, dy))
    with ThreadPoolExecutor(search_threads()) as pool:
        fractions = list(pool.map(lambda s: coarse.disoccluded(wide, s[0], region), searched))
    candidates = []
    for (crop, dx, dy), disoccluded in zip(searched, fractions, strict=True):
        score = disoccluded
        if target is not None:
            distance = np.hypot(crop.center_x_px - target[0], crop.center_y_px - target[1])
            score += SALIENCY_WEIGHT * distance / crop.width_px
        if use_motion:
            shift = np.hypot(dx, dy) / crop.width_px
            score += MOTION_WEIGHT * max(0.0, 1.0 - shift / MIN_VISIBLE_SHIFT_FRACTION)
        candidates.append(Candidate(crop, disoccluded, score))
    if head is not None and candidates:
        def kept(c: Candidate) -> tuple[bool, bool, int]:
            """The subject's head whole, else its centre (a head wider than any crop: a
            close-up, a ship), then the most of its group's."""
            return (keeps(c.crop, head), keeps(c.crop, head, whole=False),
                    sum(keeps(c.crop, h) for h in heads))

        ranks = [kept(c) for c in candidates]
        most = max(ranks)
        candidates = [c for c, rank in zip(candidates, ranks, strict=True) if rank == most]
        candidates = least_cut(candidates, lambda crop: head_top_cut_px(crop, heads))
    elif subject is not None:
        # its top and sides first, then the most of it
        candidates = least_cut(candidates, lambda crop: float(subject.cut_px(
            crop.left_px, crop.top_px, crop.right_px)))
        framed = []
        if subject.too_tall_for(wide):  # the end crop keeps the top it was framed from
            framed = [c for c in candidates if keeps(c.crop, subject.top_head())]
        if subject.free and not framed:  # no end crop keeps less of it than the unshifted one
            least = subject.held_by(tight) - SUBJECT_TIE_FRACTION * subject.area
            framed = [c for c in candidates if subject.held_by(c.crop) >= least]
        candidates = framed or candidates
    return wide, candidates, tight


def head_top_cut_px(crop: Crop, heads: list[Head]) -> float:
    """How much more the crop cuts off the tops of the heads it shows (their centres inside
    it) than HEAD_TOP_CUT_FRACTION of their heights allows."""
    shown = [h for h in heads if crop.left_px <= h.x_px <= crop.right_px]
    return max((crop.top_px - h.top_px - HEAD_TOP_CUT_FRACTION * 2 * (h.y_px - h.top_px)
                for h in shown), default=0.0)


def least_cut(candidates: list[Candidate], cut_px: Callable[[Crop], float]
              ) -> list[Candidate]:
    """The candidates whose crops cut least off the heads' tops or into the subject (cut_px:
    how much, past what may go), within CUT_SLACK_FRACTION."""
    if not candidates:
        return candidates
    cuts = [max(0.0, cut_px(c.crop)) for c in candidates]
    slack = CUT_SLACK_FRACTION * candidates[0].crop.height_px
    return [c for c, cut in zip(candidates, cuts, strict=True) if cut <= min(cuts) + slack]


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
        wide, candidates, tight = score_candidates(request, self.use_saliency, self.use_motion)
        chosen = best(candidates, tight)
        return ordered(wide, chosen, request.preset.zoom_direction, request.preset.easing,
                       self.name)
