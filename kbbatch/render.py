"""Point cloud from image + depth, and its forward-projection renderer (paper section 3.2).

Points carry an alpha: the soft edge of a foreground layer (kbbatch.layers) is drawn with
premultiplied alpha over the surface behind it. Each pixel keeps two surfaces, the front one
and the nearest one behind it, so a soft edge is composited over what really lies behind it
wherever the camera moves, instead of dragging its old background along.

The kernels are compiled with numba and release the GIL, so frames render in parallel threads
(one frame per thread keeps every frame bit-identical whatever the thread count).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

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
through a crack in a magnified foreground (the paper's z-buffer filter): it is emptied."""

FILL_CRACK_PX = 2
"""An empty pixel with covered pixels this close on both sides of its row or column is a crack
in one surface (a magnified slanted ground spreads its rows apart) and takes its colour from
those sides; the long walk to the farthest covered pixel could fetch the sky into the ground."""

MIN_SPLAT_WEIGHT = 1e-3
"""Bilinear weights below this neither raise the z-buffer nor colour a pixel."""

NEAR_PLANE = 1e-3
"""Points closer to the camera than this (working units) are behind it and skipped."""


@dataclass(frozen=True)
class PointCloud:
    """Coloured 3D points in working units (camera at the origin for the input photo)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    colour: np.ndarray  # (N, 3) uint8 RGB
    alpha: np.ndarray | None = None
    """(N,) uint8 coverage of each point, 255 = opaque (the default); below 255 only on the
    soft edge of a foreground layer, whose colour is then its own, un-mixed. The opaque
    points come first (the cloud is reordered so): opaque_count of them."""
    opaque_count: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        if self.alpha is None:
            object.__setattr__(self, "alpha", np.full(self.z.shape[0], 255, np.uint8))
        soft = self.alpha < 255
        opaque_count = len(self) - int(soft.sum())
        if soft[:opaque_count].any():  # opaque points first: the renderer splats them first
            order = np.concatenate([np.flatnonzero(~soft), np.flatnonzero(soft)])
            for name in ("x", "y", "z", "colour", "alpha"):
                object.__setattr__(self, name, np.ascontiguousarray(getattr(self, name)[order]))
        object.__setattr__(self, "opaque_count", opaque_count)

    def __len__(self) -> int:
        return int(self.z.shape[0])

    def extended(self, other: PointCloud) -> PointCloud:
        """Both clouds' points, opaque ones first (joined in that order directly: joining, then
        reordering, copied every point of a large cloud twice)."""
        def joined(name: str) -> np.ndarray:
            mine, theirs = getattr(self, name), getattr(other, name)
            return np.concatenate([mine[:self.opaque_count], theirs[:other.opaque_count],
                                   mine[self.opaque_count:], theirs[other.opaque_count:]])

        return PointCloud(*(joined(name) for name in ("x", "y", "z", "colour", "alpha")))


@dataclass(frozen=True)
class Rendering:
    """One rendered view: colour, per-pixel depth (inf where empty) and splat weight.

    Where a soft edge of alpha below one half lies over a surface, depth is that surface's."""

    colour: np.ndarray  # (H, W, 3) float32 RGB 0..255
    depth: np.ndarray  # (H, W) float32
    weight: np.ndarray  # (H, W) float32, 0 where no point landed
    fringe: np.ndarray | None = None
    """(H, W) bool: the front is a layer's soft edge, its colour a mix of two surfaces."""

    @property
    def covered(self) -> np.ndarray:
        return self.weight > MIN_SPLAT_WEIGHT


