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

HINGE_HALF_WIDTH = 0.15
"""Half the height (fraction of the image) over which the backdrop bends into the ground.

Where the two planes met at one row, every straight upright thing crossing the horizon that
is not a card (a pole, a window frame, a tower) broke there into two straight pieces at an
angle as the camera moved. Rounded over this band, its bend is a gentle curve."""

_THINNEST_BAND = 1e-6  # a horizon at the image's very edge still gets a band (no 0 / 0)


def ground_plane_disparity(height_px: int, width_px: int, horizon_fraction: float = HORIZON_FRACTION
                           ) -> np.ndarray:
    """Disparity of a flat ground below the horizon (linear in the row, but for the rounded
    band around the horizon) and a far backdrop."""
    rows = (np.arange(height_px, dtype=np.float64) + 0.5) / height_px
    below = rows - horizon_fraction
    half = max(min(HINGE_HALF_WIDTH, horizon_fraction, 1.0 - horizon_fraction), _THINNEST_BAND)
    # a parabola over the band, meeting both planes with their slopes (no corner)
    rounded = np.where(below > -half, (below + half) ** 2 / (4.0 * half), 0.0)
    ground = np.where(below >= half, below, rounded) / max(1.0 - horizon_fraction, half)
    column = (BACKDROP_DISPARITY + (1.0 - BACKDROP_DISPARITY) * np.minimum(ground, 1.0)
              ).astype(np.float32)
    return np.repeat(column[:, None], width_px, axis=1)


class RampDepth:
    name = "ramp"

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: object = None
                  ) -> DepthResult:
        height, width = image.shape[:2]
        return DepthResult(ground_plane_disparity(height, width), self.name, "ground-plane prior")
