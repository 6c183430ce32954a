"""Depth stage: one interface over the backends that give a relative disparity per photo.

A backend returns disparity (larger is nearer, any scale) at the working size; the camera
stage normalises it as the paper does. `auto` takes a depth file beside the photo when there
is one, else the best estimator available.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np


class DepthError(ValueError):
    """A depth map that cannot be used; the message names the file and the reason."""


@dataclass(frozen=True)
class DepthResult:
    disparity: np.ndarray  # (H, W) float32 at the working size, larger is nearer
    backend: str
    source: str  # what it came from: a file path or an estimator name


class DepthBackend(Protocol):
    name: str

    def disparity(self, image: np.ndarray, photo_path: Path | None) -> DepthResult: ...


BACKEND_NAMES = ("auto", "file", "ramp")


def get_backend(name: str, photo_path: Path | None) -> DepthBackend:
    """The backend for a photo: by name, or for `auto` the best one available."""
    from kbbatch.depth.file import FileDepth, find_depth_file
    from kbbatch.depth.ramp import RampDepth

    if name == "auto":
        depth_file = find_depth_file(photo_path) if photo_path else None
        return FileDepth(depth_file) if depth_file else RampDepth()
    if name == "file":
        depth_file = find_depth_file(photo_path) if photo_path else None
        if depth_file is None:
            raise DepthError(f"{photo_path}: --depth file needs <stem>.depth.png/.npy or "
                             "<stem>.disparity.png/.npy beside the photo")  # fmt: skip
        return FileDepth(depth_file)
    if name == "ramp":
        return RampDepth()
    raise DepthError(f"unknown depth backend {name!r}; available: {', '.join(BACKEND_NAMES)}")


def estimate_disparity(image: np.ndarray, photo_path: Path | None, backend: str = "auto"
                       ) -> DepthResult:  # fmt: skip
    """Relative disparity at the image's size from the chosen backend."""
    result = get_backend(backend, photo_path).disparity(image, photo_path)
    height, width = image.shape[:2]
    if result.disparity.shape != (height, width):
        resized = cv2.resize(result.disparity, (width, height), interpolation=cv2.INTER_LINEAR)
        result = DepthResult(resized.astype(np.float32), result.backend, result.source)
    return result