def depth_edges(depth: np.ndarray, relief: float = 1.0) -> np.ndarray:
    """Pixels on depth discontinuities, by the paper's Laplacian test on normalised disparity.

    relief: the factor kbbatch.risk.relieved scaled depth's relief by. The Laplacian scales
    with it, and so does the test, so a relieved depth has the photo's edges: at a quarter of
    the relief a lantern's step fell just under the test, which caught only the corners of its
    stairs, and the soft layers split it in blobs that showed as blocks in its glow."""
    if relief <= 0.0:  # flat: no edge
        return np.zeros(depth.shape, bool)
    disparity = 1.0 / depth
    normalised = (disparity / disparity.max()).astype(np.float32)
    laplacian = cv2.Laplacian(normalised, cv2.CV_32F, ksize=1)
    return np.abs(laplacian) >= paper.DEPTH_EDGE_LAPLACIAN * relief


def back_project(
    colour: np.ndarray,
    depth: np.ndarray,
    view: View,
    keep: np.ndarray | None = None,
    alpha: np.ndarray | None = None,
) -> PointCloud:
    """Points seen by a view: each pixel centre pushed out to its depth.

    colour and depth (and alpha, uint8, when given) must have the view's size; keep selects
    which pixels become points.
    """
    height, width = depth.shape
    if (width, height) != (view.width_px, view.height_px):
        raise ValueError("depth does not match the view size")
    if keep is None:
        keep = np.isfinite(depth)
    rows, cols = np.nonzero(keep)
    return points_at(view, rows, cols, depth[rows, cols], colour[rows, cols],
                     None if alpha is None else alpha[rows, cols])


def points_at(view: View, rows: np.ndarray, cols: np.ndarray, depth: np.ndarray,
              colour: np.ndarray, alpha: np.ndarray | None = None) -> PointCloud:
    """Points at the centres of some pixels of a view (rows, cols), at their depths, with
    their colours (and alpha)."""
    z = depth.astype(np.float32)
    scale = z / np.float32(view.focal_px)
    x = (cols.astype(np.float32) + np.float32(0.5 - view.principal_x_px)) * scale
    y = (rows.astype(np.float32) + np.float32(0.5 - view.principal_y_px)) * scale
    return PointCloud(
        np.ascontiguousarray(x + np.float32(view.position[0]), dtype=np.float32),
        np.ascontiguousarray(y + np.float32(view.position[1]), dtype=np.float32),
        np.ascontiguousarray(z + np.float32(view.position[2]), dtype=np.float32),
        np.ascontiguousarray(colour, dtype=np.uint8),
        None if alpha is None else np.ascontiguousarray(alpha, dtype=np.uint8),
    )


_WEIGHT = 3  # a cell holds red, green, blue weighted by weight x alpha, then the weight
_ON_OPAQUE = -1.0
"""back_cell's weight where a soft front, with no surface behind it, blends into an opaque
one at its own depth (the inner side of an object's soft edge)."""
OPAQUE_ALPHA = 0.99
"""A pixel whose front surface has at least this alpha hides whatever lies behind it."""


@dataclass(frozen=True)
class SplatBuffers:
    """Per-pixel accumulation: the front surface, and behind soft edges the surface behind.

    cell: the front's colour weighted by bilinear weight x alpha, and its summed weight (its
    coverage); front: its inverse depth (0: none). Where a soft point touched a pixel in the
    frame numbered stamp: clear, the summed weight x (1 - alpha) of the front (its alpha is
    1 - clear / weight), and back / back_cell, the nearest surface behind it as the front's.
    Opaque points only touch cell and front, as a plain z-buffer does: the soft state is
    written by the few soft points alone, and the stamp says which pixels it is valid for.
    """

    cell: np.ndarray  # (H, W, 4) float32
    front: np.ndarray  # (H, W) float32
    stamp: np.ndarray  # (H, W) int32
    clear: np.ndarray  # (H, W) float32
    back: np.ndarray  # (H, W) float32
    back_cell: np.ndarray  # (H, W, 4) float32

    @classmethod
    def empty(cls, height: int, width: int) -> SplatBuffers:
        return cls(
            np.zeros((height, width, 4), np.float32),
            np.zeros((height, width), np.float32),
            np.zeros((height, width), np.int32),
            np.zeros((height, width), np.float32),
            np.zeros((height, width), np.float32),
            np.zeros((height, width, 4), np.float32),
        )

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.cell, self.front, self.stamp, self.clear, self.back, self.back_cell


