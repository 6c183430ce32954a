"""Monocular depth networks exported to ONNX (Depth Anything V2 small, MiDaS v2.1 small)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kbbatch import models
from kbbatch.depth import DepthResult, SceneContext

DEPTH_MODELS = ("depth-anything-v2-small", "midas-v21-small")
"""Registered depth networks, best first: `auto` takes the first one in the cache."""


def first_cached_model() -> str | None:
    return next((name for name in DEPTH_MODELS if models.cached_path(name)), None)


def relative_disparity(output: np.ndarray) -> np.ndarray:
    """A network's affine-invariant disparity, rescaled to 0..1 (1 is the nearest)."""
    data = np.squeeze(np.asarray(output, np.float32))
    if data.ndim != 2:
        raise models.ModelError(f"depth network returned shape {output.shape}, expected a map")
    low, high = float(data.min()), float(data.max())
    if not np.isfinite([low, high]).all() or high - low <= 0:
        raise models.ModelError("depth network returned a constant or non-finite map")
    return (data - low) / (high - low)


class OnnxDepth:
    name = "onnx"

    def __init__(self, model: str) -> None:
        if model not in DEPTH_MODELS:
            raise models.ModelError(f"{model} is not a depth model; choose from "
                                    f"{', '.join(DEPTH_MODELS)}")
        self.spec = models.REGISTRY[model]

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: SceneContext
                  ) -> DepthResult:
        session = models.load(self.spec.name)
        height, width = image.shape[:2]
        size = models.session_input_size(session, models.input_size_for(self.spec, width,
                                                                          height))
        batch = models.prepare_input(self.spec, image, size)
        output = session.run(None, {session.get_inputs()[0].name: batch})[0]
        return DepthResult(relative_disparity(output), self.name, self.spec.name)
