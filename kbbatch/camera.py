"""From two crop windows to a virtual camera per time (paper section 3.3). Pure and small.

Coordinates are working pixels (long side 1024) with pixel centres at i + 0.5 and the
principal point at the image centre. The camera never rotates: zoom is a dolly toward the
scene, and a crop shift is a lateral move, both chosen so that the nearest surface behaves
exactly like a 2D Ken Burns crop of the same windows. Farther surfaces move less: parallax.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from kbbatch import paper

ASPECT_TOLERANCE = 0.02
"""Two aspect ratios this close (as a fraction) are the same, allowing for pixel rounding; a
manifest crop or a depth map further from its target's aspect is refused, not stretched."""

Easing = Literal["linear", "ease-in-out"]
EASINGS: tuple[str, ...] = ("linear", "ease-in-out")


@dataclass(frozen=True)
class Crop:
    """A crop window in working pixels: centre and size."""

    center_x_px: float
    center_y_px: float
    width_px: float
    height_px: float

    @property
    def left_px(self) -> float:
        return self.center_x_px - self.width_px / 2

    @property
    def top_px(self) -> float:
        return self.center_y_px - self.height_px / 2

    @property
    def right_px(self) -> float:
        return self.center_x_px + self.width_px / 2

    @property
    def bottom_px(self) -> float:
        return self.center_y_px + self.height_px / 2

    def inside(self, width_px: float, height_px: float, tolerance_px: float = 1e-6) -> bool:
        """Whether the window lies within an image of this size."""
        return (
            self.left_px >= -tolerance_px
            and self.top_px >= -tolerance_px
            and self.right_px <= width_px + tolerance_px
            and self.bottom_px <= height_px + tolerance_px
        )

    def scaled(self, factor: float) -> Crop:
        """The same window in an image resized by this factor."""
        return Crop(
            self.center_x_px * factor,
            self.center_y_px * factor,
            self.width_px * factor,
            self.height_px * factor,
        )


@dataclass(frozen=True)
class Plan:
    """What a planner decides for one image: where the camera starts and ends, and how."""

    start: Crop
    end: Crop
    easing: Easing = "linear"
    planner: str = "center"
    parallax: bool = True
    """False renders the same crops as a plain 2D Ken Burns (the paper's baseline)."""


@dataclass(frozen=True)
class View:
    """A pinhole camera: position in working units, intrinsics and image size in pixels."""

    position: tuple[float, float, float]
    focal_px: float
    principal_x_px: float
    principal_y_px: float
    width_px: int
    height_px: int


@dataclass(frozen=True)
class SceneGeometry:
    """What the camera needs to know about the photo: working size and nearest depth."""

    width_px: int
    height_px: int
    nearest_depth: float

    @property
    def focal_px(self) -> float:
        return paper.focal_px(max(self.width_px, self.height_px))


def working_size(width_px: int, height_px: int) -> tuple[int, int]:
    """The working size of an image: long side 1024, aspect kept."""
    scale = paper.WORKING_LONG_SIDE_PX / max(width_px, height_px)
    return max(1, round(width_px * scale)), max(1, round(height_px * scale))