_buffers = threading.local()


def _scratch(height: int, width: int) -> tuple[SplatBuffers, int]:
    """Per-thread accumulation buffers, reused across frames (no page faults per frame, also
    when frames of a clip are rendered at several sizes: views of the first pixels of buffers
    as large as the largest frame yet), and the number of this frame in them. The number only
    grows, so no stamp left by an earlier frame, of any size, matches it."""
    if getattr(_buffers, "capacity", 0) < height * width:
        _buffers.capacity = height * width
        _buffers.flat = SplatBuffers.empty(1, height * width)
        _buffers.frame = getattr(_buffers, "frame", 0)
    _buffers.frame = _buffers.frame % 2_000_000_000 + 1
    pixels = height * width
    splats = SplatBuffers(*(
        array.reshape(-1, *array.shape[2:])[:pixels].reshape(height, width, *array.shape[2:])
        for array in _buffers.flat.arrays()))
    return splats, _buffers.frame


def _splat_view(cloud: PointCloud, view: View, disparity_scale: float,
                buffers: SplatBuffers, frame: int) -> np.ndarray:
    """Splat a view; returns the flat indices of the pixels that soft points touched."""
    touched = np.empty(4 * (len(cloud) - cloud.opaque_count), np.int64)
    count = _splat_kernel(
        cloud.x, cloud.y, cloud.z, cloud.colour, cloud.alpha, cloud.opaque_count,
        np.float32(view.position[0]), np.float32(view.position[1]),
        np.float32(view.position[2]), np.float32(view.focal_px),
        np.float32(view.principal_x_px - 0.5), np.float32(view.principal_y_px - 0.5),
        np.float32(SOFT_Z_DISPARITY_PX / disparity_scale),
        np.float32(CRACK_DISPARITY_PX / disparity_scale),
        *buffers.arrays(), np.int32(frame), touched,
    )
    return touched[:count]


def render(cloud: PointCloud, view: View, disparity_scale: float) -> Rendering:
    """Render a view: soft z-buffered bilinear splats, crack filter, composite, normalise.

    disparity_scale converts inverse depth into working disparity pixels (f * baseline), so
    the tolerances mean the same at every output size. A pixel counts as covered (weight > 0)
    when its front surface is opaque or has a surface behind it; a soft edge over nothing is
    a hole still to fill where its alpha is under one half. (render_frame, finishing a frame,
    composites every soft edge over nothing over its fill, except one blended into an opaque
    surface at its own depth.)
    """
    buffers = SplatBuffers.empty(view.height_px, view.width_px)
    _splat_view(cloud, view, disparity_scale, buffers, 1)
    colour = np.empty((view.height_px, view.width_px, 3), np.float32)
    depth = np.empty((view.height_px, view.width_px), np.float32)
    weight = np.empty((view.height_px, view.width_px), np.float32)
    _normalise_kernel(*buffers.arrays(), np.int32(1), colour, depth, weight)
    fringe = (buffers.stamp == 1) & (buffers.clear > 0) & (buffers.front > 0)
    return Rendering(colour, depth, weight, fringe)


