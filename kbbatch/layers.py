"""Soft layers at depth edges: an alpha matte and un-mixed colours for both sides.

A pixel on the boundary of a foreground object mixes the object's colour with the
background's. Given to one side only, that mix either travels with the object (a halo) or
stays behind when the object moves away (a ghost). So every pixel within a band around a depth
edge becomes two points: one on the near side, with the edge's alpha matte and the object's own
colour, and one on the far side, opaque, with the background's colour estimated from clean
background pixels only. The renderer composites the two with premultiplied alpha, so the
start view reproduces the photo and every other view moves them apart cleanly (the soft
layering of SLIDE, Jampani et al. 2021).

Everything here works at the cloud's density (one point per output pixel or more), so edges
follow the photo's own colour edges at the output size instead of the working-size depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch.render import depth_edges

LAYER_BAND_PX = 6
"""Pixels within this distance (working px) of a depth edge may belong to both layers: wide
enough for the soft edge of a defocused object (a blur of about 2.5 px)."""

MATTE_RADIUS_PX = 2.0
"""Radius of the guided filter that shapes the matte along colour edges, in working px."""

MATTE_EPSILON = 1e-2
"""Guided-filter regulariser (colours in 0..1). Smaller follows colour edges more closely, but
below about 1e-2 OpenCV's float32 filter degrades to a plain blur on smooth gradients."""

MATTE_SLACK_PX = 1
"""The guided filter may place the object's edge this far (working px) from its depth edge."""

COLOUR_CONTRAST = 40.0
"""Difference (8-bit levels) between object and background colour at which the matte read
from the colours and the one from the guided filter are trusted equally."""

EDGE_BLUR_MAX_PX = 2.5
"""The widest blur (Gaussian sigma, working px) an object's edge is assumed to have: its alpha
beyond the depth edge stays below that blur's tail."""

BACKGROUND_SPREAD = 2.0
"""A band pixel's background colour may differ from the clean estimate by this many standard
deviations of the clean background's own colours (its texture); the rest is the object's."""

BACKGROUND_SLACK = 8.0
"""... plus this many 8-bit levels (noise, and the estimate's own error on flat backgrounds)."""

EDGE_SLACK = 1.0
"""Right at the object's edge the background colour may differ from its clean estimate by
only this many levels; the allowance grows to the full texture spread across the band. What
lies beside an edge is the object's soft tail, rim light or colour fringe far more often than
the background's texture, and left in the background layer it stays behind as a line tracing
the object's old outline (and the fill copies that line as streaks). Even 3 levels traced a
white pot's outline on a white wall (photo 15); what exceeds 1 is the object's."""

BACKGROUND_REACH_WIDER = 4
"""Where no clean background pixel lies near a band pixel, its colour is estimated over a box
this many times wider."""

MIRROR_SPREAD_MIN = 6.0
"""Behind an object, the background's texture is continued (mirrored from its clean pixels)
where that texture's spread exceeds this many levels (a field, foliage, brick); a smoother
background (sky, a wall) takes its flat clean mean, which the mirror would only give shards
of nearby edges."""

MIRROR_DEPTH_MARGIN = 0.05
"""A mirrored texture comes from pixels no nearer than the far side of the edge it continues,
less this fraction of its depth: never from the object itself."""

MIRROR_NORMAL_SMOOTH_PX = 2.0
"""The distance to the clean background is smoothed this much before its gradient gives the
mirror's direction: mirrored through each pixel's nearest clean pixel, a slanted border's
stairs turned the mirror from pixel to pixel, and the texture behind came out saw-toothed."""

BACKGROUND_SLOPE_REACH = 0.1
"""The background continued behind an object along its slope departs at most this fraction
from the disparity of the clean pixel it continues (a steep slope is no plane to extend)."""

MIXED_EDGE_PX = 1.0
"""Up to this far beyond the depth edge (working px) a pixel is read as a mix of object and
background, none of it the background's texture; the texture's share then grows to the full
over MIXED_EDGE_PX more. Behind a shoulder against chandelier lights (photo 03) the lights'
spread took every mixed pixel for texture: their dark half stayed behind as a line tracing
the old outline."""

LEVEL_SIGMA_PX = 3.0
"""Gaussian sigma (working px) over which the background's level (its shading, as against its
texture) is read from clean pixels. A box's ripple left stripes' phase in the level, and a
narrower reach carried a field's dark speck across the band as a streak (photo 33)."""

