"""Depth stage: estimate, adjust, refine (paper section 3.1), behind one interface.

A backend returns relative disparity (larger is nearer, any scale, any size); the stage then
refines it to the working size with sharp edges and flattens salient objects into cards. The
camera stage normalises it as the paper does. `auto` uses a depth file beside the photo, else
a cached depth network, else the pop-up geometry.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

log = logging.getLogger(__name__)


class DepthError(ValueError):
    """A depth map that cannot be used; the message names the file and the reason."""


@dataclass(frozen=True)
class DepthResult:
    disparity: np.ndarray  # (H, W) float32, larger is nearer
    backend: str
    source: str  # what it came from: a file path, a model, a description
    segmentation: SceneContext | None = field(default=None, compare=False, repr=False)
    """What the stage worked out of the photo's objects, for the planner to reuse (its salient
    map is kept in the depth cache)."""


@dataclass(frozen=True)
class DepthOptions:
    backend: str = "auto"
    model: str | None = None  # a registered depth network for `onnx`
    adjust: bool = True
    refine: bool = True
    file: str | None = None  # a depth or disparity map named for this photo (manifest)


class SceneContext:
    """Per-photo segmentation, computed at most once and only if some step asks for it.

    The results are stored on the instance, so they are freed with it: a module-level cache
    would keep every photo's image and masks alive for the life of a daemon.
    """

    def __init__(self, image: np.ndarray,
                 on_saliency: Callable[[np.ndarray], None] | None = None) -> None:
        self.image = image
        self.on_saliency = on_saliency  # told the map once it is worked out (the depth cache)
        self.saliency_by_planner = False  # kept by the cache for the planner, not the depth stage

    @classmethod
    def known(cls, image: np.ndarray, saliency: np.ndarray, by_planner: bool = False
              ) -> SceneContext:
        """A context whose salient map is already known (read from the depth cache; by_planner:
        worked out for the planner after the depth stage, which ran no ISNet)."""
        context = cls(image)
        context.__dict__["saliency"] = saliency  # where functools.cached_property keeps it
        context.saliency_by_planner = by_planner
        return context

    def known_saliency(self) -> np.ndarray | None:
        """The salient map if it has been worked out, without working it out."""
        return self.__dict__.get("saliency")

    @functools.cached_property
    def instances(self) -> list:
        from kbbatch.segment import find_instances

        return find_instances(self.image, lambda: self.saliency)

    @functools.cached_property
    def saliency(self) -> np.ndarray | None:
        from kbbatch.segment import salient_mask

        saliency = salient_mask(self.image)
        if saliency is not None and self.on_saliency is not None:
            self.on_saliency(saliency)
        return saliency


class DepthBackend(Protocol):
    name: str

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: SceneContext
                  ) -> DepthResult: ...


def _file_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    from kbbatch.depth.file import FileDepth, find_depth_file

    depth_file = find_depth_file(photo_path) if photo_path else None
    if depth_file is None:
        raise DepthError(f"{photo_path}: --depth file needs <stem>.depth.png/.npy or "
                         "<stem>.disparity.png/.npy beside the photo")
    return FileDepth(depth_file)


def _onnx_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    from kbbatch.depth.onnx import OnnxDepth, first_cached_model

    model = options.model or first_cached_model()
    if model is None:
        raise DepthError("no depth network is cached: run `kbbatch models pull "
                         "depth-anything-v2-small`, or use --depth popup (no network)")
    return OnnxDepth(model)


def _popup_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    from kbbatch.depth.popup import PopupDepth

    return PopupDepth()


def _ramp_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    from kbbatch.depth.ramp import RampDepth

    return RampDepth()


def _auto_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    """A depth file beside the photo, else a cached network, else the pop-up geometry."""
    from kbbatch.depth.file import find_depth_file
    from kbbatch.depth.onnx import first_cached_model

    if photo_path and find_depth_file(photo_path):
        return _file_backend(options, photo_path)
    if options.model or first_cached_model():
        return _onnx_backend(options, photo_path)
    return _popup_backend(options, photo_path)


BACKENDS: dict[str, Callable[[DepthOptions, Path | None], DepthBackend]] = {
    "auto": _auto_backend, "file": _file_backend, "onnx": _onnx_backend,
    "popup": _popup_backend, "ramp": _ramp_backend,
}
"""The registry: --depth's choices come from it; each entry builds the backend for a photo."""
BACKEND_NAMES = tuple(BACKENDS)


def get_backend(options: DepthOptions, photo_path: Path | None) -> DepthBackend:
    """The backend for a photo: by name, or for `auto` the best one available."""
    if options.file and options.backend in ("auto", "file"):
        from kbbatch.depth.file import FileDepth

        return FileDepth(Path(options.file))  # named by the manifest
    if options.backend not in BACKENDS:
        raise DepthError(f"unknown depth backend {options.backend!r}; available: "
                         f"{', '.join(BACKEND_NAMES)}")
    return BACKENDS[options.backend](options, photo_path)


def estimate_disparity(image: np.ndarray, photo_path: Path | None,
                       options: DepthOptions = DepthOptions()) -> DepthResult:
    """Relative disparity at the image's size: estimated, refined, adjusted."""
    from kbbatch.depth.adjust import adjust
    from kbbatch.depth.refine import refine

    context = SceneContext(image)
    result = get_backend(options, photo_path).disparity(image, photo_path, context)
    height, width = image.shape[:2]
    disparity = result.disparity.astype(np.float32)
    if disparity.shape != (height, width):
        if options.refine:
            disparity = refine(disparity, image)
        else:
            disparity = cv2.resize(disparity, (width, height), interpolation=cv2.INTER_LINEAR)
    # Pop-up cards are already flat and the ramp is a prior with nothing to adjust.
    if options.adjust and result.backend not in ("popup", "ramp"):
        instances = context.instances
        if instances:
            disparity = adjust(disparity, instances)
    log.info("depth from %s (%s)", result.backend, result.source)
    return DepthResult(disparity, result.backend, result.source, context)
