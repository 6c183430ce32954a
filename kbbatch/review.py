"""Pictures of plans for people to review: crops drawn on the photo, and a contact sheet."""

from __future__ import annotations

import math

import cv2
import numpy as np

from kbbatch.camera import Crop, Plan

START_COLOUR = (60, 220, 60)
END_COLOUR = (240, 70, 50)
THUMBNAIL_WIDTH_PX = 360


def _rectangle(image: np.ndarray, crop: Crop, colour: tuple[int, int, int], thickness: int
               ) -> None:
    top_left = (round(crop.left_px), round(crop.top_px))
    bottom_right = (round(crop.right_px) - 1, round(crop.bottom_px) - 1)
    cv2.rectangle(image, top_left, bottom_right, colour, thickness, cv2.LINE_AA)


def draw_plan(image: np.ndarray, plan: Plan, label: str) -> np.ndarray:
    """The working image with the start (green) and end (red) crops and the move between."""
    canvas = image.copy()
    thickness = max(2, round(max(image.shape[:2]) / 300))
    _rectangle(canvas, plan.start, START_COLOUR, thickness)
    _rectangle(canvas, plan.end, END_COLOUR, thickness)
    start = (round(plan.start.center_x_px), round(plan.start.center_y_px))
    end = (round(plan.end.center_x_px), round(plan.end.center_y_px))
    cv2.arrowedLine(canvas, start, end, (255, 255, 255), thickness, cv2.LINE_AA, tipLength=0.3)
    # OpenCV's fonts draw printable ASCII only, and a name that is not UTF-8 (a surrogate
    # escape) crashed the process inside putText: every other character shows as '?'.
    printable = "".join(c if " " <= c <= "~" else "?" for c in label)
    cv2.putText(canvas, printable, (10, 10 + 12 * thickness), cv2.FONT_HERSHEY_SIMPLEX,
                0.4 * thickness, (255, 255, 255), thickness, cv2.LINE_AA)
    return canvas


def contact_sheet(pictures: list[np.ndarray], columns: int = 4) -> np.ndarray:
    """Thumbnails in a grid, each the same width, rows as tall as their tallest picture."""
    if not pictures:
        return np.zeros((16, 16, 3), np.uint8)
    columns = min(columns, len(pictures))
    thumbs = [cv2.resize(p, (THUMBNAIL_WIDTH_PX, max(1, round(p.shape[0] * THUMBNAIL_WIDTH_PX
                                                               / p.shape[1]))),
                         interpolation=cv2.INTER_AREA) for p in pictures]
    rows = []
    for start in range(0, len(thumbs), columns):
        row = thumbs[start : start + columns]
        height = max(t.shape[0] for t in row)
        padded = [cv2.copyMakeBorder(t, 0, height - t.shape[0], 0, 0, cv2.BORDER_CONSTANT)
                  for t in row]
        padded += [np.zeros((height, THUMBNAIL_WIDTH_PX, 3), np.uint8)] * (columns - len(row))
        rows.append(np.concatenate(padded, axis=1))
    sheet = np.concatenate(rows, axis=0)
    return sheet if math.prod(sheet.shape) else np.zeros((16, 16, 3), np.uint8)


def normalised_disparity(disparity: np.ndarray) -> np.ndarray:
    """Disparity scaled so that the nearest surface is 1."""
    return disparity / max(float(disparity.max()), 1e-6)


def depth_picture(disparity: np.ndarray) -> np.ndarray:
    """Disparity as an RGB colour map (near bright, far dark), for people to judge depth."""
    levels = (normalised_disparity(disparity) * 255).astype(np.uint8)
    return cv2.applyColorMap(levels, cv2.COLORMAP_INFERNO)[..., ::-1]
