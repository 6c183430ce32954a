"""Refinement (paper section 3.1): upsampling to the working size with sharp depth edges.

The paper warns that a joint bilateral filter copies image texture into depth. Here each pixel
in a depth-edge zone is given one of the two depths that meet there (the zone's nearest or
farthest), whichever side's colour it resembles: edges land on image edges, and no value that
is not already in the map is ever created, so texture cannot leak in.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from kbbatch import paper

EDGE_STEP_FRACTION = 0.1
"""A window whose disparity range exceeds this fraction of its largest value holds an edge."""

COLOUR_MARGIN_LAB = 20.0
"""A pixel snaps to a side only when it is this much closer (Lab units) to that side's colour."""


def refine(disparity: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Disparity at the image's size, with depth edges snapped to colour edges."""
    height, width = image.shape[:2]
    up = cv2.resize(disparity.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    factor = max(width / disparity.shape[1], height / disparity.shape[0], 1.0)
    window = 2 * (math.ceil(factor) + 1) + 1
    kernel = np.ones((window, window), np.uint8)
    nearest = cv2.dilate(up, kernel)
    farthest = cv2.erode(up, kernel)
    edge = (nearest - farthest) > EDGE_STEP_FRACTION * np.maximum(nearest, 1e-6)
    if not edge.any():
        return up
    colour = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    near_side = (up >= 0.5 * (nearest + farthest)).astype(np.float32)
    far_side = 1.0 - near_side
    size = (2 * window + 1, 2 * window + 1)

    def side_mean(side: np.ndarray) -> np.ndarray:
        weight = cv2.boxFilter(side, -1, size, normalize=False)
        total = cv2.boxFilter(colour * side[..., None], -1, size, normalize=False)
        return total / np.maximum(weight, 1e-6)[..., None]

    near_distance = np.linalg.norm(colour - side_mean(near_side), axis=-1)
    far_distance = np.linalg.norm(colour - side_mean(far_side), axis=-1)
    by_colour = np.where(near_distance < far_distance, nearest, farthest)
    by_value = np.where(near_side > 0, nearest, farthest)
    # The colour decides where it says clearly which side a pixel is on. Elsewhere, across a
    # step of the map itself, the upsampled value does: no depth between the two sides is
    # kept there, since such a pixel is no surface and drifts apart from both as the camera
    # moves (an object's soft edge left floating beside it as faint rings). On a steep slope
    # the smooth upsampling stays: snapped, it would become steps.
    decisive = np.abs(near_distance - far_distance) > COLOUR_MARGIN_LAB
    step = cv2.resize(_steps(disparity), (width, height), interpolation=cv2.INTER_NEAREST)
    step = cv2.dilate(step, kernel) > 0
    snapped = np.where(decisive, by_colour, np.where(step, by_value, up))
    return np.where(edge, snapped, up).astype(np.float32)


def _steps(disparity: np.ndarray) -> np.ndarray:
    """Pixels of the map on a depth discontinuity, by the paper's Laplacian test."""
    normalised = (disparity / max(float(disparity.max()), 1e-6)).astype(np.float32)
    laplacian = cv2.Laplacian(normalised, cv2.CV_32F, ksize=1)
    return (np.abs(laplacian) >= paper.DEPTH_EDGE_LAPLACIAN).astype(np.uint8)