ENLARGEMENT_MAX = 1.5
"""A small photo's edges are counted in its own pixels up to this enlargement: at 2 (photo 01,
512 px) the band reached a red stripe of the flag beside the astronaut's shoulder, and part of
it went with her layer as a red tick."""

CLEAN_ALPHA = 0.02
"""Alpha below this is pure background, above 1 minus this pure foreground."""

SEE_THROUGH_ALPHA = 0.5
"""A patch of partial alpha with no pixel below this is the object's own grain (the matte's
noise inside a head's hair or ear), not a view through it: it is made opaque. Its background
point, a guess behind a pixel the object nearly hides, stayed behind as a dark speck in the
fill once the object moved off it (photo 03 at 4K)."""


@dataclass(frozen=True)
class SoftLayers:
    """Per pixel of the photo at the cloud's density.

    Outside the band a pixel is one opaque point at depth. Inside, it is a near point
    (near_depth, foreground colour, alpha) where alpha > 0 and a far opaque point
    (far_depth, background colour) where alpha < 1.
    """

    depth: np.ndarray  # (H, W) float32
    band: np.ndarray  # (H, W) bool
    has_background: np.ndarray  # (H, W) bool, where a clean background colour was found
    alpha: np.ndarray  # (H, W) float32 0..1, the near layer's matte
    near_depth: np.ndarray  # (H, W) float32
    far_depth: np.ndarray  # (H, W) float32
    foreground: np.ndarray  # (H, W, 3) uint8
    background: np.ndarray  # (H, W, 3) uint8

    @property
    def near(self) -> np.ndarray:
        return self.band & (self.alpha > CLEAN_ALPHA) & ~self.unsplit

    @property
    def unsplit(self) -> np.ndarray:
        """Band pixels with no clean background near: kept whole, one opaque point on the
        side their alpha leans to (as if there were no layers)."""
        return self.band & (self.alpha < 1.0 - CLEAN_ALPHA) & ~self.has_background

    @property
    def far(self) -> np.ndarray:
        return self.band & (self.alpha < 1.0 - CLEAN_ALPHA) & self.has_background


def _opaque_where_unseen(matte: np.ndarray, band: np.ndarray) -> np.ndarray:
    """matte (at band pixels) at 1 in every patch of partial alpha with no pixel below
    SEE_THROUGH_ALPHA (8-connected)."""
    partial = np.zeros(band.shape, np.uint8)
    partial[band] = matte < 1.0
    count, labels = cv2.connectedComponents(partial, connectivity=8)
    labels_here = labels[band]
    seen_through = np.zeros(count, bool)
    seen_through[labels_here[matte < SEE_THROUGH_ALPHA]] = True
    seen_through[0] = True  # not partial
    return np.where(seen_through[labels_here], matte, np.float32(1.0)).astype(np.float32)