@numba.njit(cache=True, nogil=True, inline="always")
def _composite(cell, stamp, clear, back, back_cell, frame, yy, xx, out):
    """Pixel (yy, xx): the front over the back with premultiplied alpha; a soft front with
    nothing behind it keeps its own colour. Returns whether the pixel is covered."""
    weight = cell[yy, xx, _WEIGHT]
    if stamp[yy, xx] != frame or clear[yy, xx] <= 0:  # opaque: the plain z-buffer's case
        scale = np.float32(1.0) / weight
        for c in range(3):
            out[c] = cell[yy, xx, c] * scale
        return True
    alpha_sum = max(weight - clear[yy, xx], np.float32(0.0))
    alpha = alpha_sum / weight
    if back[yy, xx] > 0 and alpha < np.float32(OPAQUE_ALPHA):
        back_scale = (np.float32(1.0) - alpha) / back_cell[yy, xx, _WEIGHT]
        front_scale = np.float32(1.0) / weight
        for c in range(3):
            out[c] = cell[yy, xx, c] * front_scale + back_cell[yy, xx, c] * back_scale
        return True
    scale = np.float32(1.0) / max(alpha_sum, np.float32(MIN_SPLAT_WEIGHT * MIN_SPLAT_WEIGHT))
    for c in range(3):
        out[c] = cell[yy, xx, c] * scale
    return alpha >= np.float32(0.5)  # a fringe mostly over nothing is a hole to fill


@numba.njit(cache=True, nogil=True)
def _normalise_kernel(cell, front, stamp, clear, back, back_cell, frame, colour, depth,
                      weight):
    height, width = front.shape
    pixel = np.empty(3, np.float32)
    one = np.float32(1.0)
    for yy in range(height):
        for xx in range(width):
            surface = front[yy, xx]
            if surface > 0 and (stamp[yy, xx] != frame or clear[yy, xx] <= 0):
                # opaque, the common case, written out (through _composite: four times slower)
                total = cell[yy, xx, _WEIGHT]
                scale = one / total
                for c in range(3):
                    colour[yy, xx, c] = cell[yy, xx, c] * scale
                depth[yy, xx] = one / surface
                weight[yy, xx] = total
                continue
            covered = False
            if surface > 0:
                covered = _composite(cell, stamp, clear, back, back_cell, frame, yy, xx, pixel)
                for c in range(3):
                    colour[yy, xx, c] = pixel[c]
                surface = front[yy, xx]
                if (stamp[yy, xx] == frame and back[yy, xx] > 0
                        and clear[yy, xx] > np.float32(0.5) * cell[yy, xx, _WEIGHT]):
                    surface = back[yy, xx]  # a faint fringe: the depth is the one behind
                depth[yy, xx] = np.float32(1.0) / surface
            else:
                for c in range(3):
                    colour[yy, xx, c] = 0.0
                depth[yy, xx] = np.inf
            weight[yy, xx] = cell[yy, xx, _WEIGHT] if covered else np.float32(0.0)


def coverage(cloud: PointCloud, view: View, disparity_scale: float) -> np.ndarray:
    """Which pixels of a view the cloud covers (the planner's disocclusion test).

    Without soft points a pixel is covered exactly when a surface survived the crack filter,
    so the compositing pass, most of the cost at the planner's size, is skipped."""
    if cloud.opaque_count < len(cloud):
        return render(cloud, view, disparity_scale).covered
    buffers = SplatBuffers.empty(view.height_px, view.width_px)
    _splat_view(cloud, view, disparity_scale, buffers, 1)
    return buffers.front > 0


