"""Point cloud from image + depth, and its forward-projection renderer (paper section 3.2).

The kernels are compiled with numba and release the GIL, so frames render in parallel threads
(one frame per thread keeps every frame bit-identical whatever the thread count).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from kbbatch import paper
from kbbatch.camera import View

SOFT_Z_DISPARITY_PX = 0.5
"""A point splats onto a pixel when its disparity is within this of the front surface there
(in working pixels of disparity): surfaces closer than this blend, farther ones are hidden."""

CRACK_DISPARITY_PX = 1.0
"""A pixel whose two opposite neighbours are nearer by this much disparity is background shining
through a crack in a magnified foreground (the paper's z-buffer filter)."""

MIN_SPLAT_WEIGHT = 1e-3
"""Bilinear weights below this neither claim the z-buffer nor colour a pixel."""

NEAR_PLANE = 1e-3
"""Points closer to the camera than this (working units) are behind it and skipped."""


@dataclass(frozen=True)
class PointCloud:
    """Coloured 3D points in working units (camera at the origin for the input photo)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    colour: np.ndarray  # (N, 3) uint8 RGB

    def __len__(self) -> int:
        return int(self.z.shape[0])

    def extended(self, other: PointCloud) -> PointCloud:
        return PointCloud(
            np.concatenate([self.x, other.x]),
            np.concatenate([self.y, other.y]),
            np.concatenate([self.z, other.z]),
            np.concatenate([self.colour, other.colour]),
        )


@dataclass(frozen=True)
class Rendering:
    """One rendered view: colour, per-pixel depth (inf where empty) and splat weight."""

    colour: np.ndarray  # (H, W, 3) float32 RGB 0..255
    depth: np.ndarray  # (H, W) float32
    weight: np.ndarray  # (H, W) float32, 0 where no point landed

    @property
    def covered(self) -> np.ndarray:
        return self.weight > MIN_SPLAT_WEIGHT


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """Pixels on depth discontinuities, by the paper's Laplacian test on normalised disparity."""
    disparity = 1.0 / depth
    normalised = (disparity / disparity.max()).astype(np.float32)
    laplacian = cv2.Laplacian(normalised, cv2.CV_32F, ksize=1)
    return np.abs(laplacian) >= paper.DEPTH_EDGE_LAPLACIAN


def back_project(
    colour: np.ndarray,
    depth: np.ndarray,
    view: View,
    keep: np.ndarray | None = None,
) -> PointCloud:
    """Points seen by a view: each pixel centre pushed out to its depth.

    colour and depth must have the view's size; keep selects which pixels become points.
    """
    height, width = depth.shape
    if (width, height) != (view.width_px, view.height_px):
        raise ValueError("depth does not match the view size")
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    if keep is None:
        keep = np.isfinite(depth)
    z = depth[keep].astype(np.float32)
    x = (cols[keep] + 0.5 - view.principal_x_px) * z / view.focal_px + view.position[0]
    y = (rows[keep] + 0.5 - view.principal_y_px) * z / view.focal_px + view.position[1]
    return PointCloud(
        np.ascontiguousarray(x, dtype=np.float32),
        np.ascontiguousarray(y, dtype=np.float32),
        np.ascontiguousarray(z + view.position[2], dtype=np.float32),
        np.ascontiguousarray(colour[keep], dtype=np.uint8),
    )


def render(cloud: PointCloud, view: View, disparity_scale: float) -> Rendering:
    """Render a view: z-buffer, crack filter, soft-z bilinear splat, normalise.

    disparity_scale converts inverse depth into working disparity pixels (f * baseline), so
    the tolerances mean the same at every output size.
    """
    # Interleaved (red, green, blue, weight): each splat touches one 16-byte cell; the nearest
    # surface's inverse depth lives in its own compact array for the z pass.
    buffer = np.zeros((view.height_px, view.width_px, 4), np.float32)
    front = np.zeros((view.height_px, view.width_px), np.float32)
    _render_kernel(
        cloud.x, cloud.y, cloud.z, cloud.colour,
        float(view.position[0]), float(view.position[1]), float(view.position[2]),
        float(view.focal_px), float(view.principal_x_px), float(view.principal_y_px),
        np.float32(SOFT_Z_DISPARITY_PX / disparity_scale),
        np.float32(CRACK_DISPARITY_PX / disparity_scale),
        buffer, front,
    )  # fmt: skip
    weight = buffer[..., _WEIGHT]
    with np.errstate(divide="ignore"):
        depth = np.where(weight > 0, 1.0 / front, np.inf).astype(np.float32)
    return Rendering(buffer[..., 0:3], depth, weight)


_WEIGHT = 3


@numba.njit(cache=True, nogil=True, inline="always")
def _project(x, y, z, cam_x, cam_y, cam_z, focal, ppx, ppy):
    depth = z - cam_z
    if depth <= NEAR_PLANE:
        return False, 0.0, 0.0, 0.0
    inv_z = 1.0 / depth
    return (
        True,
        focal * (x - cam_x) * inv_z + ppx - 0.5,
        focal * (y - cam_y) * inv_z + ppy - 0.5,
        inv_z,
    )


@numba.njit(cache=True, nogil=True, inline="always")
def _claim(front, yy, xx, w, inv_z):
    if w > MIN_SPLAT_WEIGHT and inv_z > front[yy, xx]:
        front[yy, xx] = inv_z


@numba.njit(cache=True, nogil=True, inline="always")
def _splat(buffer, front, yy, xx, w, inv_z, r, g, b, soft_inv_z):
    if w > MIN_SPLAT_WEIGHT and inv_z >= front[yy, xx] - soft_inv_z:
        buffer[yy, xx, 0] += w * r
        buffer[yy, xx, 1] += w * g
        buffer[yy, xx, 2] += w * b
        buffer[yy, xx, _WEIGHT] += w


@numba.njit(cache=True, nogil=True)
def _render_kernel(
    xs, ys, zs, colours, cam_x, cam_y, cam_z, focal, ppx, ppy, soft_inv_z, crack_inv_z, buffer,
    front,
):
    height, width = buffer.shape[0], buffer.shape[1]
    n = zs.shape[0]
    # Pass 1: the nearest surface (largest inverse depth) per pixel, over each point's four
    # bilinear pixels.
    for i in range(n):
        visible, px, py, inv_z = _project(xs[i], ys[i], zs[i], cam_x, cam_y, cam_z, focal, ppx, ppy)
        if not visible or px <= -1.0 or py <= -1.0 or px >= width or py >= height:
            continue
        x0 = int(math.floor(px))
        y0 = int(math.floor(py))
        fx = px - x0
        fy = py - y0
        if 0 <= x0 < width - 1 and 0 <= y0 < height - 1:
            _claim(front, y0, x0, (1 - fx) * (1 - fy), inv_z)
            _claim(front, y0, x0 + 1, fx * (1 - fy), inv_z)
            _claim(front, y0 + 1, x0, (1 - fx) * fy, inv_z)
            _claim(front, y0 + 1, x0 + 1, fx * fy, inv_z)
        else:
            for dy in range(2):
                for dx in range(2):
                    yy, xx = y0 + dy, x0 + dx
                    if 0 <= yy < height and 0 <= xx < width:
                        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                        _claim(front, yy, xx, w, inv_z)
    # Pass 2: close cracks where background shines through a magnified foreground.
    _filter_cracks(front, crack_inv_z)
    # Pass 3: splat every point that lies on the front surface, weighted bilinearly.
    for i in range(n):
        visible, px, py, inv_z = _project(xs[i], ys[i], zs[i], cam_x, cam_y, cam_z, focal, ppx, ppy)
        if not visible or px <= -1.0 or py <= -1.0 or px >= width or py >= height:
            continue
        x0 = int(math.floor(px))
        y0 = int(math.floor(py))
        fx = px - x0
        fy = py - y0
        r = np.float32(colours[i, 0])
        g = np.float32(colours[i, 1])
        b = np.float32(colours[i, 2])
        if 0 <= x0 < width - 1 and 0 <= y0 < height - 1:
            _splat(buffer, front, y0, x0, (1 - fx) * (1 - fy), inv_z, r, g, b, soft_inv_z)
            _splat(buffer, front, y0, x0 + 1, fx * (1 - fy), inv_z, r, g, b, soft_inv_z)
            _splat(buffer, front, y0 + 1, x0, (1 - fx) * fy, inv_z, r, g, b, soft_inv_z)
            _splat(buffer, front, y0 + 1, x0 + 1, fx * fy, inv_z, r, g, b, soft_inv_z)
        else:
            for dy in range(2):
                for dx in range(2):
                    yy, xx = y0 + dy, x0 + dx
                    if 0 <= yy < height and 0 <= xx < width:
                        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                        _splat(buffer, front, yy, xx, w, inv_z, r, g, b, soft_inv_z)
    for yy in range(height):
        for xx in range(width):
            pixel = buffer[yy, xx]
            w = pixel[_WEIGHT]
            if w > MIN_SPLAT_WEIGHT:
                scale = 1.0 / w
                pixel[0] *= scale
                pixel[1] *= scale
                pixel[2] *= scale
            else:
                pixel[0] = 0.0
                pixel[1] = 0.0
                pixel[2] = 0.0
                pixel[_WEIGHT] = 0.0


@numba.njit(cache=True, nogil=True)
def _filter_cracks(front, crack_inv_z):
    """Give a pixel the average inverse depth of two opposite neighbours that are clearly nearer."""
    height, width = front.shape
    source = front.copy()
    for yy in range(1, height - 1):
        above = source[yy - 1]
        row = source[yy]
        below = source[yy + 1]
        for xx in range(1, width - 1):
            threshold = row[xx] + crack_inv_z
            # Opposite neighbour pairs: horizontal, vertical and both diagonals.
            if row[xx - 1] > threshold and row[xx + 1] > threshold:
                front[yy, xx] = 0.5 * (row[xx - 1] + row[xx + 1])
            elif above[xx] > threshold and below[xx] > threshold:
                front[yy, xx] = 0.5 * (above[xx] + below[xx])
            elif above[xx - 1] > threshold and below[xx + 1] > threshold:
                front[yy, xx] = 0.5 * (above[xx - 1] + below[xx + 1])
            elif above[xx + 1] > threshold and below[xx - 1] > threshold:
                front[yy, xx] = 0.5 * (above[xx + 1] + below[xx - 1])


def fill_from_background(rendering: Rendering) -> np.ndarray:
    """Colour every empty pixel from the farthest covered pixel found along its row and column.

    A cheap, deterministic fill for the few pixels that stay uncovered after the cloud has been
    extended; taking the farthest candidate keeps foreground colour from bleeding into holes.
    """
    colour = rendering.colour.copy()
    _fill_holes_kernel(colour, rendering.depth, rendering.weight > MIN_SPLAT_WEIGHT)
    return colour


@numba.njit(cache=True, nogil=True)
def _fill_holes_kernel(colour, depth, covered):
    height, width = covered.shape
    source = colour.copy()
    for yy in range(height):
        for xx in range(width):
            if covered[yy, xx]:
                continue
            best_depth = -1.0
            best_y = -1
            best_x = -1
            # Nearest covered pixel in each of the four directions; keep the farthest one.
            for step_y, step_x in ((0, -1), (0, 1), (-1, 0), (1, 0)):
                cy = yy + step_y
                cx = xx + step_x
                while 0 <= cy < height and 0 <= cx < width and not covered[cy, cx]:
                    cy += step_y
                    cx += step_x
                if 0 <= cy < height and 0 <= cx < width and depth[cy, cx] > best_depth:
                    best_depth = depth[cy, cx]
                    best_y = cy
                    best_x = cx
            if best_y >= 0:
                colour[yy, xx, 0] = source[best_y, best_x, 0]
                colour[yy, xx, 1] = source[best_y, best_x, 1]
                colour[yy, xx, 2] = source[best_y, best_x, 2]


def to_uint8(colour: np.ndarray) -> np.ndarray:
    """Round a float colour image to 8 bits."""
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8)
