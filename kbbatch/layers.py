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

from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch.render import depth_edges

LAYER_BAND_PX = 3
"""Pixels within this distance (working px) of a depth edge may belong to both layers."""

MATTE_RADIUS_PX = 2.0
"""Radius of the guided filter that shapes the matte along colour edges, in working px."""

MATTE_EPSILON = 1e-2
"""Guided-filter regulariser (colours in 0..1). Smaller follows colour edges more closely, but
below about 1e-2 OpenCV's float32 filter degrades to a plain blur on smooth gradients."""

MATTE_SLACK_PX = 1
"""The matte may place the object's edge this far (working px) from its depth edge."""

CLEAN_ALPHA = 0.02
"""Alpha below this is pure background, above 1 minus this pure foreground."""

UNMIX_RADIUS_PX = 4.0
"""How far (working px) clean pixels are looked for to estimate un-mixed colours."""


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
        return self.band & (self.alpha > CLEAN_ALPHA)

    @property
    def far(self) -> np.ndarray:
        return self.band & (self.alpha < 1.0 - CLEAN_ALPHA) & self.has_background


def upsample_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth at the cloud's size, interpolated linearly in disparity.

    Nearest-neighbour enlargement turns a slanted surface (a ground plane) into steps of flat
    strips, and a dolly opens a one-pixel crack between every two strips; interpolating in
    disparity keeps it one smooth surface. Depth edges are handled by the band, not here.
    """
    disparity = cv2.resize(1.0 / depth, (width, height), interpolation=cv2.INTER_LINEAR)
    return (1.0 / disparity).astype(np.float32)


def _normalised_blur(image: np.ndarray, weight: np.ndarray, radius: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of image over the weighted pixels in a box, and the summed weight there."""
    size = (2 * radius + 1, 2 * radius + 1)
    total = cv2.blur(weight, size)
    weighted = cv2.blur(image * weight[..., None], size)
    return weighted / np.maximum(total, 1e-6)[..., None], total


def split_layers(photo: np.ndarray, depth: np.ndarray) -> SoftLayers:
    """The photo (RGB uint8 at the cloud's density) and its depth (working size) as soft layers.

    The matte starts as the near side of each depth edge, enlarged smoothly, and is shaped by
    a guided filter on the full-size photo (OpenCV ximgproc), so it follows the object's real
    edge, anti-aliased. Background colour in the band is the mean of nearby pure-background
    pixels, so no object colour stays behind; foreground colour is the mean of nearby
    pure-foreground pixels corrected by the residual of the compositing equation (fast
    approximate foreground estimation, Forte and Pitie 2021).
    """
    height, width = photo.shape[:2]
    scale = width / depth.shape[1]
    window = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * LAYER_BAND_PX + 1,) * 2)
    nearest = cv2.erode(depth, window)
    farthest = cv2.dilate(depth, window)
    edges = depth_edges(depth).astype(np.uint8)
    small_band = cv2.dilate(edges, window) > 0
    # Which side each pixel is on, judged over a reach that covers the matte filter's window
    # too, so that the filter sees the far side as 0 beyond the band, not as a flat "near".
    reach = LAYER_BAND_PX + int(np.ceil(MATTE_RADIUS_PX)) + 1
    wide = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1,) * 2)
    wide_near = cv2.erode(depth, wide)
    wide_far = cv2.dilate(depth, wide)
    to_near = (np.abs(1 / depth - 1 / wide_near) <= np.abs(1 / depth - 1 / wide_far)) & (
        cv2.dilate(edges, wide) > 0
    )
    size = (width, height)
    band = cv2.resize(small_band.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    near_mask = cv2.resize(to_near.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    guide = photo.astype(np.float32) / 255.0
    radius = max(1, round(MATTE_RADIUS_PX * scale))
    matte = cv2.ximgproc.guidedFilter(guide, near_mask, radius, MATTE_EPSILON)
    # The depth edge says where the object is to within MATTE_SLACK_PX: the matte may move it
    # that far, not further (where the object and its background have the same colour).
    slack = np.ones((2 * MATTE_SLACK_PX + 1,) * 2, np.uint8)
    near_u8 = to_near.astype(np.uint8)
    most = cv2.resize(cv2.dilate(near_u8, slack).astype(np.float32), size,
                      interpolation=cv2.INTER_LINEAR)
    least = cv2.resize(cv2.erode(near_u8, slack).astype(np.float32), size,
                       interpolation=cv2.INTER_LINEAR)
    matte = np.clip(matte, least, most)
    alpha = np.where(band, np.clip(matte, 0.0, 1.0), near_mask > 0.5).astype(np.float32)
    alpha[alpha < CLEAN_ALPHA] = 0.0
    alpha[alpha > 1.0 - CLEAN_ALPHA] = 1.0

    colour = photo.astype(np.float32)
    unmix_radius = max(1, round(UNMIX_RADIUS_PX * scale))
    # Background sources keep a guard of one pixel from any trace of the near layer.
    guard = np.ones((3, 3), np.uint8)
    clean_back = cv2.erode((alpha <= 0.0).astype(np.uint8), guard).astype(np.float32)
    clean_front = (alpha >= 1.0).astype(np.float32)
    back_mean, back_weight = _normalised_blur(colour, clean_back, unmix_radius)
    front_mean, front_weight = _normalised_blur(colour, clean_front, unmix_radius)
    a = alpha[..., None]
    # Where no clean background lies near, there is no background colour to give: the pixel
    # gets no far point, and the extension fills what is behind it from background only.
    has_background = (back_weight > 0) | (alpha <= 0.0)
    background = np.where(a <= 0.0, colour, back_mean)
    front_start = np.where((front_weight > 0)[..., None], front_mean, colour)
    foreground = front_start + a * (colour - a * front_start - (1 - a) * background)
    foreground = np.where(a >= 1.0, colour, foreground)

    smooth = upsample_depth(depth, width, height)
    return SoftLayers(
        depth=smooth,
        band=band,
        has_background=has_background,
        alpha=alpha,
        near_depth=cv2.resize(nearest, size, interpolation=cv2.INTER_NEAREST),
        far_depth=cv2.resize(farthest, size, interpolation=cv2.INTER_NEAREST),
        foreground=np.clip(foreground + 0.5, 0, 255).astype(np.uint8),
        background=np.clip(background + 0.5, 0, 255).astype(np.uint8),
    )