def render_frame(cloud: PointCloud, view: View, disparity_scale: float) -> np.ndarray:
    """A finished 8-bit frame: rendered, holes filled from the background side, rounded.

    The same passes as render(), with compositing, filling and rounding fused into one.
    """
    buffers, number = _scratch(view.height_px, view.width_px)
    touched = _splat_view(cloud, view, disparity_scale, buffers, number)
    frame = np.empty((view.height_px, view.width_px, 3), np.uint8)
    _finish_kernel(*buffers.arrays(), np.int32(number), touched, frame)
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
    xs, ys, zs, colours, alphas, opaque_count, cam_x, cam_y, cam_z, focal, ppx, ppy, soft_inv_z,
    crack_inv_z, cell, front, stamp, clear, back, back_cell, frame, touched,
):
    # Opaque points first, in one pass of soft z-buffering exactly as a plain cloud; then the
    # few soft points, which keep what lies behind them; then the crack filter. All
    # arithmetic is float32: float64 promotion made this loop two to three times slower.
    # cell arrives cleared (new, or left so by the finishing pass).
    height, width = front.shape
    one = np.float32(1.0)
    front[:] = 0.0
    cols = np.empty(PROJECT_CHUNK, np.int32)
    rows = np.empty(PROJECT_CHUNK, np.int32)
    frac_x = np.empty(PROJECT_CHUNK, np.float32)
    frac_y = np.empty(PROJECT_CHUNK, np.float32)
    inv_zs = np.empty(PROJECT_CHUNK, np.float32)
    for start in range(0, opaque_count, PROJECT_CHUNK):
        _project_chunk(
            xs, ys, zs, start, cam_x, cam_y, cam_z, focal, ppx, ppy, width, height,
            cols, rows, frac_x, frac_y, inv_zs,
        )
        for j in range(min(PROJECT_CHUNK, opaque_count - start)):
            x0 = cols[j]
            if x0 == _OUTSIDE:
                continue
            y0 = rows[j]
            fx = frac_x[j]
            fy = frac_y[j]
            inv_z = inv_zs[j]
            i = start + j
            r = np.float32(colours[i, 0])
            g = np.float32(colours[i, 1])
            b = np.float32(colours[i, 2])
            if x0 >= 0 and y0 >= 0 and x0 < width - 1 and y0 < height - 1:
                # Interior: all four pixels exist (the common case, unrolled).
                _soft_z(front, cell, y0, x0, (one - fx) * (one - fy), inv_z, soft_inv_z,
                        r, g, b)
                _soft_z(front, cell, y0, x0 + 1, fx * (one - fy), inv_z, soft_inv_z,
                        r, g, b)
                _soft_z(front, cell, y0 + 1, x0, (one - fx) * fy, inv_z, soft_inv_z,
                        r, g, b)
                _soft_z(front, cell, y0 + 1, x0 + 1, fx * fy, inv_z, soft_inv_z, r, g, b)
                continue
            for k in range(4):  # at the frame's edge: only the corners inside
                inside, yy, xx, w = _corner(k, x0, y0, fx, fy, width, height)
                if inside:
                    _soft_z(front, cell, yy, xx, w, inv_z, soft_inv_z, r, g, b)
    to_unit = np.float32(1.0 / 255.0)
    touched_count = 0
    count = zs.shape[0]
    for start in range(opaque_count, count, PROJECT_CHUNK):
        _project_chunk(
            xs, ys, zs, start, cam_x, cam_y, cam_z, focal, ppx, ppy, width, height,
            cols, rows, frac_x, frac_y, inv_zs,
        )
        for j in range(min(PROJECT_CHUNK, count - start)):
            x0 = cols[j]
            if x0 == _OUTSIDE:
                continue
            i = start + j
            a = np.float32(alphas[i]) * to_unit
            r = np.float32(colours[i, 0])
            g = np.float32(colours[i, 1])
            b = np.float32(colours[i, 2])
            for k in range(4):
                inside, yy, xx, w = _corner(k, x0, rows[j], frac_x[j], frac_y[j], width,
                                            height)
                if inside and w > np.float32(MIN_SPLAT_WEIGHT):
                    if stamp[yy, xx] != frame:
                        stamp[yy, xx] = frame
                        clear[yy, xx] = 0.0
                        back[yy, xx] = 0.0
                        # an opaque surface here already: what this point blends into
                        back_cell[yy, xx, _WEIGHT] = _ON_OPAQUE if front[yy, xx] > 0 else 0.0
                        touched[touched_count] = yy * width + xx
                        touched_count += 1
                    _soft_layer_z(front, cell, clear, back, back_cell, yy, xx, w, inv_zs[j],
                                  soft_inv_z, a, r, g, b)
    _clear_cracks(front, cell, stamp, clear, back, frame, touched[:touched_count], crack_inv_z)
    return touched_count