def upsample_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth at the cloud's size, interpolated linearly in disparity.

    Nearest-neighbour enlargement turns a slanted surface (a ground plane) into steps of flat
    strips, and a dolly opens a one-pixel crack between every two strips; interpolating in
    disparity keeps it one smooth surface. Depth edges are handled by the band, not here.
    """
    disparity = cv2.resize(1.0 / depth, (width, height), interpolation=cv2.INTER_LINEAR)
    return (1.0 / disparity).astype(np.float32)


def blurred_edge_tail(distance_px: np.ndarray, blur_px: float = EDGE_BLUR_MAX_PX
                      ) -> np.ndarray:
    """Alpha of a step edge blurred by blur_px (a Gaussian's sigma) at this distance beyond
    it (negative: inside)."""
    table_px = np.linspace(-8.0 * blur_px, 8.0 * blur_px, 513)
    tail = [0.5 * math.erfc(d / (math.sqrt(2.0) * blur_px)) for d in table_px]
    return np.interp(distance_px, table_px, tail).astype(np.float32)


def _remainder(colour: np.ndarray, known: np.ndarray, share: np.ndarray) -> np.ndarray:
    """The other layer's colour, given one layer's colour and its share of the pixel."""
    return (colour - share * known) / np.maximum(1 - share, 1 / 255)


def _into_gamut(colour: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """colour moved along the line to anchor (a clean colour, in gamut) until it is in 0..255.

    Clipping each channel on its own changes the hue of a colour solved from a poor estimate
    (a dark suit's edge over a bright wall turns cyan) and that rim travels with the layer;
    moving towards the layer's own clean colour keeps the hue and stays close to it.
    """
    offset = colour - anchor
    room = np.where(offset > 0, 255.0 - anchor, anchor)  # distance to the gamut per channel
    needed = np.abs(offset)
    fraction = np.min(np.where(needed > room, room / np.maximum(needed, 1e-6), 1.0), axis=-1,
                      keepdims=True)
    return anchor + offset * fraction


def _held_to(colour: np.ndarray, clean: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """colour, each channel within tolerance of the clean colour, in 0..255."""
    return np.clip(clean + np.clip(colour - clean, -tolerance, tolerance), 0, 255)


def _held_near(colour: np.ndarray, clean: np.ndarray, behind: np.ndarray,
               tolerance: np.ndarray) -> np.ndarray:
    """colour held to within tolerance of the clean colour, or of the texture continued behind
    (equal to clean on a smooth background), whichever changes it less.

    Held to the flat clean mean alone, a textured background (a field's dark specks) lost its
    texture in a strip along the object's old outline, which the move uncovered as a pale
    smooth band beside a post (photo 33). Held to the continued texture alone, pixels that
    strayed only a little from the clean mean took a colour from elsewhere, and the start
    view moved further from the photo (on the band pixels of photos 02, 03, 09 and 22, by 1
    to 5 levels on average); the nearer of the two keeps it closer than either does."""
    held = _held_to(colour, clean, tolerance)
    continued = _held_to(colour, behind, tolerance)
    nearer = (np.abs(continued - colour).sum(axis=-1, keepdims=True)
              < np.abs(held - colour).sum(axis=-1, keepdims=True))
    return np.where(nearer, continued, held)


def _normalised_blur(image: np.ndarray, weight: np.ndarray, radius: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of image over the weighted pixels in a box (the side of 2 radius + 1), and the
    summed weight there: a local colour model of some pixels only."""
    size = (2 * radius + 1, 2 * radius + 1)
    total = cv2.blur(weight, size)
    weighted = cv2.blur(image * weight[..., None], size)
    return weighted / np.maximum(total, 1e-6)[..., None], total


def _gaussian_mean(image: np.ndarray, where: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian-weighted mean of image over the pixels of where, at every pixel."""
    weight = cv2.GaussianBlur(where.astype(np.float32), (0, 0), sigma_px)
    weighted = cv2.GaussianBlur(image * where[..., None], (0, 0), sigma_px)
    return weighted / np.maximum(weight, 1e-6)[..., None]


def nearest_pixels(mask: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the nearest pixel of mask (which must have one) to each pixel of
    where (in np.nonzero order)."""
    rows, cols, _ = nearest_with_distance(mask, where)
    return rows, cols


def nearest_with_distance(mask: np.ndarray, where: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """nearest_pixels, and the distance to mask of every pixel (an image)."""
    distance, labels = cv2.distanceTransformWithLabels(
        (~mask).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    mask_rows, mask_cols = np.nonzero(mask)
    by_label = np.zeros((int(labels.max()) + 1, 2), np.int64)
    by_label[labels[mask_rows, mask_cols]] = np.stack([mask_rows, mask_cols], axis=1)
    nearest = by_label[labels[where]]
    return nearest[:, 0], nearest[:, 1], distance


_REMAP_CHUNK = 1024
"""cv2.remap takes maps (and images) of fewer than 32767 rows and columns: a list of pixels
goes in rows this long."""

_SOBEL_GAIN = 8
"""A 3x3 Sobel filter's response to a unit slope."""

_RIDGE_SLOPE = 0.3
"""Where the smoothed distance to the clean pixels rises slower than this per pixel, the pixel
lies on a ridge between two borders, and has no one normal to mirror along."""


def mirrored_texture(colour: np.ndarray, clean: np.ndarray, where: np.ndarray,
                     depth: np.ndarray, far_depth: np.ndarray,
                     nearest: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                     surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                     ) -> np.ndarray:
    """For each pixel of where, the colour of the pixel mirrored across the border of the
    clean pixels, along the border's normal and sampled bilinearly (its nearest clean pixel
    where the mirror falls off): the clean texture continued across the region's border,
    seamless there and smooth along it.

    The mirror may land on any pixel outside where whose depth (per image pixel) is at least
    the pixel's far_depth (per pixel of where), not only on clean ones: those may be a thin
    strip (between the band and the reach of the depth edge), and mirrors falling off it took
    one pixel's colour across the band as a smooth streak. nearest: nearest_with_distance
    (clean, where), when the caller has it already. surface: (level image, each pixel of
    where's level, tolerance per pixel of where): the mirror lands only where the level is
    the pixel's own within the tolerance, on the same surface (beyond a lit curtain, a dark
    one was mirrored behind a head as a dark shard; beyond the sky, a sail's tip)."""
    ys, xs = np.nonzero(where)
    if not clean.any() or len(ys) == 0:
        return colour[ys, xs]
    near_y, near_x, distance = nearest or nearest_with_distance(clean, where)
    fallback = colour[near_y, near_x].astype(np.float32)
    smooth = cv2.GaussianBlur(distance, (0, 0), MIRROR_NORMAL_SMOOTH_PX)
    slope_x = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)[ys, xs] / _SOBEL_GAIN
    slope_y = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)[ys, xs] / _SOBEL_GAIN
    slope = np.hypot(slope_x, slope_y)
    # on a ridge of the distance (between two borders) the normal is undefined: there the
    # mirror goes through the nearest clean pixel
    steep = slope > _RIDGE_SLOPE
    reach = 2 * distance[ys, xs] / np.maximum(slope, 1e-6)
    mirror_x = np.where(steep, xs - reach * slope_x, 2 * near_x - xs)
    mirror_y = np.where(steep, ys - reach * slope_y, 2 * near_y - ys)

    # where the mirror lands: the four pixels it samples bilinearly, then the nearest one,
    # then the mirror through the nearest clean pixel; each must be a background pixel
    left, top = np.floor(mirror_x).astype(np.int32), np.floor(mirror_y).astype(np.int32)
    through_y, through_x = (2 * near_y - ys).astype(np.int32), (2 * near_x - xs).astype(np.int32)
    land_rows = np.stack([top, top, top + 1, top + 1,
                          np.round(mirror_y).astype(np.int32), through_y])
    land_cols = np.stack([left, left + 1, left, left + 1,
                          np.round(mirror_x).astype(np.int32), through_x])
    height, width = clean.shape
    inside = (land_rows >= 0) & (land_rows < height) & (land_cols >= 0) & (land_cols < width)
    flat = (np.clip(land_rows, 0, height - 1).astype(np.int64) * width
            + np.clip(land_cols, 0, width - 1))
    lands = inside & ~where.ravel()[flat] & (
        depth.ravel()[flat] >= far_depth * (1.0 - MIRROR_DEPTH_MARGIN))
    if surface is not None:  # channel by channel: a third of the time of one (6, N, 3) array
        level, level_here, tolerance = surface
        levels, tolerance = level.reshape(-1, 3), tolerance.reshape(-1)
        for channel in range(3):
            lands &= (np.abs(levels[:, channel][flat] - level_here[:, channel])
                      <= tolerance)
    bilinear = lands[:4].all(axis=0)
    nearest = ~bilinear & lands[4]
    through = ~bilinear & ~nearest & lands[5]
    count = len(ys)
    rows = -(-count // _REMAP_CHUNK)
    map_x = np.zeros(rows * _REMAP_CHUNK, np.float32)
    map_y = np.zeros(rows * _REMAP_CHUNK, np.float32)
    map_x[:count] = np.where(nearest, np.round(mirror_x), np.where(through, through_x, mirror_x))
    map_y[:count] = np.where(nearest, np.round(mirror_y), np.where(through, through_y, mirror_y))
    sampled = cv2.remap(np.asarray(colour, np.float32), map_x.reshape(rows, _REMAP_CHUNK),
                        map_y.reshape(rows, _REMAP_CHUNK), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:count]
    return np.where((bilinear | nearest | through)[:, None], sampled, fallback)


def background_depth(depth: np.ndarray, where: np.ndarray, near_rows: np.ndarray,
                     near_cols: np.ndarray, farthest: np.ndarray) -> np.ndarray:
    """The depth of the background layer: at each pixel of where, the background's surface
    continued from its nearest clean pixel (near_rows, near_cols, in np.nonzero order), along
    that surface's slope there (elsewhere farthest, the farthest depth nearby).

    The farthest depth nearby put the background behind an object as far as the ground a
    band's width away: on the sloping ground of the pop-up geometry 4 % farther than the
    ground beside it (photo 03), so that the two moved apart along the object's old outline
    as the camera moved. The nearest clean pixel's depth alone, on a slope, broke the surface
    behind into flat facets."""
    far_depth = farthest.copy()
    disparity = 1.0 / depth
    slope_x = cv2.Sobel(disparity, cv2.CV_32F, 1, 0, ksize=3)[near_rows, near_cols] / _SOBEL_GAIN
    slope_y = cv2.Sobel(disparity, cv2.CV_32F, 0, 1, ksize=3)[near_rows, near_cols] / _SOBEL_GAIN
    where_rows, where_cols = np.nonzero(where)
    start = disparity[near_rows, near_cols]
    continued = start + slope_x * (where_cols - near_cols) + slope_y * (where_rows - near_rows)
    # a surface continued only so far: never far off the depth it starts from
    continued = np.clip(continued, start * (1.0 - BACKGROUND_SLOPE_REACH),
                        start * (1.0 + BACKGROUND_SLOPE_REACH))
    far_depth[where] = 1.0 / continued
    return far_depth


def _window_around(mask: np.ndarray, margin: int) -> tuple[slice, slice]:
    """The box of mask's pixels grown by margin, within the image (all of it when empty)."""
    if not mask.any():
        return slice(None), slice(None)
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return (slice(max(0, rows[0] - margin), rows[-1] + margin + 1),
            slice(max(0, cols[0] - margin), cols[-1] + margin + 1))


def split_layers(photo: np.ndarray, depth: np.ndarray, enlargement: float = 1.0,
                 relief: float = 1.0) -> SoftLayers:
    """The photo (RGB uint8 at the cloud's density) and its depth (working size) as soft layers.

    Near each depth edge, the clean colours of both sides are estimated from pixels well
    inside each side (the background's beyond the band, so that none carries the object's
    soft edge). The matte is each pixel's position on the line between those two colours,
    where they differ, and a guided filter of the near side on the full-size photo (OpenCV
    ximgproc) where they do not; so it follows the object's real, anti-aliased edge at the
    output size. The object's colour is then solved from the compositing equation, so the
    start view reproduces the photo, and the background's is the clean estimate, so no object
    colour stays behind.

    enlargement: working pixels per pixel of the source photo, when it was smaller than the
    working size. Its edges are blurred over that many more working pixels, so the band, the
    matte's reach and the widest edge blur are counted in the photo's own pixels (up to
    ENLARGEMENT_MAX): in working pixels, a small photo's soft edges (a cat's out-of-focus
    cheek, 451 px wide) were cut hard. relief: what the depth's relief was scaled by
    (depth_edges).
    """
    height, width = photo.shape[:2]
    scale = width / depth.shape[1]
    enlargement = min(max(1.0, enlargement), ENLARGEMENT_MAX)
    band_px = round(LAYER_BAND_PX * enlargement)
    blur_px = EDGE_BLUR_MAX_PX * enlargement
    window = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1,) * 2)
    nearest = cv2.erode(depth, window)
    farthest = cv2.dilate(depth, window)
    edges = depth_edges(depth, relief).astype(np.uint8)
    # Split only where the two sides really differ in depth within reach.
    small_band = (cv2.dilate(edges, window) > 0) & (farthest > nearest * 1.001)
    # Which side each pixel is on, judged over twice the band, so that clean pixels of both
    # sides lie within reach of every band pixel. A pixel is judged where its window surely
    # holds both sides of the edge (an edge marks a pixel on each, 1 to 1.5 px apart): at the
    # rim of the window's reach it held one side alone, and a one-pixel ring of background
    # around every object was taken for the object's side (a line of a lantern's glow moved
    # with it, and the clean background beside the edge shrank to a strip: blocks of darker
    # background behind its top).
    reach = 2 * band_px + 2
    wide = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1,) * 2)
    near_depth_wide = cv2.erode(depth, wide)
    far_depth_wide = cv2.dilate(depth, wide)
    judged = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * (reach - 2) + 1,) * 2)
    in_reach = cv2.dilate(edges, judged) > 0
    closer = np.abs(1 / depth - 1 / near_depth_wide) <= np.abs(1 / depth - 1 / far_depth_wide)
    near_side = closer & in_reach
    far_side = ~closer & in_reach
    to_far = cv2.distanceTransform((~far_side).astype(np.uint8), cv2.DIST_L2, 3)
    to_near = cv2.distanceTransform((~near_side).astype(np.uint8), cv2.DIST_L2, 3)
    # Clean background: beyond the band; clean object: its deepest pixels (a thin pole has few).
    back_source = (far_side & (to_near > band_px)).astype(np.float32)
    front_source = np.where(near_side, np.minimum(to_far, band_px) ** 2, 0).astype(np.float32)

    size = (width, height)
    band = cv2.resize(small_band.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    colour = photo.astype(np.float32)
    box = max(1, round(2 * band_px * scale))
    matte_radius = max(1, round(MATTE_RADIUS_PX * enlargement * scale))
    # The local colour models and the guided filter are read at band pixels only: they are
    # computed on the band's box, with a margin as wide as their reach (exact there).
    win = _window_around(band, max(BACKGROUND_REACH_WIDER * box, 2 * matte_radius) + 2)
    here = band[win]
    colour_near = colour[win]
    back_weights = cv2.resize(back_source, size, interpolation=cv2.INTER_LINEAR)[win]
    back_mean, back_weight = _normalised_blur(colour_near, back_weights, box)
    back_square, _ = _normalised_blur(colour_near * colour_near, back_weights, box)
    # Where no clean background lies within the box (a narrow wedge between two spikes, a gap
    # between fingers), a wider one: kept whole instead, the wedge's mixed colour stayed
    # behind as a tinted ghost of the object.
    missing = back_weight <= 1e-3
    if missing[here].any():
        wide_mean, wide_weight = _normalised_blur(colour_near, back_weights,
                                                  BACKGROUND_REACH_WIDER * box)
        wide_square, _ = _normalised_blur(colour_near * colour_near, back_weights,
                                          BACKGROUND_REACH_WIDER * box)
        back_mean = np.where(missing[..., None], wide_mean, back_mean)
        back_square = np.where(missing[..., None], wide_square, back_square)
        back_weight = np.where(missing, wide_weight, back_weight)
    back_spread = np.sqrt(np.maximum(back_square - back_mean * back_mean, 0.0)).mean(axis=-1)
    front_mean, front_weight = _normalised_blur(
        colour_near, cv2.resize(front_source, size, interpolation=cv2.INTER_LINEAR)[win], box)
    has_background = back_weight > 1e-3
    has_foreground = front_weight > 1e-3

    near_mask = cv2.resize(near_side.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    guided = cv2.ximgproc.guidedFilter(colour_near / 255.0, near_mask[win], matte_radius,
                                       MATTE_EPSILON)
    slack = np.ones((2 * MATTE_SLACK_PX + 1,) * 2, np.uint8)
    near_u8 = near_side.astype(np.uint8)
    most = cv2.resize(cv2.dilate(near_u8, slack).astype(np.float32), size,
                      interpolation=cv2.INTER_LINEAR)[win]
    least = cv2.resize(cv2.erode(near_u8, slack).astype(np.float32), size,
                       interpolation=cv2.INTER_LINEAR)[win]
    guided = np.clip(guided, least, most)
    # Beyond the depth edge an object's alpha can only fade like a blurred edge does, so a
    # background that happens to share the object's colour is not taken for part of it.
    # Pixel centres next to the near side lie half a pixel beyond its edge.
    beyond = np.where(near_side, -float(band_px), to_near - 0.5).astype(np.float32)
    within = np.where(near_side, to_far - 0.5, 0.0).astype(np.float32)
    outside_px = cv2.resize(beyond, size, interpolation=cv2.INTER_LINEAR)

    # The rest concerns band pixels only.
    pixel = colour[band]
    back_here = back_mean[here]
    spread_here = back_spread[here]  # the clean background's texture
    background_here, foreground_here = has_background[here], has_foreground[here]
    front_here = np.where(foreground_here[:, None], front_mean[here], pixel)
    # how far a background colour may stray from its clean estimate: its texture, and noise
    texture = BACKGROUND_SPREAD * spread_here + BACKGROUND_SLACK
    contrast = front_here - back_here
    spread = np.sum(contrast * contrast, axis=-1)
    along = np.sum((pixel - back_here) * contrast, axis=-1) / np.maximum(spread, 1e-6)
    trust = spread / (spread + COLOUR_CONTRAST**2)
    # A pixel far off the line between the two colours is no mix of them (a dark spar beside a
    # magenta star is "less green" like the star, and read a third transparent): its colour
    # says nothing of the matte, which the guided filter gives instead.
    off_line = pixel - back_here - along[:, None] * contrast
    trust = trust * texture**2 / (texture**2 + np.sum(off_line * off_line, axis=-1))
    trust = np.where(background_here & foreground_here, trust, 0.0)
    # Beyond the depth edge, a background's own texture moves a pixel along the line to the
    # object's colour too (a red sail towards magenta): only what exceeds that spread is the
    # object's, or the object carries a faint skirt of background texture as its soft edge.
    texture_share = BACKGROUND_SPREAD * spread_here / np.sqrt(np.maximum(spread, 1e-6))
    beyond_edge = outside_px[band] > 0
    # ... except right at the edge, where a pixel is the two sides' mix
    mixed_px = MIXED_EDGE_PX * enlargement
    share_here = texture_share * np.clip(outside_px[band] / mixed_px - 1.0, 0.0, 1.0)
    along = np.where(beyond_edge, (along - share_here) / np.maximum(1 - share_here, 0.1),
                     along)
    matte = trust * np.clip(along, 0.0, 1.0) + (1 - trust) * guided[here]
    matte = np.minimum(matte, blurred_edge_tail(outside_px[band], blur_px))
    # Inside it, likewise, an object can only be as transparent as a blurred edge displaced
    # by its widest blur (the depth edge may sit that far inside): the light grain of a
    # wooden post was taken for half transparency, and the field behind it showed through.
    inside_px = cv2.resize(within, size, interpolation=cv2.INTER_LINEAR)[band]
    matte = np.maximum(matte, np.where(inside_px > 0,
                                       blurred_edge_tail(blur_px - inside_px, blur_px), 0.0))
    matte = np.clip(matte, 0.0, 1.0)
    matte[matte < CLEAN_ALPHA] = 0.0
    matte[matte > 1.0 - CLEAN_ALPHA] = 1.0
    matte = _opaque_where_unseen(matte, band)
    # Alpha is quantised first, as the cloud stores it.
    matte = (np.round(matte * 255) / 255).astype(np.float32)

    # Colours are solved so that the start view reproduces the photo to the 8-bit level: the
    # side with the larger share takes its clean estimate, the other the rest of the pixel.
    a = matte[:, None]
    mostly_front = a >= 0.5
    # Behind the object the background is unknown: its texture mirrored from the clean
    # background beyond the band, not the flat mean, or the move uncovers a smooth strip.
    smooth = upsample_depth(depth, width, height)
    clean_back = cv2.resize(back_source, size, interpolation=cv2.INTER_NEAREST) > 0.5
    farthest_nearby = cv2.resize(farthest, size, interpolation=cv2.INTER_NEAREST)
    # each band pixel's nearest clean background pixel, for the mirror and the depth behind
    nearest_clean = nearest_with_distance(clean_back, band) if clean_back.any() else None
    # The background's shading is continued flat from where it meets the band (its local
    # level at each pixel's nearest clean pixel), its texture by the mirror: mirrored whole, a
    # wall darkening towards a shoulder lightened again behind it, a crease along the old
    # outline; and the wider box mean differed from the wall beside the band by a few levels.
    # (A level varies slowly: it is read at the working size, four times fewer pixels.)
    small_size = (depth.shape[1], depth.shape[0])
    small_clean = back_source > 0.5
    small_colour = cv2.resize(colour, small_size, interpolation=cv2.INTER_AREA)
    small_level = _gaussian_mean(small_colour, small_clean, LEVEL_SIGMA_PX)
    # The texture mirrored is read against the level of where the mirror lands, a mean over
    # the clean pixels and those beyond every edge's reach (no soft edge among them): read
    # against the clean ring's level, extrapolated beyond the ring, it was the difference
    # between two surfaces (a dark curtain beyond a lit one laid a dark shard behind a head).
    level = cv2.resize(_gaussian_mean(small_colour, small_clean | ~in_reach, LEVEL_SIGMA_PX),
                       size, interpolation=cv2.INTER_LINEAR)
    if small_clean.any():
        # carried to each band pixel from its nearest clean pixel, then smoothed along the
        # band: nearest clean pixels jump along a border's stairs, and carried alone the
        # level made blocks
        rows, cols, _ = nearest_with_distance(small_clean, small_band)
        carried = np.zeros_like(small_level)
        carried[small_band] = small_level[rows, cols]
        carried = _gaussian_mean(carried, small_band, LEVEL_SIGMA_PX)
        level_here = cv2.resize(carried, size, interpolation=cv2.INTER_LINEAR)[band]
    else:
        level_here = back_here
    level_here = np.where(background_here[:, None], level_here, back_here)
    detail = mirrored_texture(colour - level, clean_back, band, smooth,
                              farthest_nearby[band], nearest_clean,
                              surface=(level, level_here, texture))
    # ... less what lies further along the line to the object's colour than the texture's
    # own spread: a trace of the object (the blurred tail of a wire) in the clean background
    # would be copied behind it as a ghost. The same is taken off the other way, or the
    # texture behind comes out paler than the texture it continues (dark grass dropped).
    towards = np.sum(detail * contrast, axis=-1) / np.maximum(spread, 1e-6)
    excess = towards - np.clip(towards, -texture_share, texture_share)
    back_behind = level_here + detail - excess[:, None] * contrast
    textured = background_here & (spread_here > MIRROR_SPREAD_MIN)
    back_behind = np.where(textured[:, None],
                           _held_to(back_behind, np.clip(level_here, 0, 255), texture[:, None]),
                           level_here)
    first = np.round(np.clip(np.where(mostly_front, back_behind, front_here), 0, 255))
    share = np.where(mostly_front, 1 - a, a)  # the larger share's side, and its share
    second = _remainder(pixel, first, share)
    # Where the background (as the remainder) strays from its clean estimate further than
    # the background's own texture does, or out of gamut, the object takes up the
    # difference: it is the object's (a rim light, a lighter edge) and must not stay behind
    # as a ghost. Never the other way, which would hand the object's colour to the
    # background. What the object cannot take (out of its gamut) is dropped: the start view
    # then differs from the photo there, which is less visible than a ghost. (Held to the
    # texture mirrored from beside the object instead of the clean mean, a pixel wholly the
    # background's strayed wherever the mirror was not the photo, and the start frame lost
    # structure at edges: a railing's bar beside a man on a ladder, photo 22.)
    back_clean = np.clip(level_here, 0, 255)
    # the allowance grows with the square of the distance: an object's soft tail fades fast
    from_edge = np.clip(outside_px[band][:, None] / band_px, 0.0, 1.0) ** 2
    tolerance = EDGE_SLACK + (texture[:, None] - EDGE_SLACK) * from_edge
    behind = np.clip(back_behind, 0, 255)
    kept = _held_near(second, back_clean, behind, tolerance)
    strays = np.any(np.abs(kept - second) > 0.5, axis=-1, keepdims=True) & ~mostly_front
    first = np.where(strays, _into_gamut(_remainder(pixel, np.round(kept), 1 - share),
                                         np.clip(front_here, 0, 255)), first)
    first = np.round(np.clip(first, 0, 255))
    second = _remainder(pixel, first, share)
    second = np.where(mostly_front, _into_gamut(second, np.clip(front_here, 0, 255)),
                      _held_near(second, back_clean, behind, tolerance))
    second = np.round(np.clip(second, 0, 255))
    front_band = np.where(a >= 1.0, pixel, np.where(mostly_front, second, first))
    # A band pixel the matte left wholly to the background is held to the same allowance: near
    # the edge, what strays further is dropped (the start view loses a faint rim) rather than
    # left behind.
    whole = np.where(background_here[:, None],
                     np.round(_held_near(pixel, back_clean, behind, tolerance)), pixel)
    back_band = np.where(a <= 0.0, whole, np.where(mostly_front, first, second))

    alpha = (near_mask > 0.5).astype(np.float32)
    alpha[band] = matte
    foreground = photo.copy()
    foreground[band] = front_band.astype(np.uint8)
    background = photo.copy()
    background[band] = back_band.astype(np.uint8)
    # Where no clean background lies near, there is no background colour to give: the pixel
    # is kept whole (unsplit), and the extension fills what is behind it from background only.
    found = np.zeros((height, width), bool)
    found[win] = has_background
    has_background = found | (alpha <= 0.0)
    if nearest_clean is None:
        far_depth = farthest_nearby
    else:
        continued = has_background[band]
        far_depth = background_depth(smooth, band & has_background,
                                     nearest_clean[0][continued], nearest_clean[1][continued],
                                     farthest_nearby)

    return SoftLayers(
        depth=smooth,
        band=band,
        has_background=has_background,
        alpha=alpha,
        near_depth=cv2.resize(nearest, size, interpolation=cv2.INTER_NEAREST),
        far_depth=far_depth,
        foreground=foreground,
        background=background,
    )
