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
from kbbatch.layers import nearest_pixels, split_layers
from kbbatch.render import (
    SOFT_Z_DISPARITY_PX,
    PointCloud,
    back_project,
    depth_edges,
    points_at,
    render,
)

FOREGROUND_MARGIN = 0.05
"""A pixel beside a hole is foreground when it is this much (relatively) nearer than the
farthest surface around it; foreground pixels are never used as colour sources."""

INTERMEDIATE_TIMES = (0.5, 0.25, 0.75)
"""Times inside the move that are filled too, after the extreme views (once per clip)."""

SOURCE_MARGIN_FRACTION = 0.05
"""Photo points this far (fraction of the long side) outside every crop are still kept."""

EDGE_SNAP_RADIUS_PX = 2
"""Depth-edge pixels snap to the nearest or farthest depth within this radius (working px)."""

FILL_BEHIND_DISPARITY_PX = 0.75
"""Fill points lie at least this much disparity (working px) behind the farthest surface the
photo shows where they fall in its own view: beyond the renderer's blend (SOFT_Z_DISPARITY_PX),
short of its crack test (CRACK_DISPARITY_PX). A fill is what the photo does not show, yet a
crack filled at a cup's rim, level with it, blended into the rim's soft edge and broke the
rim up in the start frame."""

LAYER_GAP_MIN_PX = 2 * SOFT_Z_DISPARITY_PX
"""A band pixel's two layers closer than this in disparity (working px, in the photo's view)
are one point: the renderer blends points within SOFT_Z_DISPARITY_PX of each other as one
surface, and a soft point blended into the opaque one behind it showed as grey blocks along a
lantern's lower edge, where its card meets the ground's depth (at a quarter of the relief).
Twice that: a move changes the gap."""

SOURCE_BAND_PX = 7
"""How far around a hole colour sources are screened for foreground, at the working size."""

PATCH_RADIUS_PX = 3
"""Exemplar fill: patches of (2r+1)^2 pixels are compared, at the working size."""

SEARCH_RADIUS_PX = 40
"""Exemplar fill: random source candidates are drawn within this distance of a hole pixel..."""

SEARCH_SCALES = 3
"""... and within 2x, 4x (up to 2^(n-1)x) that distance, in turn, for holes wider than it."""

RANDOM_CANDIDATES = 24
"""Exemplar fill: random candidates per hole pixel, besides its neighbours' coherent ones."""

REFINE_SWEEPS = 2
"""Exemplar fill: PatchMatch sweeps over the filled pixels after the onion-peel pass."""

VOTE_RADIUS_PX = 2
"""Exemplar fill: the patches voting on a pixel's final colour lie within this radius."""

COARSE_HOLE_PX = 6
"""Exemplar fill: a hole whose thickest part lies farther than this from its border (working
px) is matched at half the size first, and so on, ..."""

PYRAMID_LEVELS_MAX = 3
"""... at most this many times."""

COARSE_TO_FINE_ROUNDS = 3
"""Exemplar fill: PatchMatch sweeps at each level finer than the coarsest, before its vote (a
vote after every sweep blurred stripes)."""


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
    midpoint of the band's disparity range are foreground, the rest are background sources;
    except a pixel with something clearly nearer around it (within twice SOURCE_BAND_PX),
    which is the far side there. Judged over the whole hole alone, a hole running
    down a post into a field (whose ground comes nearer towards the bottom) took the near end
    of the field for foreground and left only the far horizon as its source: the field beside
    the post was filled with sky.
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
    # something clearly nearer close by: then it is the far side there, whatever the hole
    around = cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (4 * SOURCE_BAND_PX + 1, 4 * SOURCE_BAND_PX + 1)
    )
    band_disparity = np.zeros(hole.shape, np.float32)
    band_disparity[band] = disparity
    locally_far = cv2.dilate(band_disparity, around) > band_disparity * (
        1.0 + 2 * FOREGROUND_MARGIN)
    return near & ~locally_far