def depth_from_disparity(disparity: np.ndarray, focal: float) -> np.ndarray:
    """Depth in working units from a relative disparity (larger is nearer), as the paper does.

    The disparity is normalised to a maximum of 40 px (baseline 40), so the nearest point lies
    at depth f; a floor keeps the sky at a finite distance.
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    peak = float(np.max(disparity))
    if not math.isfinite(peak) or peak <= 0:
        raise ValueError("disparity has no positive finite maximum")
    normalised = np.clip(disparity / peak, paper.DISPARITY_FLOOR_FRACTION, 1.0)
    return (focal * paper.DISPARITY_MAX_PX / (normalised * paper.DISPARITY_MAX_PX)).astype(
        np.float32
    )


def nearest_depth(depth: np.ndarray) -> float:
    """The nearest depth, ignoring the reference's border (narrowed for thin images)."""
    height, width = depth.shape
    border_y = min(paper.ZMIN_BORDER_PX, height // 4)
    border_x = min(paper.ZMIN_BORDER_PX, width // 4)
    interior = depth[border_y : height - border_y, border_x : width - border_x]
    return float(np.min(interior if interior.size else depth))


def ease(t: float, easing: Easing) -> float:
    """Map linear time in [0, 1] to progress along the move."""
    t = min(max(t, 0.0), 1.0)
    if easing == "linear":
        return t
    if easing == "ease-in-out":
        return 0.5 - 0.5 * math.cos(math.pi * t)
    raise ValueError(f"unknown easing {easing!r}; expected one of {', '.join(EASINGS)}")


def crop_at(plan: Plan, t: float) -> Crop:
    """The crop window at time t: centre and size interpolated linearly in eased time."""
    s = ease(t, plan.easing)
    a, b = plan.start, plan.end
    return Crop(
        a.center_x_px + s * (b.center_x_px - a.center_x_px),
        a.center_y_px + s * (b.center_y_px - a.center_y_px),
        a.width_px + s * (b.width_px - a.width_px),
        a.height_px + s * (b.height_px - a.height_px),
    )


def widest_crop(plan: Plan) -> Crop:
    return plan.start if plan.start.width_px >= plan.end.width_px else plan.end


def framing_offset(plan: Plan, scene: SceneGeometry) -> tuple[float, float]:
    """The widest crop's offset from the image centre, in working pixels.

    It is rendered as a shifted principal point (plain framing, no parallax); only the move
    between the crops translates the camera. With a centred widest crop this is the paper's
    camera exactly, and a photo framed off-centre still starts as the photo itself.
    """
    widest = widest_crop(plan)
    return widest.center_x_px - scene.width_px / 2, widest.center_y_px - scene.height_px / 2


def camera_position(plan: Plan, scene: SceneGeometry, t: float) -> tuple[float, float, float]:
    """Camera position at time t so that the nearest surface follows the crop exactly.

    The dolly brings the nearest surface from depth zmin to zmin * w(t) / max(w): that
    magnifies it by the crop-width ratio. The lateral move puts the nearest surface under the
    crop centre where the framing expects it, so a 100 px crop offset moves it by 100 px.
    """
    crop = crop_at(plan, t)
    widest = widest_crop(plan)
    zmin = scene.nearest_depth
    relative_size = crop.width_px / widest.width_px
    target_depth = zmin * relative_size
    f = scene.focal_px
    frame_x, frame_y = framing_offset(plan, scene)
    offset_x = crop.center_x_px - scene.width_px / 2 - frame_x * relative_size
    offset_y = crop.center_y_px - scene.height_px / 2 - frame_y * relative_size
    return (offset_x * zmin / f, offset_y * zmin / f, zmin - target_depth)


def output_view(
    plan: Plan,
    scene: SceneGeometry,
    t: float,
    width_px: int,
    height_px: int,
    position: tuple[float, float, float] | None = None,
) -> View:
    """The view that renders the frame at time t straight at the output size.

    Equivalent to the reference's full-size render, cut of the widest crop's window, and
    resize, without rendering pixels that are thrown away.
    """
    widest = widest_crop(plan)
    scale = width_px / widest.width_px
    frame_x, frame_y = framing_offset(plan, scene)
    return View(
        position=camera_position(plan, scene, t) if position is None else position,
        focal_px=scene.focal_px * scale,
        principal_x_px=width_px / 2 - frame_x * scale,
        principal_y_px=height_px / 2 - frame_y * scale,
        width_px=width_px,
        height_px=height_px,
    )


def working_view(
    scene: SceneGeometry, position: tuple[float, float, float], scale: float = 1.0
) -> View:
    """A full-frame view at the working size (times scale) from a camera position; at least
    one pixel each way, as an image resized to that scale is (a strip 1024 x 2 px at the
    planner's quarter scale had a view of no rows, and its depth matched no view)."""
    width = max(1, round(scene.width_px * scale))
    height = max(1, round(scene.height_px * scale))
    return View(
        position=position,
        focal_px=scene.focal_px * scale,
        principal_x_px=scene.width_px * scale / 2,
        principal_y_px=scene.height_px * scale / 2,
        width_px=width,
        height_px=height,
    )


def overshoot(
    start: tuple[float, float, float], end: tuple[float, float, float], factor: float
) -> tuple[float, float, float]:
    """A camera position past the end of the move, along the same line."""
    return (
        start[0] + factor * (end[0] - start[0]),
        start[1] + factor * (end[1] - start[1]),
        start[2] + factor * (end[2] - start[2]),
    )


def fit_crop(
    width_px: float,
    height_px: float,
    aspect: float,
    fraction: float,
    center: tuple[float, float] | None = None,
) -> Crop:
    """The largest window of this aspect (width / height) inside `fraction` of the image."""
    avail_w, avail_h = width_px * fraction, height_px * fraction
    if avail_w / avail_h > aspect:
        crop_h = avail_h
        crop_w = crop_h * aspect
    else:
        crop_w = avail_w
        crop_h = crop_w / aspect
    cx, cy = center if center is not None else (width_px / 2, height_px / 2)
    return Crop(cx, cy, crop_w, crop_h)


def zoomed(crop: Crop, zoom: float, center: tuple[float, float] | None = None) -> Crop:
    """The crop divided by zoom (zoom > 1 narrows it), optionally recentred."""
    cx, cy = center if center is not None else (crop.center_x_px, crop.center_y_px)
    return Crop(cx, cy, crop.width_px / zoom, crop.height_px / zoom)


def clamp_inside(crop: Crop, width_px: float, height_px: float) -> Crop:
    """Move (never resize) a window so that it lies inside the image, if it fits at all."""
    cx = min(max(crop.center_x_px, crop.width_px / 2), width_px - crop.width_px / 2)
    cy = min(max(crop.center_y_px, crop.height_px / 2), height_px - crop.height_px / 2)
    return Crop(cx, cy, crop.width_px, crop.height_px)


def project(view: View, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, ...]:
    """Pixel coordinates (continuous, pixel centres at i + 0.5) of world points in a view."""
    depth = z - view.position[2]
    u = view.focal_px * (x - view.position[0]) / depth + view.principal_x_px
    v = view.focal_px * (y - view.position[1]) / depth + view.principal_y_px
    return u, v


def unproject(scene: SceneGeometry, u_px: np.ndarray, v_px: np.ndarray, depth: np.ndarray
              ) -> tuple[np.ndarray, ...]:
    """World points seen at working-image coordinates (u, v) with the given depth."""
    f = scene.focal_px
    return (
        (u_px - scene.width_px / 2) * depth / f,
        (v_px - scene.height_px / 2) * depth / f,
        depth,
    )
