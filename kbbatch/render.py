"""Point cloud from image + depth, and its forward-projection renderer (paper section 3.2).

The kernels are compiled with numba and release the GIL, so frames render in parallel threads
(one frame per thread keeps every frame bit-identical whatever the thread count).
"""

from __future__ import annotations

import threading
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
    if keep is None:
        keep = np.isfinite(depth)
    rows, cols = np.nonzero(keep)
    z = depth[rows, cols].astype(np.float32)
    scale = z / np.float32(view.focal_px)
    x = (cols.astype(np.float32) + np.float32(0.5 - view.principal_x_px)) * scale
    y = (rows.astype(np.float32) + np.float32(0.5 - view.principal_y_px)) * scale
    return PointCloud(
        np.ascontiguousarray(x + np.float32(view.position[0]), dtype=np.float32),
        np.ascontiguousarray(y + np.float32(view.position[1]), dtype=np.float32),
        np.ascontiguousarray(z + np.float32(view.position[2]), dtype=np.float32),
        np.ascontiguousarray(colour[rows, cols], dtype=np.uint8),
    )


_WEIGHT = 3
_buffers = threading.local()


def _scratch(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-thread accumulation buffers, reused across frames (no page faults per frame)."""
    key = (height, width)
    if getattr(_buffers, "key", None) != key:
        _buffers.key = key
        _buffers.accumulator = np.zeros((height, width, 4), np.float32)
        _buffers.front = np.empty((height, width), np.float32)
    return _buffers.accumulator, _buffers.front


def _splat_view(
    cloud: PointCloud,
    view: View,
    disparity_scale: float,
    accumulator: np.ndarray,
    front: np.ndarray,
    clear: bool = True,
) -> None:
    _splat_kernel(
        cloud.x, cloud.y, cloud.z, cloud.colour,
        np.float32(view.position[0]), np.float32(view.position[1]),
        np.float32(view.position[2]), np.float32(view.focal_px),
        np.float32(view.principal_x_px - 0.5), np.float32(view.principal_y_px - 0.5),
        np.float32(SOFT_Z_DISPARITY_PX / disparity_scale),
        np.float32(CRACK_DISPARITY_PX / disparity_scale),
        accumulator, front, clear,
    )


def render(cloud: PointCloud, view: View, disparity_scale: float) -> Rendering:
    """Render a view: z-buffer, crack filter, soft-z bilinear splat, normalise.

    disparity_scale converts inverse depth into working disparity pixels (f * baseline), so
    the tolerances mean the same at every output size.
    """
    # Interleaved (red, green, blue, weight): each splat touches one 16-byte cell; the nearest
    # surface's inverse depth lives in its own compact array for the z pass.
    accumulator = np.empty((view.height_px, view.width_px, 4), np.float32)
    front = np.empty((view.height_px, view.width_px), np.float32)
    _splat_view(cloud, view, disparity_scale, accumulator, front)
    colour = np.empty((view.height_px, view.width_px, 3), np.float32)
    depth = np.empty((view.height_px, view.width_px), np.float32)
    weight = np.empty((view.height_px, view.width_px), np.float32)
    _normalise_kernel(accumulator, front, colour, depth, weight)
    return Rendering(colour, depth, weight)


@numba.njit(cache=True, nogil=True)
def _normalise_kernel(accumulator, front, colour, depth, weight):
    height, width = front.shape
    for yy in range(height):
        for xx in range(width):
            w = accumulator[yy, xx, _WEIGHT]
            if w > MIN_SPLAT_WEIGHT:
                scale = np.float32(1.0) / w
                for c in range(3):
                    colour[yy, xx, c] = accumulator[yy, xx, c] * scale
                depth[yy, xx] = np.float32(1.0) / front[yy, xx]
                weight[yy, xx] = w
            else:
                for c in range(3):
                    colour[yy, xx, c] = 0.0
                depth[yy, xx] = np.inf
                weight[yy, xx] = 0.0


def coverage(cloud: PointCloud, view: View, disparity_scale: float) -> np.ndarray:
    """Which pixels of a view the cloud covers (the planner's disocclusion test)."""
    accumulator = np.empty((view.height_px, view.width_px, 4), np.float32)
    front = np.empty((view.height_px, view.width_px), np.float32)
    _splat_view(cloud, view, disparity_scale, accumulator, front)
    return accumulator[..., _WEIGHT] > MIN_SPLAT_WEIGHT


def render_frame(cloud: PointCloud, view: View, disparity_scale: float) -> np.ndarray:
    """A finished 8-bit frame: rendered, holes filled from the background side, rounded.

    The same passes as render(), with normalising, filling and rounding fused into one.
    """
    accumulator, front = _scratch(view.height_px, view.width_px)
    _splat_view(cloud, view, disparity_scale, accumulator, front, clear=False)
    frame = np.empty((view.height_px, view.width_px, 3), np.uint8)
    _finish_kernel(accumulator, front, frame)
    return frame


PROJECT_CHUNK = 1024
"""Points projected together in one vectorised loop before they are splatted one by one; small
enough that the projections stay in the L1 cache between the two loops."""

_OUTSIDE = -2  # column marking a point that no pixel of the view receives


@numba.njit(cache=True, nogil=True)
def _project_chunk(
    xs, ys, zs, start, cam_x, cam_y, cam_z, focal, ppx, ppy, width, height,
    cols, rows, frac_x, frac_y, inv_zs,
):
    """Bilinear footprints of points start.. (top-left pixel, fractions, inverse depth).

    Branch-free so that it compiles to SIMD: points behind the camera or off the view get
    column _OUTSIDE instead of an early exit.
    """
    one = np.float32(1.0)
    near = np.float32(NEAR_PLANE)
    right = np.float32(width)
    bottom = np.float32(height)
    for j in range(min(cols.shape[0], zs.shape[0] - start)):
        i = start + j
        depth = zs[i] - cam_z
        inv_z = one / max(depth, near)
        px = focal * (xs[i] - cam_x) * inv_z + ppx
        py = focal * (ys[i] - cam_y) * inv_z + ppy
        visible = depth > near and px > -one and py > -one and px < right and py < bottom
        px = min(max(px, -one), right)
        py = min(max(py, -one), bottom)
        x_floor = np.floor(px)
        y_floor = np.floor(py)
        cols[j] = np.int32(x_floor) if visible else np.int32(_OUTSIDE)
        rows[j] = np.int32(y_floor)
        frac_x[j] = px - x_floor
        frac_y[j] = py - y_floor
        inv_zs[j] = inv_z


@numba.njit(cache=True, nogil=True)
def _corner(k, x0, y0, fx, fy, width, height):
    """Corner k (0..3) of a bilinear footprint: whether it is in the frame, where, its weight."""
    one = np.float32(1.0)
    dx = k & 1
    dy = k >> 1
    inside = 0 <= y0 + dy < height and 0 <= x0 + dx < width
    return inside, y0 + dy, x0 + dx, (fx if dx else one - fx) * (fy if dy else one - fy)


@numba.njit(cache=True, nogil=True)
def _splat_kernel(
    xs, ys, zs, colours, cam_x, cam_y, cam_z, focal, ppx, ppy, soft_inv_z, crack_inv_z,
    accumulator, front, clear,
):
    # The per-pixel work is written out by hand on purpose: helpers taking the buffers, and
    # float64 promotion, made this loop two to three times slower; one loop shared by both
    # passes behind a flag measured 13% slower than the two below. All arithmetic is float32.
    height, width = front.shape
    one = np.float32(1.0)
    min_weight = np.float32(MIN_SPLAT_WEIGHT)
    if clear:  # render_frame's finishing pass leaves its buffer cleared for the next frame
        accumulator[:] = 0.0
    front[:] = 0.0
    cols = np.empty(PROJECT_CHUNK, np.int32)
    rows = np.empty(PROJECT_CHUNK, np.int32)
    frac_x = np.empty(PROJECT_CHUNK, np.float32)
    frac_y = np.empty(PROJECT_CHUNK, np.float32)
    inv_zs = np.empty(PROJECT_CHUNK, np.float32)
    count = zs.shape[0]
    # Pass 1: the nearest surface (largest inverse depth) per pixel, over each point's four
    # bilinear pixels.
    for start in range(0, count, PROJECT_CHUNK):
        _project_chunk(
            xs, ys, zs, start, cam_x, cam_y, cam_z, focal, ppx, ppy, width, height,
            cols, rows, frac_x, frac_y, inv_zs,
        )
        for j in range(min(PROJECT_CHUNK, count - start)):
            x0 = cols[j]
            if x0 == _OUTSIDE:
                continue
            y0 = rows[j]
            fx = frac_x[j]
            fy = frac_y[j]
            inv_z = inv_zs[j]
            if x0 >= 0 and y0 >= 0 and x0 < width - 1 and y0 < height - 1:
                # Interior: all four pixels exist (the common case, unrolled).
                if (one - fx) * (one - fy) > min_weight and inv_z > front[y0, x0]:
                    front[y0, x0] = inv_z
                if fx * (one - fy) > min_weight and inv_z > front[y0, x0 + 1]:
                    front[y0, x0 + 1] = inv_z
                if (one - fx) * fy > min_weight and inv_z > front[y0 + 1, x0]:
                    front[y0 + 1, x0] = inv_z
                if fx * fy > min_weight and inv_z > front[y0 + 1, x0 + 1]:
                    front[y0 + 1, x0 + 1] = inv_z
                continue
            for k in range(4):  # at the frame's edge: only the corners inside
                inside, yy, xx, w = _corner(k, x0, y0, fx, fy, width, height)
                if inside and w > min_weight and inv_z > front[yy, xx]:
                    front[yy, xx] = inv_z
    # Pass 2: close cracks where background shines through a magnified foreground.
    _filter_cracks(front, crack_inv_z)
    # Pass 3: splat every point that lies on the front surface, weighted bilinearly.
    for start in range(0, count, PROJECT_CHUNK):
        _project_chunk(
            xs, ys, zs, start, cam_x, cam_y, cam_z, focal, ppx, ppy, width, height,
            cols, rows, frac_x, frac_y, inv_zs,
        )
        for j in range(min(PROJECT_CHUNK, count - start)):
            x0 = cols[j]
            if x0 == _OUTSIDE:
                continue
            y0 = rows[j]
            fx = frac_x[j]
            fy = frac_y[j]
            i = start + j
            r = np.float32(colours[i, 0])
            g = np.float32(colours[i, 1])
            b = np.float32(colours[i, 2])
            lowest = inv_zs[j] + soft_inv_z  # a pixel's front may be at most this near
            if x0 >= 0 and y0 >= 0 and x0 < width - 1 and y0 < height - 1:
                # Interior: all four pixels exist (the common case, unrolled).
                w00 = (one - fx) * (one - fy)
                w01 = fx * (one - fy)
                w10 = (one - fx) * fy
                w11 = fx * fy
                if w00 > min_weight and front[y0, x0] <= lowest:
                    cell = accumulator[y0, x0]
                    cell[0] += w00 * r
                    cell[1] += w00 * g
                    cell[2] += w00 * b
                    cell[3] += w00
                if w01 > min_weight and front[y0, x0 + 1] <= lowest:
                    cell = accumulator[y0, x0 + 1]
                    cell[0] += w01 * r
                    cell[1] += w01 * g
                    cell[2] += w01 * b
                    cell[3] += w01
                if w10 > min_weight and front[y0 + 1, x0] <= lowest:
                    cell = accumulator[y0 + 1, x0]
                    cell[0] += w10 * r
                    cell[1] += w10 * g
                    cell[2] += w10 * b
                    cell[3] += w10
                if w11 > min_weight and front[y0 + 1, x0 + 1] <= lowest:
                    cell = accumulator[y0 + 1, x0 + 1]
                    cell[0] += w11 * r
                    cell[1] += w11 * g
                    cell[2] += w11 * b
                    cell[3] += w11
                continue
            for k in range(4):  # at the frame's edge: only the corners inside
                inside, yy, xx, w = _corner(k, x0, y0, fx, fy, width, height)
                if inside and w > min_weight and front[yy, xx] <= lowest:
                    cell = accumulator[yy, xx]
                    cell[0] += w * r
                    cell[1] += w * g
                    cell[2] += w * b
                    cell[_WEIGHT] += w


@numba.njit(cache=True, nogil=True)
def _filter_cracks(front, crack_inv_z):
    """Give a pixel the average inverse depth of two opposite neighbours that are clearly nearer."""
    height, width = front.shape
    # Only the unfiltered row above and the current row are kept: the row below is untouched yet.
    above = front[0].copy()
    row = np.empty_like(above)
    for yy in range(1, height - 1):
        row[:] = front[yy]
        below = front[yy + 1]
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
        above, row = row, above


@numba.njit(cache=True, nogil=True)
def _finish_kernel(accumulator, front, frame):
    """Normalise, round, and give every empty pixel the colour of the farthest covered pixel
    found along its row and column (a cheap fill from the background side). Leaves the
    accumulator cleared for the next frame; front keeps 0 where a pixel was empty."""
    height, width = front.shape
    empty = 0
    for yy in range(height):
        for xx in range(width):
            cell = accumulator[yy, xx]
            w = cell[_WEIGHT]
            if w > MIN_SPLAT_WEIGHT:
                scale = np.float32(1.0) / w
                for c in range(3):
                    frame[yy, xx, c] = min(255, int(cell[c] * scale + np.float32(0.5)))
            else:
                front[yy, xx] = 0.0
                empty += 1
            for c in range(4):
                cell[c] = 0.0
    if empty == 0:
        return
    for yy in range(height):
        for xx in range(width):
            if front[yy, xx] > 0:
                continue
            best_inv = np.float32(np.inf)
            best_y = -1
            best_x = -1
            for step_y, step_x in ((0, -1), (0, 1), (-1, 0), (1, 0)):
                cy = yy + step_y
                cx = xx + step_x
                while 0 <= cy < height and 0 <= cx < width and front[cy, cx] == 0:
                    cy += step_y
                    cx += step_x
                if 0 <= cy < height and 0 <= cx < width and front[cy, cx] < best_inv:
                    best_inv = front[cy, cx]
                    best_y = cy
                    best_x = cx
            for c in range(3):
                frame[yy, xx, c] = frame[best_y, best_x, c] if best_y >= 0 else 0


def to_uint8(colour: np.ndarray) -> np.ndarray:
    """Round a float colour image to 8 bits."""
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8)