def fill_background(
    colour: np.ndarray, depth: np.ndarray, hole: np.ndarray, blocked: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fill holes jointly in colour and depth from background sources only, with texture.

    Depth grows in ring by ring from the far side (each hole pixel takes the farthest depth of
    its known neighbours), so the surface behind the hole continues. Colour is an exemplar
    synthesis in the same ring order: each pixel copies real background pixels, found by
    patch matching among sources at least as far as its filled depth, then overlapping
    patches vote: texture, not a flat blob. Blocked pixels (the near side of a hole border)
    and pixels without depth are never sources. A thick hole is matched coarse to fine
    (_match_coarse_to_fine).
    """
    filled_colour = colour.astype(np.float32).copy()
    filled_depth = depth.astype(np.float32).copy()
    source = ~hole & ~blocked & np.isfinite(filled_depth) & (filled_depth > 0)
    ring = _in_ring_order(source, hole)
    _grow_far_depth(filled_depth, source, *ring, SEARCH_RADIUS_PX)
    _match_coarse_to_fine(filled_colour, filled_depth, source, hole, _pyramid_levels(hole),
                          ring=ring)
    return filled_colour, filled_depth


def _in_ring_order(source: np.ndarray, hole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows and columns of the hole's pixels in onion-peel order (_ring_order)."""
    rows, cols = np.nonzero(hole)
    order = _ring_order(source, rows.astype(np.int64), cols.astype(np.int64))
    return rows[order].astype(np.int64), cols[order].astype(np.int64)


def _pyramid_levels(hole: np.ndarray) -> int:
    """How many times a hole is halved before it is matched: until its thickest part is at
    most COARSE_HOLE_PX from its border (0 for thin holes: matched at their own size)."""
    if not hole.any():
        return 0
    thickness = float(cv2.distanceTransform(hole.astype(np.uint8), cv2.DIST_L2, 3).max())
    levels = 0
    height, width = hole.shape
    while (thickness > COARSE_HOLE_PX and levels < PYRAMID_LEVELS_MAX
           and min(height, width) >> (levels + 1) >= 2 * SEARCH_RADIUS_PX):
        thickness /= 2
        levels += 1
    return levels


def _match_coarse_to_fine(colour: np.ndarray, depth: np.ndarray, source: np.ndarray,
                          hole: np.ndarray, levels: int, scale: int = 1,
                          ring: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Fill colour at the hole's pixels in place; returns each one's source pixel. ring: the
    hole's pixels in ring order, when the caller has them (scale: this level's, 1 the photo's).

    At the coarsest level the hole is synthesised ring by ring and refined; each finer level
    starts from the coarser one's sources, enlarged, and improves them with PatchMatch
    sweeps, then votes (after Wexler et al.'s completion). Matched at its own size only, a thick
    hole's inner rings are decided from what its outer rings copied, so an edge running into
    it (a curtain's border) drifts and breaks into steps; the coarse level sees where the
    edge goes across the whole hole.
    """
    ring_rows, ring_cols = ring if ring is not None else _in_ring_order(source, hole)
    nearest = _nearest_sources(source, hole)
    search = max(SEARCH_RADIUS_PX // scale, 2 * PATCH_RADIUS_PX)  # the same reach in the photo
    if levels > 0:
        coarse_source = _halved(source.astype(np.float32)) >= 1.0  # wholly source pixels
        coarse_hole = _halved(hole.astype(np.float32)) > 0.0  # any hole pixel
        if coarse_source.sum() < coarse_hole.sum():  # sources too scattered (sparse depth)
            levels = 0
    if levels == 0:
        offsets = _synthesise(colour, depth, source, ring_rows, ring_cols, nearest, search)
        rounds = REFINE_SWEEPS
    else:
        coarse = [_halved(layer) for layer in (colour, depth)]
        coarse_offsets = _match_coarse_to_fine(*coarse, coarse_source, coarse_hole, levels - 1,
                                               2 * scale)
        offsets = _enlarged_offsets(colour, depth, source, coarse_offsets, ring_rows,
                                    ring_cols, nearest)
        rounds = COARSE_TO_FINE_ROUNDS
    for sweep in range(rounds):
        step = 1 if sweep % 2 else -1  # inward, then outward, ...
        _refine(colour, depth, source, offsets, ring_rows[::step], ring_cols[::step], sweep,
                search)
    _vote(colour, source, offsets, ring_rows, ring_cols)
    return offsets


def _halved(image: np.ndarray) -> np.ndarray:
    """image at half the size, each pixel the mean of a 2x2 block (the last row and column
    repeated where a side is odd)."""
    height, width = image.shape[:2]
    padding = ((0, height % 2), (0, width % 2)) + ((0, 0),) * (image.ndim - 2)
    padded = np.pad(image.astype(np.float32), padding, mode="edge")
    shape = (padded.shape[0] // 2, 2, padded.shape[1] // 2, 2) + padded.shape[2:]
    return padded.reshape(shape).mean(axis=(1, 3))


@numba.njit(cache=True, nogil=True)
def _enlarged_offsets(colour, depth, source, coarse, rows, cols, nearest):
    # Each hole pixel starts from its coarse pixel's source, at twice the distance, with its
    # place inside the 2x2 block; where that is no usable source (a sliver of the near side
    # at the fine size), from its nearest source. Copies the colours too.
    height, width = source.shape
    offsets = np.full((height, width, 2), -1, np.int64)
    for k in range(rows.shape[0]):
        y, x = rows[k], cols[k]
        cy = 2 * coarse[y // 2, x // 2, 0] + y % 2
        cx = 2 * coarse[y // 2, x // 2, 1] + x % 2
        minimum = depth[y, x] * (1.0 - FOREGROUND_MARGIN)
        if (coarse[y // 2, x // 2, 0] < 0 or not (0 <= cy < height and 0 <= cx < width)
                or not source[cy, cx] or depth[cy, cx] < minimum):
            cy, cx = _nearest_source(depth, source, y, x, minimum)
        if cy < 0:
            cy, cx = nearest[y, x, 0], nearest[y, x, 1]
        if cy >= 0:
            offsets[y, x, 0] = cy
            offsets[y, x, 1] = cx
            for c in range(3):
                colour[y, x, c] = colour[cy, cx, c]
    return offsets


def _nearest_sources(source: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """(H, W, 2): at each hole pixel, the row and column of its nearest source pixel (-1
    elsewhere, and everywhere without any source)."""
    nearest = np.full(source.shape + (2,), -1, np.int64)
    if source.any():
        rows, cols = nearest_pixels(source, hole)
        nearest[hole] = np.stack([rows, cols], axis=1)
    return nearest


@numba.njit(cache=True, nogil=True)
def _ring_order(known, rows, cols):
    # Indices of the hole pixels (rows, cols) in onion-peel order: those touching a known
    # pixel first, then ring by ring inward; pixels no ring reaches (fenced in) come last.
    height, width = known.shape
    total = rows.shape[0]
    index = np.full((height, width), -1, np.int64)
    for k in range(total):
        index[rows[k], cols[k]] = k
    reached = known.copy()
    order = np.empty(total, np.int64)
    size = 0
    for k in range(total):
        y, x = rows[k], cols[k]
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if (0 <= yy < height and 0 <= xx < width and known[yy, xx]
                        and not reached[y, x]):
                    reached[y, x] = True
                    order[size] = k
                    size += 1
    start = 0
    while start < size:
        end = size
        for j in range(start, end):
            y, x = rows[order[j]], cols[order[j]]
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy, xx = y + dy, x + dx
                    if (0 <= yy < height and 0 <= xx < width and index[yy, xx] >= 0
                            and not reached[yy, xx]):
                        reached[yy, xx] = True
                        order[size] = index[yy, xx]
                        size += 1
        start = end
    for k in range(total):
        if not reached[rows[k], cols[k]]:
            order[size] = k
            size += 1
    return order


@numba.njit(cache=True, nogil=True)
def _grow_far_depth(depth, known, rows, cols, radius):
    # In ring order, each hole pixel takes the farthest depth among its neighbours of the ring
    # before its own (known pixels are ring 0). Neighbours of its own ring are not used: along
    # a ring the farthest depth would run on from pixel to pixel, and the far end of a long
    # hole (the horizon at the top of a post) flooded all of it. A pixel fenced in by
    # foreground or soft edges takes the farthest known depth within radius: the scene's
    # farthest would have it copy a distant backdrop. (Looked up at those few pixels only: a
    # dilation of the whole view by that disk cost a quarter of a second per view.)
    height, width = known.shape
    ring = np.full((height, width), np.iinfo(np.int64).max, np.int64)
    farthest = np.float32(0.0)
    for y in range(height):
        for x in range(width):
            if known[y, x]:
                ring[y, x] = 0
                if depth[y, x] > farthest:
                    farthest = depth[y, x]
    for k in range(rows.shape[0]):
        y, x = rows[k], cols[k]
        before = np.iinfo(np.int64).max
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if 0 <= yy < height and 0 <= xx < width:
                    before = min(before, ring[yy, xx])
        far = np.float32(0.0)
        if before < np.iinfo(np.int64).max:
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < height and 0 <= xx < width and ring[yy, xx] == before:
                        far = max(far, depth[yy, xx])
            ring[y, x] = before + 1
        else:
            ring[y, x] = 0  # fenced in: a ring of its own
        if far <= 0:  # fenced in: the farthest background around it, else anywhere
            far = _farthest_within(depth, known, y, x, radius)
            if far <= 0:
                far = farthest
        depth[y, x] = far


@numba.njit(cache=True, nogil=True)
def _farthest_within(depth, known, y, x, radius):
    """The farthest known depth within radius px of (y, x); 0 where none is known."""
    height, width = known.shape
    far = np.float32(0.0)
    for yy in range(max(0, y - radius), min(height, y + radius + 1)):
        span = int(np.sqrt(radius * radius - (yy - y) * (yy - y)))
        for xx in range(max(0, x - span), min(width, x + span + 1)):
            if known[yy, xx] and depth[yy, xx] > far:
                far = depth[yy, xx]
    return far


@numba.njit(cache=True, nogil=True)
def _candidate_hash(y, x, k):
    # A fixed pseudo-random number per (pixel, candidate): the fill is deterministic.
    h = (y * 73856093) ^ (x * 19349663) ^ (k * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return h ^ (h >> 16)


@numba.njit(cache=True, nogil=True)
def _patch_distance(colour, valid, source, ty, tx, sy, sx):
    # Mean squared colour difference between the target patch (its known or filled pixels)
    # and the source patch (its source pixels); inf when they share no pixel.
    height, width = source.shape
    radius = PATCH_RADIUS_PX
    total = 0.0
    count = 0
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            y1, x1, y2, x2 = ty + dy, tx + dx, sy + dy, sx + dx
            if not (0 <= y1 < height and 0 <= x1 < width and 0 <= y2 < height
                    and 0 <= x2 < width):
                continue
            if not valid[y1, x1] or not source[y2, x2]:
                continue
            for c in range(3):
                d = colour[y1, x1, c] - colour[y2, x2, c]
                total += d * d
            count += 1
    return total / count if count else np.inf


@numba.njit(cache=True, nogil=True)
def _candidate_score(colour, depth, valid, source, y, x, cy, cx, minimum):
    # A source candidate's patch distance; inf when it is outside, not a background source,
    # or nearer than the surface being continued.
    height, width = source.shape
    if not (0 <= cy < height and 0 <= cx < width) or not source[cy, cx]:
        return np.inf
    if depth[cy, cx] < minimum:
        return np.inf
    return _patch_distance(colour, valid, source, y, x, cy, cx)


@numba.njit(cache=True, nogil=True)
def _synthesise(colour, depth, source, rows, cols, nearest, search):
    # Exemplar synthesis in ring order: each hole pixel copies the centre of the best
    # matching source patch among coherent candidates (its filled neighbours' sources,
    # shifted) and random ones within search px; a candidate must be a source at
    # least as far as the pixel's filled depth. Returns the source of each filled pixel.
    height, width = source.shape
    valid = source.copy()  # sources and copied pixels: what target patches are compared on
    filled = source.copy()  # ... and pixels given a neighbour mean (not compared on)
    offsets = np.full((height, width, 2), -1, np.int64)
    candidates = np.empty((RANDOM_CANDIDATES + 9, 2), np.int64)
    for k in range(rows.shape[0]):
        y, x = rows[k], cols[k]
        minimum = depth[y, x] * (1.0 - FOREGROUND_MARGIN)
        n = 0
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if 0 <= yy < height and 0 <= xx < width and valid[yy, xx]:
                    if offsets[yy, xx, 0] >= 0:
                        candidates[n, 0] = offsets[yy, xx, 0] - dy
                        candidates[n, 1] = offsets[yy, xx, 1] - dx
                    else:
                        candidates[n, 0] = yy
                        candidates[n, 1] = xx
                    n += 1
        for j in range(RANDOM_CANDIDATES):
            h = _candidate_hash(y, x, j)
            reach = search << (j % SEARCH_SCALES)  # near ones, and some far for wide holes
            candidates[n, 0] = y + h % (2 * reach + 1) - reach
            candidates[n, 1] = x + (h >> 11) % (2 * reach + 1) - reach
            n += 1
        best_y, best_x = -1, -1
        best_score = np.inf
        for j in range(n):
            cy, cx = candidates[j, 0], candidates[j, 1]
            score = _candidate_score(colour, depth, valid, source, y, x, cy, cx, minimum)
            if score < best_score:
                best_score = score
                best_y, best_x = cy, cx
        if best_y < 0:  # no patch to compare (fenced in by a soft edge): a near source
            best_y, best_x = _nearest_source(depth, source, y, x, minimum)
        if best_y < 0:  # none far enough on the probes: the nearest source of all
            best_y, best_x = nearest[y, x, 0], nearest[y, x, 1]
        if best_y >= 0:
            for c in range(3):
                colour[y, x, c] = colour[best_y, best_x, c]
            offsets[y, x, 0] = best_y
            offsets[y, x, 1] = best_x
            valid[y, x] = True
        else:  # no source in the whole image: the mean of the far neighbours, else mid grey
            _neighbour_mean(colour, depth, filled, y, x, minimum)
        filled[y, x] = True
    return offsets


@numba.njit(cache=True, nogil=True)
def _nearest_source(depth, source, y, x, minimum):
    # The first source at least minimum deep met going out from (y, x) in the eight
    # directions, pixel by pixel within SEARCH_RADIUS_PX and at doubling distances beyond;
    # (-1, -1) if none. A hole fenced in by a soft edge has no known pixel within any patch,
    # so no patch distance ranks its candidates: without this it took a neighbour mean of
    # nothing (mid grey dashes beside a shoulder).
    height, width = source.shape
    reach = 1
    while reach < 2 * max(height, width):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                cy, cx = y + dy * reach, x + dx * reach
                if ((dy or dx) and 0 <= cy < height and 0 <= cx < width and source[cy, cx]
                        and depth[cy, cx] >= minimum):
                    return cy, cx
        reach = reach + 1 if reach < SEARCH_RADIUS_PX else 2 * reach
    return -1, -1


@numba.njit(cache=True, nogil=True)
def _refine(colour, depth, source, offsets, rows, cols, sweep, search):
    # One PatchMatch sweep over the filled pixels, now that every patch is complete: each
    # tries its neighbours' sources (shifted) and random ones around its own at shrinking
    # distances, and keeps the best far enough source.
    height, width = source.shape
    valid = source.copy()
    for k in range(rows.shape[0]):
        valid[rows[k], cols[k]] = True
    for k in range(rows.shape[0]):
        y, x = rows[k], cols[k]
        minimum = depth[y, x] * (1.0 - FOREGROUND_MARGIN)
        best_y, best_x = offsets[y, x, 0], offsets[y, x, 1]
        best_score = np.inf
        if best_y >= 0:
            best_score = _patch_distance(colour, valid, source, y, x, best_y, best_x)
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                yy, xx = y + dy, x + dx
                if not (0 <= yy < height and 0 <= xx < width) or offsets[yy, xx, 0] < 0:
                    continue
                cy, cx = offsets[yy, xx, 0] - dy, offsets[yy, xx, 1] - dx
                score = _candidate_score(colour, depth, valid, source, y, x, cy, cx, minimum)
                if score < best_score:
                    best_score, best_y, best_x = score, cy, cx
        reach = search
        j = 0
        while reach >= 1 and best_y >= 0:
            h = _candidate_hash(y, x, 1000 * (sweep + 1) + j)
            cy = best_y + h % (2 * reach + 1) - reach
            cx = best_x + (h >> 11) % (2 * reach + 1) - reach
            score = _candidate_score(colour, depth, valid, source, y, x, cy, cx, minimum)
            if score < best_score:
                best_score, best_y, best_x = score, cy, cx
            reach //= 2
            j += 1
        if best_y >= 0:
            offsets[y, x, 0] = best_y
            offsets[y, x, 1] = best_x
            for c in range(3):
                colour[y, x, c] = colour[best_y, best_x, c]


@numba.njit(cache=True, nogil=True)
def _neighbour_mean(colour, depth, valid, y, x, minimum):
    height, width = valid.shape
    total = np.zeros(3, np.float32)
    count = 0
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            yy, xx = y + dy, x + dx
            if (0 <= yy < height and 0 <= xx < width and valid[yy, xx]
                    and depth[yy, xx] >= minimum):
                for c in range(3):
                    total[c] += colour[yy, xx, c]
                count += 1
    for c in range(3):
        colour[y, x, c] = total[c] / count if count else 127.5


@numba.njit(cache=True, nogil=True)
def _vote(colour, source, offsets, rows, cols):
    # Each filled pixel becomes the mean of what the patches of its filled neighbours copied
    # onto it (Wexler et al.'s voting): coherent copies stay sharp, stray ones blend in. A
    # patch's pixel that is neither a source nor filled (the near side beside a source)
    # casts no vote.
    height, width = offsets.shape[:2]
    radius = VOTE_RADIUS_PX
    voted = np.empty((rows.shape[0], 3), np.float32)
    for k in range(rows.shape[0]):
        y, x = rows[k], cols[k]
        total = np.zeros(3, np.float32)
        count = 0
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                yy, xx = y + dy, x + dx
                if 0 <= yy < height and 0 <= xx < width and offsets[yy, xx, 0] >= 0:
                    sy, sx = offsets[yy, xx, 0] - dy, offsets[yy, xx, 1] - dx
                    if (0 <= sy < height and 0 <= sx < width
                            and (source[sy, sx] or offsets[sy, sx, 0] >= 0)):
                        for c in range(3):
                            total[c] += colour[sy, sx, c]
                        count += 1
        for c in range(3):
            voted[k, c] = total[c] / count if count else colour[y, x, c]
    for k in range(rows.shape[0]):
        for c in range(3):
            colour[rows[k], cols[k], c] = voted[k, c]


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
    small_uncovered = cv2.resize(uncovered, small_size, interpolation=cv2.INTER_AREA) > 0
    # Only the region is filled (no frame shows the rest); the rest is no source either. In
    # floats: resized as uint8, a working pixel that a view pixel of the region only partly
    # covers rounded to 0, and the hole pixels along the region's edge took infinite depth.
    small_region = cv2.resize(region.astype(np.float32), small_size,
                              interpolation=cv2.INTER_AREA) > 0
    small_hole = small_uncovered & small_region
    small_depth = cv2.resize(rendering.depth, small_size, interpolation=cv2.INTER_NEAREST)
    small_depth[small_uncovered & ~small_region] = np.inf
    small_colour = cv2.resize(rendering.colour, small_size, interpolation=cv2.INTER_AREA)
    blocked = near_side_of_holes(small_depth, small_hole)
    if rendering.fringe is not None:  # a soft edge's colour is part object: never a source
        blocked |= cv2.resize(rendering.fringe.astype(np.float32), small_size,
                              interpolation=cv2.INTER_AREA) > 0
        blocked &= ~small_hole
    small_colour, small_depth = fill_background(small_colour, small_depth, small_hole, blocked)
    if inpainter is not None:
        image = np.clip(small_colour + 0.5, 0, 255).astype(np.uint8)
        mask = (small_hole | blocked).astype(np.uint8) * 255
        small_colour = inpainter(image, mask).astype(np.float32)
    rows, cols = np.nonzero(hole)
    # Enlarged from filled and background pixels only: a plain bilinear enlargement blends the
    # near side's colour (a magenta star, a dark suit, a soft edge) into the fill's border.
    usable = small_hole | ~(blocked | small_uncovered)
    near_rows, near_cols = _nearest_source_pixel(small_depth.shape, (width, height), rows, cols)
    colour_at = _enlarged_at(small_colour, usable, (width, height), rows, cols,
                             (near_rows, near_cols))
    return points_at(view, rows, cols, small_depth[near_rows, near_cols],
                     np.clip(colour_at + 0.5, 0, 255).astype(np.uint8)), hole_count


def _nearest_source_pixel(small_shape: tuple[int, int], size: tuple[int, int],
                          rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel of an image of small_shape that an enlargement to size (width, height) by
    nearest neighbour gives pixels (rows, cols), computed as cv2.resize's INTER_NEAREST does
    it (in doubles, through the inverse of the scale: at exact multiples that can pick the
    pixel before the one integer arithmetic gives)."""
    small_height, small_width = small_shape

    def nearest(index: np.ndarray, small: int, full: int) -> np.ndarray:
        picked = np.floor(index * (1.0 / (full / small))).astype(np.int64)
        return np.minimum(picked, small - 1)

    return nearest(rows, small_height, size[1]), nearest(cols, small_width, size[0])


def _enlarged_at(colour: np.ndarray, usable: np.ndarray, size: tuple[int, int],
                 rows: np.ndarray, cols: np.ndarray, nearest: tuple[np.ndarray, np.ndarray]
                 ) -> np.ndarray:
    """colour enlarged bilinearly to size (width, height) from its usable pixels alone
    (normalised interpolation), at pixels (rows, cols) only; where no usable pixel is near,
    the colour of their nearest pixels (_nearest_source_pixel's rows and columns). (Only the
    hole pixels of a view become points: enlarging the whole view cost more than the fill.)"""
    small_height, small_width = usable.shape

    def taps(index: np.ndarray, small: int, full: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel centres aligned as cv2.resize's INTER_LINEAR aligns them, clamped at edges."""
        position = (index + 0.5) * (small / full) - 0.5
        low = np.floor(position)
        fraction = (position - low).astype(np.float32)
        low = low.astype(np.int64)
        fraction[(low < 0) | (low >= small - 1)] = 0.0
        low = np.clip(low, 0, small - 1)
        return low, np.minimum(low + 1, small - 1), fraction

    top, bottom, fy = taps(rows, small_height, size[1])
    left, right, fx = taps(cols, small_width, size[0])
    weighted = np.zeros((rows.size, 3), np.float32)
    weight = np.zeros(rows.size, np.float32)
    for ys, wy in ((top, 1 - fy), (bottom, fy)):
        for xs, wx in ((left, 1 - fx), (right, fx)):
            w = wy * wx * usable[ys, xs]
            weighted += w[:, None] * colour[ys, xs]
            weight += w
    return np.where(weight[:, None] > 1e-3, weighted / np.maximum(weight, 1e-3)[:, None],
                    colour[nearest])


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


def snap_edge_depth(depth: np.ndarray, relief: float = 1.0) -> np.ndarray:
    """Depth with every depth-edge pixel moved to the nearer or farther side of its edge.

    Points are splatted independently, so a rubber sheet only comes from in-between depths
    on a blurred edge; snapping each edge pixel to the side it is closest to (in disparity)
    removes the sheet while keeping every pixel of the photo, rim colours included. relief:
    what depth's relief was scaled by (depth_edges).
    """
    edges = depth_edges(depth, relief)
    window = np.ones((2 * EDGE_SNAP_RADIUS_PX + 1,) * 2, np.uint8)
    nearest = cv2.erode(depth, window)
    farthest = cv2.dilate(depth, window)
    to_near = np.abs(1 / depth - 1 / nearest) <= np.abs(1 / depth - 1 / farthest)
    snapped = np.where(to_near, nearest, farthest)
    return np.where(edges, snapped, depth).astype(np.float32)


def layered_cloud(photo: np.ndarray, depth: np.ndarray, view: View, keep: np.ndarray,
                  disparity_scale: float, enlargement: float = 1.0, relief: float = 1.0
                  ) -> tuple[PointCloud, np.ndarray]:
    """The photo as soft layers (kbbatch.layers): one opaque point per pixel away from depth
    edges; within their band a far opaque point with the background's colour and a near point
    with the object's colour and its alpha matte, except where the two would lie within
    LAYER_GAP_MIN_PX of each other: one point, whole, as where no clean background lies near
    (SoftLayers.unsplit). Also the depth of the farthest point at each pixel (the surface a
    fill must stay behind).

    disparity_scale: inverse depth to working disparity pixels (the renderer's); enlargement
    and relief: split_layers'."""
    layers = split_layers(photo, depth, enlargement, relief)
    alpha = np.clip(layers.alpha * 255 + 0.5, 1, 255).astype(np.uint8)
    whole_depth = np.where(layers.alpha >= 0.5, layers.near_depth, layers.far_depth)
    band = layers.band
    close = np.zeros_like(band)  # read at band pixels only: a 4K photo has 8 million others
    close[band] = ((1.0 / layers.near_depth[band] - 1.0 / layers.far_depth[band])
                   * disparity_scale < LAYER_GAP_MIN_PX)
    whole = layers.unsplit | close
    far = layers.far & ~close
    cloud = (
        back_project(photo, layers.depth, view, keep=keep & ~layers.band)
        .extended(back_project(photo, whole_depth, view, keep=keep & whole))
        .extended(back_project(layers.background, layers.far_depth, view, keep=keep & far))
        .extended(back_project(layers.foreground, layers.near_depth, view,
                               keep=keep & layers.near & ~close, alpha=alpha))
    )
    farthest = np.where(far, layers.far_depth, np.where(
        whole, whole_depth, np.where(layers.band, layers.near_depth, layers.depth)))
    return cloud, farthest.astype(np.float32)


def behind_the_photo(points: PointCloud, view: View, photo_view: View, farthest: np.ndarray,
                     disparity_scale: float) -> PointCloud:
    """Fill points (made at view) moved back along view's rays where, seen from the photo's
    own view, they lie less than FILL_BEHIND_DISPARITY_PX behind farthest there (the farthest
    surface the photo shows at each pixel and the pixels around it, which a point splats
    onto). Judged once: moved back, a point falls a little elsewhere, but in the measured
    scenes (36 photos, a synthetic one of three depths) never before a farther surface."""
    if len(points) == 0:
        return points
    height, width = farthest.shape
    cols = np.clip(np.floor(points.x * photo_view.focal_px / points.z
                            + photo_view.principal_x_px), 0, width - 1).astype(np.int64)
    rows = np.clip(np.floor(points.y * photo_view.focal_px / points.z
                            + photo_view.principal_y_px), 0, height - 1).astype(np.int64)
    surface = farthest[rows, cols]
    limit = 1.0 / surface - FILL_BEHIND_DISPARITY_PX / disparity_scale
    # where even the limit is no depth (a surface at the far end), half its disparity
    limit = np.where(limit > 0, limit, 0.5 / surface)
    z = np.where(1.0 / points.z > limit, 1.0 / limit, points.z).astype(np.float32)
    # along the ray from view's centre, so the point still fills the pixel it was made for
    x0, y0, z0 = (np.float32(value) for value in view.position)
    stretch = (z - z0) / (points.z - z0)
    return PointCloud(np.ascontiguousarray(x0 + (points.x - x0) * stretch, dtype=np.float32),
                      np.ascontiguousarray(y0 + (points.y - y0) * stretch, dtype=np.float32),
                      np.ascontiguousarray(z, dtype=np.float32), points.colour, points.alpha)


def build_extended_cloud(
    photo: np.ndarray,
    depth: np.ndarray,
    plan: Plan,
    scene: SceneGeometry,
    inpainter: ColourInpainter | None = None,
    enlargement: float = 1.0,
    relief: float = 1.0,
) -> Extension:
    """The photo as a point cloud in soft layers, extended at the extreme views.

    photo is RGB at the cloud density (any size of the working aspect); depth is at the
    working size. At the start view (when it is not the photo's own) and at the overshot end
    view, the disocclusions are filled with background and appended to the cloud.
    enlargement: working pixels per pixel of the source photo, when smaller (split_layers);
    relief: what depth's relief was scaled by (kbbatch.risk.relieved), 1 when it was not.
    """
    cloud_scale = photo.shape[1] / scene.width_px
    cloud_height = round(scene.height_px * cloud_scale)
    if photo.shape[0] != cloud_height:  # a rounding apart: conform, views are sized this way
        photo = cv2.resize(photo, (photo.shape[1], cloud_height), interpolation=cv2.INTER_LINEAR)
    photo_view = working_view(scene, (0.0, 0.0, 0.0), cloud_scale)
    disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
    cloud, farthest = layered_cloud(photo, depth, photo_view,
                                    source_window(scene, plan, cloud_scale), disparity_scale,
                                    enlargement, relief)
    # a point splats onto the 2 x 2 pixels around it: a fill stays behind all of them
    farthest = cv2.dilate(farthest, np.ones((3, 3), np.uint8))
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
        points = behind_the_photo(points, view, photo_view, farthest, disparity_scale)
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
        from kbbatch import models

        size = models.session_input_size(self.session, (self.spec.input_size,) * 2)
        height, width = image.shape[:2]
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        small_mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST) > 0
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