@numba.njit(cache=True, nogil=True, inline="always")
def _soft_z(front, cell, yy, xx, w, inv_z, soft_inv_z, r, g, b):
    """Splat one bilinear corner of an opaque point with soft z-buffering.

    A point clearly nearer than the pixel's front surface restarts the pixel, one within
    soft_inv_z of it blends in, and a farther one is hidden. The front is raised with max(),
    not a branch: which of two blending points is nearer is a coin toss the CPU mispredicts.
    (Keep front first in the arguments: numba's code for this loop was 50 % slower with the
    two arrays swapped.)
    """
    if w <= np.float32(MIN_SPLAT_WEIGHT):
        return
    surface = front[yy, xx]
    if surface < inv_z - soft_inv_z:
        front[yy, xx] = inv_z
        cell[yy, xx, 0] = w * r
        cell[yy, xx, 1] = w * g
        cell[yy, xx, 2] = w * b
        cell[yy, xx, _WEIGHT] = w
    elif surface <= inv_z + soft_inv_z:
        front[yy, xx] = max(surface, inv_z)
        cell[yy, xx, 0] += w * r
        cell[yy, xx, 1] += w * g
        cell[yy, xx, 2] += w * b
        cell[yy, xx, _WEIGHT] += w


@numba.njit(cache=True, nogil=True, inline="always")
def _soft_layer_z(front, cell, clear, back, back_cell, yy, xx, w, inv_z, soft_inv_z, a, r, g,
                  b):
    """Splat one bilinear corner of a soft point (after every opaque one).

    As _soft_z, but a soft point that starts a new front keeps the old front as the pixel's
    back, and while the front is soft, farther soft points go the same way into the back.
    """
    wa = w * a
    surface = front[yy, xx]
    if surface < inv_z - soft_inv_z:
        if surface > 0 and clear[yy, xx] > 0:
            _flatten_into_back(cell, clear, back, back_cell, yy, xx, surface)
        elif surface > 0:
            for c in range(4):
                back_cell[yy, xx, c] = cell[yy, xx, c]
            back[yy, xx] = surface
        front[yy, xx] = inv_z
        cell[yy, xx, 0] = wa * r
        cell[yy, xx, 1] = wa * g
        cell[yy, xx, 2] = wa * b
        cell[yy, xx, _WEIGHT] = w
        clear[yy, xx] = w - wa
    elif surface <= inv_z + soft_inv_z:
        front[yy, xx] = max(surface, inv_z)
        cell[yy, xx, 0] += wa * r
        cell[yy, xx, 1] += wa * g
        cell[yy, xx, 2] += wa * b
        cell[yy, xx, _WEIGHT] += w
        clear[yy, xx] += w - wa
    elif clear[yy, xx] > 0:  # behind a soft front: z-buffered into the back surface
        _soft_z(back, back_cell, yy, xx, wa, inv_z, soft_inv_z, r, g, b)


@numba.njit(cache=True, nogil=True, inline="always")
def _flatten_into_back(cell, clear, back, back_cell, yy, xx, surface):
    """A soft front about to be covered by a nearer soft point becomes the back: composited
    over the surface already behind it (or, over nothing, in its own un-premultiplied colour),
    so the opaque surface behind two soft edges is not dropped (it showed as dark specks)."""
    weight = cell[yy, xx, _WEIGHT]
    alpha_sum = max(weight - clear[yy, xx], np.float32(MIN_SPLAT_WEIGHT * MIN_SPLAT_WEIGHT))
    if back[yy, xx] > 0:
        see_through = clear[yy, xx] / (weight * back_cell[yy, xx, _WEIGHT])
        for c in range(3):
            back_cell[yy, xx, c] = cell[yy, xx, c] / weight + back_cell[yy, xx, c] * see_through
        if alpha_sum >= np.float32(0.5) * weight:
            back[yy, xx] = surface
    else:
        for c in range(3):
            back_cell[yy, xx, c] = cell[yy, xx, c] / alpha_sum
        back[yy, xx] = surface
    back_cell[yy, xx, _WEIGHT] = 1.0


