"""A geometric prior for when nothing better is known: a ground plane and a far backdrop.

Most photos are taken upright with the ground below the horizon, so disparity grows from the
horizon toward the bottom edge and stays at the backdrop's value above it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kbbatch.depth import DepthResult

HORIZON_FRACTION = 0.45
"""The horizon's height as a fraction of the image, from the top (eye-level framing)."""

BACKDROP_DISPARITY = 0.15
"""Disparity of everything above the horizon, relative to the nearest ground."""


def ground_plane_disparity(height_px: int, width_px: int, horizon_fraction: float = HORIZON_FRACTION
                           ) -> np.ndarray:
    """Disparity of a flat ground below the horizon (linear in the row) and a far backdrop."""
    rows = (np.arange(height_px, dtype=np.float32) + 0.5) / height_px
    below = np.clip((rows - horizon_fraction) / (1.0 - horizon_fraction), 0.0, 1.0)
    column = BACKDROP_DISPARITY + (1.0 - BACKDROP_DISPARITY) * below
    return np.repeat(column[:, None], width_px, axis=1)


class RampDepth:
    name = "ramp"

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: object = None
                  ) -> DepthResult:
        height, width = image.shape[:2]
        return DepthResult(ground_plane_disparity(height, width), self.name, "ground-plane prior")
