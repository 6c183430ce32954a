"""Salient objects as instances with masks: YOLOX boxes, DeepLab classes, ISNet saliency.

The paper uses Mask R-CNN instance masks; we build each instance from a YOLOX box, shaped by
the DeepLab pixels of its class and the ISNet salient-object mask inside that box. Every model
is optional: what is missing from the cache is skipped, and the log says so.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from kbbatch import models, paper

log = logging.getLogger(__name__)

COCO_CLASSES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich",
    "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote",
    "keyboard", "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book",
    "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush",
)

VOC_INDEX_OF = {
    "person": 15, "car": 7, "bus": 6, "train": 19, "boat": 4, "bird": 3, "cat": 8, "dog": 12,
    "horse": 13, "sheep": 17, "cow": 10, "bicycle": 2, "motorcycle": 14, "truck": 7,
}
"""PASCAL VOC class of a COCO class, where VOC has one (a truck is closest to a car)."""

YOLOX_STRIDES = (8, 16, 32)
YOLOX_LETTERBOX_VALUE = 114
NMS_IOU = 0.45
DETECTION_SCORE_MIN = 0.3
"""Detections are kept from this score for accessory merging; salient objects need 0.7."""
SALIENT_THRESHOLD = 0.5
MASK_ERODE_PX = 2
"""Masks are eroded slightly before adjustment, as the paper does, at the working size."""


@dataclass(frozen=True)
class Detection:
    class_name: str
    score: float
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in image pixels


@dataclass(frozen=True)
class Instance:
    class_name: str
    score: float
    box: tuple[int, int, int, int]
    mask: np.ndarray  # (H, W) bool


def available(name: str) -> bool:
    return models.cached_path(name) is not None


def salient_mask(image: np.ndarray) -> np.ndarray | None:
    """ISNet salient-object probability at the image size, or None without the model."""
    if not available("isnet-dis-medium"):
        return None
    spec = models.REGISTRY["isnet-dis-medium"]
    session = models.load(spec.name)
    batch = models.prepare_input(spec, image)
    output = session.run(None, {session.get_inputs()[0].name: batch})[0][0, 0]
    height, width = image.shape[:2]
    return cv2.resize(output.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)


def semantic_labels(image: np.ndarray) -> np.ndarray | None:
    """DeepLab PASCAL VOC labels at the image size, or None without the model."""
    if not available("deeplabv3-mnv2-pascal"):
        return None
    spec = models.REGISTRY["deeplabv3-mnv2-pascal"]
    session = models.load(spec.name)
    scores = session.run(None, {session.get_inputs()[0].name: models.prepare_input(spec, image)})
    height, width = image.shape[:2]
    # The scores, not the labels, are brought to the image size: labels from a 257 px grid
    # would give every mask a staircase outline, which the fill then traces into the background.
    scores = cv2.resize(scores[0][0], (width, height), interpolation=cv2.INTER_LINEAR)
    return np.argmax(scores, axis=-1).astype(np.uint8)


@functools.cache
def _yolox_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    grids, strides = [], []
    for stride in YOLOX_STRIDES:
        cells = size // stride
        ys, xs = np.mgrid[0:cells, 0:cells]
        grids.append(np.stack([xs.ravel(), ys.ravel()], axis=1))
        strides.append(np.full(cells * cells, stride))
    return np.concatenate(grids).astype(np.float32), np.concatenate(strides)[:, None]


def detect(image: np.ndarray) -> list[Detection]:
    """YOLOX-nano detections (boxes in image pixels), or [] without the model."""
    if not available("yolox-nano"):
        return []
    spec = models.REGISTRY["yolox-nano"]
    size = spec.input_size
    height, width = image.shape[:2]
    ratio = min(size / height, size / width)
    resized = cv2.resize(image, (round(width * ratio), round(height * ratio)),
                         interpolation=cv2.INTER_LINEAR)
    canvas = np.full((size, size, 3), YOLOX_LETTERBOX_VALUE, np.uint8)
    canvas[: resized.shape[0], : resized.shape[1]] = resized
    batch = np.ascontiguousarray(canvas[..., ::-1].transpose(2, 0, 1)[None], dtype=np.float32)
    session = models.load(spec.name)
    raw = session.run(None, {session.get_inputs()[0].name: batch})[0][0]
    grid, strides = _yolox_grid(size)
    centres = (raw[:, :2] + grid) * strides
    sizes = np.exp(raw[:, 2:4]) * strides
    scores_all = raw[:, 4:5] * raw[:, 5:]
    classes = scores_all.argmax(axis=1)
    scores = scores_all[np.arange(len(classes)), classes]
    keep = scores >= DETECTION_SCORE_MIN
    boxes = np.concatenate([centres - sizes / 2, sizes], axis=1)[keep] / ratio
    scores, classes = scores[keep], classes[keep]
    chosen = []
    if len(scores):
        chosen = cv2.dnn.NMSBoxesBatched(boxes.tolist(), scores.tolist(), classes.tolist(),
                                         DETECTION_SCORE_MIN, NMS_IOU)
    detections = []
    for index in np.asarray(chosen, dtype=int).ravel():
        x, y, w, h = boxes[index]
        box = (max(0.0, x), max(0.0, y), min(float(width), x + w), min(float(height), y + h))
        detections.append(Detection(COCO_CLASSES[classes[index]], float(scores[index]), box))
    return sorted(detections, key=lambda d: -d.score)


def _box_mask(shape: tuple[int, int], box: tuple[float, float, float, float]) -> np.ndarray:
    mask = np.zeros(shape, bool)
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    mask[y0:y1, x0:x1] = True
    return mask


def find_instances(image: np.ndarray) -> list[Instance]:
    """Salient objects (people, vehicles, animals) with masks, following the paper's rules."""
    shape = image.shape[:2]
    detections = detect(image)
    if not detections:
        return []
    saliency = salient_mask(image)
    labels = semantic_labels(image)
    salient = saliency > SALIENT_THRESHOLD if saliency is not None else None

    def shape_mask(detection: Detection) -> np.ndarray:
        in_box = _box_mask(shape, detection.box)
        parts = []
        if labels is not None and detection.class_name in VOC_INDEX_OF:
            parts.append(labels == VOC_INDEX_OF[detection.class_name])
        if salient is not None:
            parts.append(salient)
        if not parts:
            return in_box
        return in_box & np.logical_or.reduce(parts)

    objects = [
        d for d in detections
        if d.class_name in paper.SALIENT_CLASSES and d.score >= paper.SALIENT_SCORE_MIN
    ]
    accessories = [d for d in detections if d.class_name in paper.ACCESSORY_CLASSES]
    masks = [shape_mask(d) for d in objects]
    for accessory in accessories:
        accessory_mask = shape_mask(accessory)
        area = accessory_mask.sum()
        if area == 0:
            continue
        overlaps = [(m & accessory_mask).sum() / area for m in masks]
        if overlaps and max(overlaps) >= paper.ACCESSORY_OVERLAP_MIN:
            best = int(np.argmax(overlaps))
            masks[best] = masks[best] | accessory_mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * MASK_ERODE_PX + 1,) * 2)
    instances = []
    for detection, mask in zip(objects, masks, strict=True):
        mask = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
        if mask.sum() < paper.SALIENT_MASK_MIN_PX:
            continue
        ys, xs = np.nonzero(mask)
        box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
        instances.append(Instance(detection.class_name, detection.score, box, mask))
    log.debug("found %d salient instance(s)", len(instances))
    return instances