@numba.njit(cache=True, nogil=True)
def _clear_cracks(front, cell, stamp, clear, back, frame, touched, crack_inv_z):
    """Empty the pixels where background shines through a crack in a magnified foreground:
    two opposite neighbours are nearer by crack_inv_z. They are filled like any hole.

    Only solid surfaces count: where the front is a soft edge of alpha below one half, the
    surface behind it is the pixel's solid one, so the fringe of an object is never taken
    for a crack around it."""
    height, width = front.shape
    # Where soft points touched, the solid depth stands in for the front while filtering.
    fronts = np.empty(touched.shape[0], np.float32)
    for k in range(touched.shape[0]):
        yy = touched[k] // width
        xx = touched[k] % width
        fronts[k] = front[yy, xx]
        weight = cell[yy, xx, _WEIGHT]
        if clear[yy, xx] > 0 and weight - clear[yy, xx] < np.float32(0.5) * weight:
            front[yy, xx] = back[yy, xx]  # mostly see-through: the surface behind counts
    # Only the unfiltered row above and the current row are kept: the row below is untouched yet.
    above = front[0].copy()
    row = np.empty_like(above)
    for yy in range(1, height - 1):
        row[:] = front[yy]
        below = front[yy + 1]
        for xx in range(1, width - 1):
            threshold = row[xx] + crack_inv_z
            # Opposite neighbour pairs: horizontal, vertical and both diagonals.
            if (
                (row[xx - 1] > threshold and row[xx + 1] > threshold)
                or (above[xx] > threshold and below[xx] > threshold)
                or (above[xx - 1] > threshold and below[xx + 1] > threshold)
                or (above[xx + 1] > threshold and below[xx - 1] > threshold)
            ) and not (stamp[yy, xx] == frame and clear[yy, xx] > 0):  # a soft edge is no crack
                front[yy, xx] = 0.0
                cell[yy, xx, :] = 0.0
        above, row = row, above
    for k in range(touched.shape[0]):
        yy = touched[k] // width
        xx = touched[k] % width
        if cell[yy, xx, _WEIGHT] > 0:  # not emptied as a crack
            front[yy, xx] = fronts[k]


@numba.njit(cache=True, nogil=True)
def _finish_kernel(cell, front, stamp, clear, back, back_cell, frame, touched, image):
    """Composite, round, and give every empty pixel the colour of the farthest covered pixel
    found along its row and column (a cheap fill from the background side). Leaves cell
    cleared for the next frame; front keeps 0 where a pixel was empty.

    A soft edge over nothing (a gap in a magnified surface behind it, or a hole) is filled
    from the surface behind the soft pixels around it, and the edge composited over that:
    in its own full colour, a faint fringe showed as dashes beside the object. A soft edge
    blended into the opaque inside of its object keeps its own colour: what it lacks of
    full alpha there is the splat's blur, not background."""
    height, width = front.shape
    pixel = np.empty(3, np.float32)
    over_nothing = 0
    for index in touched:  # soft pixels: their composite, premultiplied by the weight
        yy = index // width
        xx = index % width
        weight = cell[yy, xx, _WEIGHT]
        if front[yy, xx] > 0 and weight > 0 and clear[yy, xx] > 0:
            alpha = max(weight - clear[yy, xx], np.float32(0.0)) / weight
            if (back[yy, xx] <= 0 and back_cell[yy, xx, _WEIGHT] != _ON_OPAQUE
                    and alpha < np.float32(OPAQUE_ALPHA)):
                # over nothing: kept premultiplied in back_cell until its fill is known
                for c in range(3):
                    back_cell[yy, xx, c] = cell[yy, xx, c] / weight
                back_cell[yy, xx, _WEIGHT] = alpha
                clear[yy, xx] = -1.0
                front[yy, xx] = 0.0
                over_nothing += 1
                continue
            _composite(cell, stamp, clear, back, back_cell, frame, yy, xx, pixel)
            for c in range(3):
                cell[yy, xx, c] = pixel[c] * weight
            clear[yy, xx] = 0.0
    empty = 0
    for yy in range(height):
        for xx in range(width):
            here = cell[yy, xx]
            if front[yy, xx] > 0:
                scale = np.float32(1.0) / here[_WEIGHT]
                for c in range(3):
                    image[yy, xx, c] = min(255, max(0, int(here[c] * scale + np.float32(0.5))))
            else:
                empty += 1
            for c in range(4):
                here[c] = 0.0
    if empty == 0:
        return
    found = np.empty((4, 2), np.int64)
    for yy in range(height):
        for xx in range(width):
            if front[yy, xx] > 0 or (stamp[yy, xx] == frame and clear[yy, xx] < 0):
                continue
            best_y, best_x = _background_source(front, stamp, back, frame, False, yy, xx,
                                                found)
            for c in range(3):
                image[yy, xx, c] = image[best_y, best_x, c] if best_y >= 0 else 0
    if over_nothing == 0:
        return
    for index in touched:
        yy = index // width
        xx = index % width
        if clear[yy, xx] >= 0:
            continue
        best_y, best_x = _background_source(front, stamp, back, frame, True, yy, xx, found)
        see_through = np.float32(1.0) - back_cell[yy, xx, _WEIGHT]
        soft_source = best_y >= 0 and stamp[best_y, best_x] == frame and back[best_y, best_x] > 0
        for c in range(3):
            if soft_source:
                behind = back_cell[best_y, best_x, c] / back_cell[best_y, best_x, _WEIGHT]
            else:
                behind = np.float32(image[best_y, best_x, c]) if best_y >= 0 else np.float32(0)
            value = back_cell[yy, xx, c] + see_through * behind
            image[yy, xx, c] = min(255, max(0, int(value + np.float32(0.5))))


@numba.njit(cache=True, nogil=True, inline="always")
def _background_source(front, stamp, back, frame, behind_soft, yy, xx, found):
    """The pixel an empty pixel takes its colour from: of the nearest covered pixels to its
    left, right, above and below, the farthest. A crack (covered on both sides of a row or a
    column within FILL_CRACK_PX) is closed from those two sides. With behind_soft, a soft
    pixel counts at the depth of the surface behind it. (-1, -1) when none is found."""
    height, width = front.shape
    near_h = 0
    near_v = 0
    for k, (step_y, step_x) in enumerate(((0, -1), (0, 1), (-1, 0), (1, 0))):
        cy = yy + step_y
        cx = xx + step_x
        steps = 1
        while 0 <= cy < height and 0 <= cx < width and front[cy, cx] == 0:
            cy += step_y
            cx += step_x
            steps += 1
        inside = 0 <= cy < height and 0 <= cx < width
        found[k, 0] = cy if inside else -1
        found[k, 1] = cx
        if inside and steps <= FILL_CRACK_PX:
            if k < 2:
                near_h += 1
            else:
                near_v += 1
    crack_h = near_h == 2
    crack_v = near_v == 2
    best_inv = np.float32(np.inf)
    best_y = -1
    best_x = -1
    for k in range(4):
        cy = found[k, 0]
        cx = found[k, 1]
        if cy < 0 or ((crack_h or crack_v) and not (crack_h if k < 2 else crack_v)):
            continue
        surface = front[cy, cx]
        if behind_soft and stamp[cy, cx] == frame and back[cy, cx] > 0:
            surface = back[cy, cx]
        if surface < best_inv:
            best_inv = surface
            best_y = cy
            best_x = cx
    return best_y, best_x


def to_uint8(colour: np.ndarray) -> np.ndarray:
    """Round a float colour image to 8 bits."""
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8)
