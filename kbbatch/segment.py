"""Salient objects as instances with masks: YOLOX boxes, DeepLab classes, ISNet saliency.

The paper uses Mask R-CNN instance masks; we build each instance from a YOLOX box, shaped by
the DeepLab pixels of its class and the ISNet salient-object mask inside that box. Every model
is optional: what is missing from the cache is skipped, and the log says so.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
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
MASK_ERODE_PX = 1
"""Masks are eroded slightly before adjustment, as the paper does, at the working size; by one
pixel, not two. The soft layers cap an object's matte beyond its depth edge at a blurred
edge's tail, so at two the object's own rim (a shoulder's 2.5 px outside the card on photo
03) stayed a third opaque: a grey fringe, cut into steps of one working pixel where the
card's staircase outline crossed it (4 output px at 4K, 2 at 1080p)."""

SNAP_BAND_PX = 20
"""A mask's outline may move by up to this (working px) onto the photo's own colour edge: the
networks see the photo at 257 to 416 px, so their outlines are several pixels off, and a card
that overshoots its person carries a skirt of wall along with them as a halo."""

HAIR_FRACTION = 0.3
"""Outlines are not snapped around the lower head, down to the neck and at least this share
of a person box's height: a retouched rim along a jaw is no colour edge the cut respects, and
snapping took it off the face, left behind as a smear..."""

JAW_FROM_FRACTION = 0.4
"""... from this far down the head (box top to the bottom of the zone): about the ears' top
(from half-way down, the cut clipped an ear's rim). Above, the graph cut hugs the hair: kept
as the network drew it, a strip of window beside Obama's hair (photo 02) and a chunk of
curtain beside Biden's (03) travelled with them. (The per-pixel colour test before the cut
took grey hair away in holes; the cut does not.)"""

CLASS_COVER_MIN = 0.8
"""Where ISNet's object covers at least this share of an instance's DeepLab class in its box,
ISNet sees that object: the class's pieces farther than SNAP_BAND_PX from ISNet's outline are
not taken. DeepLab's outline at 257 px runs well off a person, and one such piece, a slab of
flag beside an astronaut's arm (photo 01) too thick for the snap to shave, travelled with
her card and left a light dash on the flag. Where ISNet covers less (the people of a crowd it
does not single out), the class is taken whole."""

JAW_SALIENT_SLACK_PX = 2
"""Where the outline is kept as drawn (jaw_region), it is ISNet's, within this many working px:
the person mask is also DeepLab's class, whose outline at 257 px runs well off the person,
and kept there it gave Obama's card a wedge of window above the shoulder beside the neck
(photo 02), which the move tore from the curtain beside it as a ragged notch."""

SKIRT_PX = 8
"""A person's card keeps no piece beyond ISNet's outline (within JAW_SALIENT_SLACK_PX) that is
nowhere twice this thick (working px): such a skirt is DeepLab's outline, drawn at 257 px, that
the graph cut did not take back (a wedge of window above Obama's shoulder, photo 02, which the
move carried along, tearing a ragged bite into the curtain beside it). Thicker pieces are
kept: a limb ISNet missed."""

HEAD_SEARCH_FRACTION = 0.5
"""The neck is looked for in the top half of a person box."""

HAIR_MARGIN_FRACTION = 0.1
"""... over the columns the mask's head spans (its top HEAD_FRACTION of the box) widened by
this share of the box width on each side, and this far below the neck. Across the whole
box, a head-and-shoulders portrait's shoulders were never snapped either, and a card kept a
chunk of white backdrop beside the helmet that the move carried over the flag."""

FURRED_CLASSES = ("bird", "cat", "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra",
                  "giraffe")
"""Salient classes whose outlines are not snapped: the graph cut clipped a giraffe's mane into
a lumpy outline."""

GRAPH_CUT_SIDE_PX = 512
"""The graph cut that snaps an outline runs on the object's box scaled to at most this long a
side: 0.4 to 0.6 s per person of a two-people portrait on 2 cores. At 384 a sliver of white
backdrop above an astronaut's helmet rim stayed on her card."""

GRAPH_CUT_MIN_CHANGE_PX = 2
"""The cut's changes to the outline that an opening by a disc of this radius removes (under
5 px thick at the working size) are not taken."""

EDGE_GAIN = 1.5
"""A piece the cut moves is taken where its new border's colour gradient is at least this many
times its old border's: on a grey shirt against a grey wall the cut would otherwise move the
outline anywhere in the band."""

GRAPH_CUT_ITERATIONS = 3
"""GrabCut rounds of re-fitting its colour models; the outline settles after two or three."""

FRAGMENT_MIN_FRACTION = 0.1
"""A piece of an instance's mask smaller than this fraction of its largest piece is dropped:
no loose sliver of a suit or shard of curtain becomes a card of its own."""

FRAGMENT_MIN_PX = 400
"""... and so is any piece under this many pixels at the working size (about 20 x 20)."""

SLIVER_OPEN_PX = 2
"""Masks are opened (eroded then dilated) by this radius: strands thinner than twice it go."""

TIP_REACH_MAX_PX = 16
"""... except a thin tip reaching at most this far (working px) beyond what the opening kept:
the narrow end of a leaf, a beak, an ear (photo 15's leaf tips reach 5 to 13 px). A longer
strand with a free end is a sliver (a strip of a neighbour's suit) and stays cut."""

HOLE_FILL_MAX_FRACTION = 0.05
"""Holes inside a mask smaller than this fraction of its area are filled (a gap between
fingers stays background, a speckle in a shirt does not)."""

BOX_CORE_FRACTION = 0.5
"""An instance keeps the mask pieces that reach the central part of its box (this share of its
width and height), and those mostly outside other objects' boxes: a neighbour's arm or
shoulder inside the box is not this person, a leg cut off by a pole is."""

BEYOND_BOX_MAX_SHARE = 0.5
"""A detector's box can cut through its object, or through what the object holds: each piece
ISNet holds salient beyond the box that touches the instance's mask, outside other objects'
boxes, joins the mask when it is at most this share of the mask. A box edge cut an
astronaut's helmet in two (the piece beyond it, 18 % of her mask, stayed on the ground as the
card moved) and a cameraman's tripod; a larger piece is scenery ISNet took as one with the
object (the lake beyond a rowing boat, twice the boat), left to the background."""

HEAD_FRACTION = 0.2
"""The top of a person box, this share of its height, holds the head: the face region that
no cleaning removes and no other card takes..."""

HEAD_WIDTH_FRACTION = 0.6
"""... in the central part of the box, this share of its width."""

GROUP_SLIVER_PX = 12
"""Within a group card, background strips narrower than this (working px) join the card."""

GROUP_TOUCH_PX = 12
"""Cards whose masks come within twice this distance (working px) touch: overlapping people, or
people with a sliver of background between them (a row or column gap up to twice this), which
joins their group card rather than float between them as a shard."""

GROUP_DISPARITY_TOLERANCE = 0.15
"""Touching cards whose disparities differ by at most this fraction become one group card."""


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
    face: np.ndarray | None = None  # (H, W) bool: a person's head region, kept whole


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
    x0, y0, x1, y1 = (max(0, int(round(v))) for v in box)  # a negative start would wrap
    mask[y0:y1, x0:x1] = True
    return mask


def _box_core(shape: tuple[int, int], box: tuple[float, float, float, float]) -> np.ndarray:
    x0, y0, x1, y1 = box
    margin_x = (1 - BOX_CORE_FRACTION) / 2 * (x1 - x0)
    margin_y = (1 - BOX_CORE_FRACTION) / 2 * (y1 - y0)
    return _box_mask(shape, (x0 + margin_x, y0 + margin_y, x1 - margin_x, y1 - margin_y))


def beyond_the_box(mask: np.ndarray, salient: np.ndarray,
                   box: tuple[float, float, float, float], others: np.ndarray) -> np.ndarray:
    """The salient pieces beyond box (and outside others) that touch mask, each at most
    BEYOND_BOX_MAX_SHARE of it."""
    beyond = salient & ~_box_mask(mask.shape, box) & ~others
    if not beyond.any() or not mask.any():
        return np.zeros_like(mask)
    count, labels = cv2.connectedComponents(beyond.astype(np.uint8), connectivity=8)
    touching = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    joined = np.zeros(count, bool)
    joined[np.unique(labels[touching & beyond])] = True
    joined &= np.bincount(labels.ravel(), minlength=count) <= BEYOND_BOX_MAX_SHARE * mask.sum()
    joined[0] = False
    return joined[labels]


def untangle_overlaps(masks: list[np.ndarray], faces: list[np.ndarray | None],
                      image: np.ndarray) -> list[np.ndarray]:
    """Masks where each piece two of them share goes to one, where that is clear from the
    colours: to the one whose outline it then leaves on a colour edge EDGE_GAIN times as
    strong as the other's would be (a face stays with its own mask).

    Each mask is every person-coloured pixel in its box, so where people overlap, both masks
    hold the one in front, each up to its own box's edge. On a card game, a woman's arm
    stood against her nearer neighbour's hair: both masks held it, the nearer card took it
    and cut it along that card's box edge (no colour edge: skin went on), and the move tore
    the arm in two. Its border with the neighbour's own pixels lay on an edge 2.5 times as
    strong as its border with the woman's.
    """
    masks = [mask.copy() for mask in masks]
    strength = None
    ring = np.ones((3, 3), np.uint8)
    for first in range(len(masks)):
        for second in range(first + 1, len(masks)):
            shared = masks[first] & masks[second]
            if not shared.any():
                continue
            if strength is None:  # the masks are eroded: an outline's edge lies that far out
                reach = np.ones((2 * MASK_ERODE_PX + 1,) * 2, np.uint8)
                strength = cv2.dilate(_edge_strength(image), reach)
            count, labels = cv2.connectedComponents(shared.astype(np.uint8), connectivity=8)
            own_first = cv2.dilate((masks[first] & ~masks[second]).astype(np.uint8), ring) > 0
            own_second = cv2.dilate((masks[second] & ~masks[first]).astype(np.uint8), ring) > 0
            # where a shared piece meets a mask's own pixels: that mask's outline if it gives
            # the piece away
            at_first = _mean_per_piece(strength, labels, count, own_first & shared)
            at_second = _mean_per_piece(strength, labels, count, own_second & shared)
            # a piece that meets only one mask's own pixels is that mask's, or a hole in it
            between = (np.bincount(labels[own_first & shared], minlength=count) > 0) & (
                np.bincount(labels[own_second & shared], minlength=count) > 0)
            between[0] = False
            to_second = between & (at_first > EDGE_GAIN * at_second)
            to_first = between & (at_second > EDGE_GAIN * at_first)
            for giver, taken in ((first, to_second[labels]), (second, to_first[labels])):
                if faces[giver] is not None:
                    taken = taken & ~faces[giver]
                masks[giver] &= ~taken
    return masks


def _mean_per_piece(values: np.ndarray, labels: np.ndarray, count: int, where: np.ndarray
                    ) -> np.ndarray:
    """The mean of values over where, for each label of labels (0 where it has none)."""
    total = np.bincount(labels[where], values[where], minlength=count)
    return total / np.maximum(np.bincount(labels[where], minlength=count), 1)


def head_region(box: tuple[float, float, float, float], shape: tuple[int, int]) -> np.ndarray:
    """The head (face) part of a person box: its top HEAD_FRACTION, central HEAD_WIDTH_FRACTION
    (a flag or a lamp beside the head is not protected as a face), in image pixels."""
    x0, y0, x1, y1 = box
    margin = (1 - HEAD_WIDTH_FRACTION) / 2 * (x1 - x0)
    return _box_mask(shape, (x0 + margin, y0, x1 - margin, y0 + HEAD_FRACTION * (y1 - y0)))


def jaw_region(mask: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Where a person's outline is left as the network drew it: the lower head, from
    JAW_FROM_FRACTION of the way down to the neck (the narrowest row of the mask below the
    head's widest, within the top HEAD_SEARCH_FRACTION of the box, and at least HAIR_FRACTION
    of it) plus a margin of HAIR_MARGIN_FRACTION of the box width, over the head's columns
    widened by that margin; not the hair above, nor the shoulders."""
    x0, y0, x1, y1 = box
    left, right = max(0, int(round(x0))), max(0, int(round(x1)))
    top, height = max(0, int(round(y0))), y1 - y0
    head_bottom = int(round(y0 + HEAD_FRACTION * height))
    in_box = mask[:, left:right]
    columns = left + np.flatnonzero(in_box[top:max(top, head_bottom)].any(axis=0))
    if columns.size == 0:
        return np.zeros(mask.shape, bool)
    search_bottom = y0 + HEAD_SEARCH_FRACTION * height
    widths = in_box[top:max(top + 1, int(round(search_bottom)))].sum(axis=1)
    widest = int(np.argmax(widths[:max(1, head_bottom - top)]))
    neck = top + widest + int(np.argmin(widths[widest:]))
    margin = HAIR_MARGIN_FRACTION * (x1 - x0)
    bottom = min(max(y0 + HAIR_FRACTION * height, neck + margin), search_bottom)
    return _box_mask(mask.shape, (max(0.0, columns.min() - margin),
                                  y0 + JAW_FROM_FRACTION * (bottom - y0),
                                  columns.max() + 1 + margin, bottom))


def thin_skirt(mask: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """What lies of mask outside outline and in no disc of radius SKIRT_PX within it (an
    opening): a skirt running along the outline, not a limb beyond it. (Whole connected
    pieces could not be judged: the skirt runs round the person, thick somewhere.)"""
    beyond = (mask & ~outline).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SKIRT_PX + 1,) * 2)
    return (beyond > 0) & (cv2.morphologyEx(beyond, cv2.MORPH_OPEN, kernel) == 0)


def own_pieces(mask: np.ndarray, core: np.ndarray, others: np.ndarray) -> np.ndarray:
    """The connected pieces of mask that reach core, or lie mostly outside others (the other
    objects' boxes): a piece cut off by an occluder stays, a neighbour's arm does not."""
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    area = np.bincount(labels.ravel(), minlength=count)
    contested = np.bincount(labels[others].ravel(), minlength=count)
    reaching = np.zeros(count, bool)
    reaching[np.unique(labels[core & mask])] = True
    keep = reaching | (contested < 0.5 * area)
    keep[0] = False
    return keep[labels]


def snap_to_colour_edges(mask: np.ndarray, image: np.ndarray,
                         saliency: np.ndarray | None = None) -> np.ndarray:
    """mask with its outline moved onto the photo's colour edge, within SNAP_BAND_PX.

    The mask shrunk by the band is surely the object, the rest beyond it surely not; in
    between, a graph cut (OpenCV's GrabCut: colour models of both sides and a cost for cutting
    across smooth colour) proposes, starting from the network's outline. Per-pixel colour tests
    cannot tell a patch of white backdrop beside a shoulder from the person's own white
    helmet rim; the cut sees that the patch joins the backdrop with no edge between. A piece it
    moves is taken only where that puts the outline on a clearly stronger colour edge (where
    object and background look alike, the network's outline stays), it punches no holes, and
    only pieces joined to the sure inside are kept.

    saliency (ISNet's map): what it holds salient in a piece mostly salient is never cut away. On a
    rowing boat whose dark hull lay on dark shingle, the cut took the gunwale's bright edge for
    the outline and gave the hull to the ground: the move tore the boat along the gunwale.
    """
    image = np.ascontiguousarray(image, dtype=np.uint8)
    original = mask.astype(bool)
    binary = original.astype(np.uint8)
    window = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SNAP_BAND_PX + 1,) * 2)
    inside = cv2.erode(binary, window) > 0
    outside = cv2.dilate(binary, window) == 0
    if not inside.any() or not outside.any():
        return original
    proposed = inside | (_graph_cut(image, inside, outside, original) & ~outside)
    # Only changes of some thickness count: a sliver shaved off a thin low-contrast rim (a
    # helmet's ring against a pale backdrop) was a notch in it, and the matte places the
    # outline within a pixel or two anyway.
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * GRAPH_CUT_MIN_CHANGE_PX + 1,) * 2)
    removed = cv2.morphologyEx((original & ~proposed).astype(np.uint8), cv2.MORPH_OPEN, kernel)
    added = cv2.morphologyEx((proposed & ~original).astype(np.uint8), cv2.MORPH_OPEN, kernel)
    strength = _edge_strength(image)
    removed = _onto_stronger_edges(removed > 0, original & ~(removed > 0), strength)
    if saliency is not None:
        removed &= ~_salient_part(removed, saliency)
    added = _onto_stronger_edges(added > 0, ~(original | (added > 0)), strength)
    snapped = (original & ~removed) | added
    # The cut moves the outline; it punches no hole: what it gives to the background but is
    # cut off from the sure outside and the image border (a white lining inside a helmet)
    # stays as it was.
    count, labels = cv2.connectedComponents((~snapped).astype(np.uint8), connectivity=4)
    reaching = np.zeros(count, bool)
    reaching[np.unique(labels[outside])] = True
    reaching[np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))] \
        = True
    enclosed = ~snapped & ~reaching[labels]
    snapped = snapped | (enclosed & original)
    count, labels = cv2.connectedComponents(snapped.astype(np.uint8), connectivity=8)
    joined = np.zeros(count, bool)
    joined[np.unique(labels[inside])] = True
    joined[0] = False
    return joined[labels]


def _salient_part(pieces: np.ndarray, saliency: np.ndarray) -> np.ndarray:
    """The salient pixels (SALIENT_THRESHOLD) of the connected pieces that are over half
    salient: a hull the cut removed with a pocket of shingle beside it keeps the hull only."""
    salient = saliency >= SALIENT_THRESHOLD
    count, labels = cv2.connectedComponents(pieces.astype(np.uint8), connectivity=8)
    mostly = 2 * np.bincount(labels[salient], minlength=count) > np.bincount(
        labels.ravel(), minlength=count)
    mostly[0] = False
    return mostly[labels] & salient


def _edge_strength(image: np.ndarray) -> np.ndarray:
    """Colour gradient magnitude (Lab, summed over channels) of a lightly smoothed image."""
    lab = cv2.cvtColor(cv2.GaussianBlur(image, (0, 0), 1.0), cv2.COLOR_RGB2LAB).astype(np.float32)
    gx = cv2.Sobel(lab, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lab, cv2.CV_32F, 0, 1, ksize=3)
    return np.sqrt(gx * gx + gy * gy).sum(axis=-1)


def _onto_stronger_edges(pieces: np.ndarray, beyond: np.ndarray, strength: np.ndarray
                         ) -> np.ndarray:
    """The connected pieces (of what the cut moves) whose new border, where they meet beyond,
    runs along a colour edge at least EDGE_GAIN times as strong as their old border."""
    count, labels = cv2.connectedComponents(pieces.astype(np.uint8), connectivity=8)
    if count <= 1:
        return pieces
    ring = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(labels.astype(np.float32), ring).astype(np.int64)  # a neighbour's label
    new_border = beyond & (grown > 0)
    old_border = pieces & (cv2.dilate((~pieces & ~beyond).astype(np.uint8), ring) > 0)
    stronger = (_mean_per_piece(strength, grown, count, new_border)
                >= EDGE_GAIN * _mean_per_piece(strength, labels, count, old_border))
    stronger[0] = False
    return stronger[labels]


def _graph_cut(image: np.ndarray, inside: np.ndarray, outside: np.ndarray, mask: np.ndarray
               ) -> np.ndarray:
    """The foreground GrabCut finds between the sure inside and outside, starting from mask,
    over the box around the unsure band, at most GRAPH_CUT_SIDE_PX a side."""
    ys, xs = np.nonzero(~outside)  # the box around the band, with a 2 px rim of outside
    top, bottom = max(0, ys.min() - 2), min(mask.shape[0], ys.max() + 3)
    left, right = max(0, xs.min() - 2), min(mask.shape[1], xs.max() + 3)
    labels = np.where(inside, cv2.GC_FGD, np.where(
        outside, cv2.GC_BGD, np.where(mask, cv2.GC_PR_FGD, cv2.GC_PR_BGD))).astype(np.uint8)
    labels = labels[top:bottom, left:right]
    height, width = labels.shape
    scale = min(1.0, GRAPH_CUT_SIDE_PX / max(height, width))
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
    if not ((small == cv2.GC_FGD).any() and (small == cv2.GC_BGD).any()):
        return mask
    colour = cv2.resize(image[top:bottom, left:right], size, interpolation=cv2.INTER_AREA)
    background_model, foreground_model = np.zeros((1, 65)), np.zeros((1, 65))
    # GrabCut seeds its colour models from OpenCV's per-thread random state: reset it, or a
    # mask (and so a clip) depends on what ran before in that thread (a Ray worker's clip
    # differed from the local one).
    cv2.setRNGSeed(0)
    cv2.grabCut(np.ascontiguousarray(colour[..., ::-1]), small, None, background_model,
                foreground_model, GRAPH_CUT_ITERATIONS, cv2.GC_INIT_WITH_MASK)
    foreground = ((small == cv2.GC_FGD) | (small == cv2.GC_PR_FGD)).astype(np.float32)
    result = mask.copy()
    result[top:bottom, left:right] = cv2.resize(foreground, (width, height),
                                                interpolation=cv2.INTER_LINEAR) > 0.5
    return result


def _sliver_kernel() -> np.ndarray:
    """The cleaning's opening: a disc of radius SLIVER_OPEN_PX."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SLIVER_OPEN_PX + 1,) * 2)


def clean_mask(mask: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """A mask without slivers, speckle holes or small loose pieces.

    Opening removes thin strands; holes under HOLE_FILL_MAX_FRACTION of the area are filled;
    pieces under FRAGMENT_MIN_FRACTION of the largest one or FRAGMENT_MIN_PX are dropped.
    Pixels of keep (a face) that were in the mask stay in it, whole.
    """
    binary = mask.astype(np.uint8)
    opened = cv2.morphologyEx(binary, cv2.MORPH_OPEN, _sliver_kernel())
    if keep is not None:
        opened |= (binary.astype(bool) & keep).astype(np.uint8)
    labels, areas = enclosed_holes(opened)
    small = areas < HOLE_FILL_MAX_FRACTION * int(opened.sum())
    small[0] = False
    return drop_fragments(opened.astype(bool) | small[labels], keep)


def with_strands(cleaned: np.ndarray, original: np.ndarray) -> np.ndarray:
    """cleaned, with two kinds of the strands of original that the cleaning cut put back.

    Bridges, joining two of its pieces: a dandelion's stalks (3 px) joined its seeds to its
    parachute; cut, they stayed on the far ground while both ends moved with the card, and
    broke off. Tips, thin all along, reaching beyond it further than the opening's width but
    at most TIP_REACH_MAX_PX, and of no more pixels than a strand as wide as the opening and
    as long as that: the narrow end of a leaf, cut, stayed on the wall and floated beside the
    leaf as it moved (photo 15, the social preset). A strand with one end free that reaches
    further (a loose sliver of a suit), runs along the outline (strips of a launch tower
    beside a rocket: on its card, they bent the tower's lines and the clip lost all its
    parallax), or has a thicker part (a fragment the cleaning dropped), stays cut.
    """
    cleaned = cleaned.astype(bool)
    strands = original.astype(bool) & ~cleaned
    strand_count, strand_labels = cv2.connectedComponents(strands.astype(np.uint8),
                                                          connectivity=8)
    piece_count, pieces = cv2.connectedComponents(cleaned.astype(np.uint8), connectivity=8)
    if strand_count <= 1 or piece_count <= 1:
        return cleaned
    # the pieces beside each strand pixel: the largest and smallest piece number around it
    square = np.ones((3, 3), np.uint8)
    pieces = pieces.astype(np.float32)
    largest = cv2.dilate(pieces, square)
    smallest = cv2.erode(np.where(cleaned, pieces, np.float32(piece_count)), square)
    at = strands & (largest > 0)
    pairs = np.unique(np.concatenate([
        np.stack([strand_labels[at], largest[at].astype(np.int32)], axis=1),
        np.stack([strand_labels[at], smallest[at].astype(np.int32)], axis=1)]), axis=0)
    pairs = pairs[pairs[:, 1] < piece_count]
    touched = np.bincount(pairs[:, 0], minlength=strand_count)
    bridges = touched >= 2
    # A tip: no part of it survives the opening on its own; it reaches beyond the piece
    # further than the opening's width (less is the outline's own roughness, which the soft
    # layers' band covers) but not far; and it is short (a strip along the outline, a tower's
    # rail beside a rocket, lies near but is no tip).
    thick = cv2.morphologyEx(strands.astype(np.uint8), cv2.MORPH_OPEN, _sliver_kernel()) > 0
    has_thick = np.bincount(strand_labels[thick], minlength=strand_count) > 0
    beyond = cv2.distanceTransform((~cleaned).astype(np.uint8), cv2.DIST_L2,
                                   cv2.DIST_MASK_PRECISE)
    reach = np.zeros(strand_count, np.float32)
    np.maximum.at(reach, strand_labels[strands], beyond[strands])
    opening_width_px = 2 * SLIVER_OPEN_PX
    size_px = np.bincount(strand_labels[strands], minlength=strand_count)
    tips = ((touched == 1) & ~has_thick & (reach > opening_width_px)
            & (reach <= TIP_REACH_MAX_PX) & (size_px <= opening_width_px * TIP_REACH_MAX_PX))
    put_back = bridges | tips
    put_back[0] = False
    return cleaned | put_back[strand_labels]


def enclosed_holes(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The background regions mask encloses (4-connected, off the image border) numbered from
    1, 0 elsewhere, and each number's area in pixels (0 for 0)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(
        (~mask.astype(bool)).astype(np.uint8), connectivity=4)
    open_to_border = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    number = np.zeros(count, np.int32)
    enclosed = np.ones(count, bool)
    enclosed[0] = False  # the mask itself
    enclosed[open_to_border] = False
    number[enclosed] = np.arange(1, int(enclosed.sum()) + 1)
    areas = np.zeros(int(enclosed.sum()) + 1, np.int64)
    areas[1:] = stats[enclosed, cv2.CC_STAT_AREA]
    return number[labels], areas


def drop_fragments(mask: np.ndarray, keep: np.ndarray | None = None,
                   min_px: int = FRAGMENT_MIN_PX) -> np.ndarray:
    """mask without pieces under FRAGMENT_MIN_FRACTION of its largest or min_px; the piece
    holding most of keep (the face) always stays."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8),
                                                               connectivity=8)
    if count <= 1:
        return mask.astype(bool)
    areas = stats[:, cv2.CC_STAT_AREA]
    minimum = max(FRAGMENT_MIN_FRACTION * areas[1:].max(), min_px)
    kept = areas >= minimum
    if keep is not None:
        in_face = np.bincount(labels[keep & mask], minlength=count)
        in_face[0] = 0
        if in_face.max() > 0:
            kept[int(np.argmax(in_face))] = True
    kept[0] = False
    return kept[labels]


def group_cards(masks: list[np.ndarray], disparities: list[float]
                ) -> list[tuple[np.ndarray, float]]:
    """Cards that touch at a similar disparity joined into one group card (a crowd, a couple).

    A group takes its nearest member's disparity, so no member moves behind the others and no
    crack opens between people who stand together.
    """
    count = len(masks)
    parent = list(range(count))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * GROUP_TOUCH_PX + 1,) * 2)
    grown = [cv2.dilate(m.astype(np.uint8), kernel).astype(bool) for m in masks]
    for a in range(count):
        for b in range(a + 1, count):
            near = max(disparities[a], disparities[b])
            similar = abs(disparities[a] - disparities[b]) <= GROUP_DISPARITY_TOLERANCE * near
            if similar and (grown[a] & grown[b]).any():
                parent[root(a)] = root(b)
    members: dict[int, list[int]] = {}
    for k in range(count):
        members.setdefault(root(k), []).append(k)
    cards = []
    for group in members.values():
        owner = np.full(masks[group[0]].shape, -1, np.int32)
        for k in group:
            owner[masks[k] & (owner < 0)] = k
        mask = (owner >= 0) | bridge_gaps(owner, 2 * GROUP_TOUCH_PX)
        if len(group) > 1:
            mask |= narrow_background(mask)
        cards.append((mask, max(disparities[k] for k in group)))
    return cards


def narrow_background(mask: np.ndarray) -> np.ndarray:
    """Background pixels beside a group card in a strip narrower than GROUP_SLIVER_PX: what
    the row and column bridges left between people (a slit between two arms), which would
    otherwise stand out of the group as a torn shard of wall."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (GROUP_SLIVER_PX + 1,) * 2)
    background = (~mask).astype(np.uint8)
    wide = cv2.morphologyEx(background, cv2.MORPH_OPEN, kernel, borderValue=1) > 0
    return ~mask & ~wide


def bridge_gaps(owner: np.ndarray, max_gap_px: int) -> np.ndarray:
    """Pixels on a straight row or column run between two different members' pixels, at most
    max_gap_px long: the background seen between people standing together."""
    bridge = np.zeros(owner.shape, bool)
    for grid, out in ((owner, bridge), (owner.T, bridge.T)):
        rows, cols = np.nonzero(grid >= 0)
        same_row = rows[1:] == rows[:-1]
        gap = cols[1:] - cols[:-1] - 1
        between = grid[rows[1:], cols[1:]] != grid[rows[:-1], cols[:-1]]
        for k in np.nonzero(same_row & between & (gap > 0) & (gap <= max_gap_px))[0]:
            out[rows[k], cols[k] + 1:cols[k + 1]] = True
    return bridge


def find_instances(image: np.ndarray,
                   saliency: Callable[[], np.ndarray | None] | None = None) -> list[Instance]:
    """Salient objects (people, vehicles, animals) with masks, following the paper's rules.

    saliency gives ISNet's map when an object needs it (SceneContext passes its own, so the
    pop-up cards reuse the same run: ISNet is most of the depth stage's time); by default it
    is computed here.
    """
    shape = image.shape[:2]
    detections = detect(image)
    objects = [
        d for d in detections
        if d.class_name in paper.SALIENT_CLASSES and d.score >= paper.SALIENT_SCORE_MIN
    ]
    if not objects:  # a cup or a chair alone: nothing to shape, so no network to run
        return []
    salient_map = saliency() if saliency is not None else salient_mask(image)
    labels = semantic_labels(image)
    salient = salient_map > SALIENT_THRESHOLD if salient_map is not None else None
    if salient is not None:
        band = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SNAP_BAND_PX + 1,) * 2)
        within_band = cv2.dilate(salient.astype(np.uint8), band) > 0

    def shape_mask(detection: Detection) -> np.ndarray:
        in_box = _box_mask(shape, detection.box)
        parts = []
        if labels is not None and detection.class_name in VOC_INDEX_OF:
            of_class = (labels == VOC_INDEX_OF[detection.class_name]) & in_box
            if salient is not None and \
                    (of_class & salient).sum() >= CLASS_COVER_MIN * of_class.sum():
                of_class &= within_band
            parts.append(of_class)
        if salient is not None:
            parts.append(salient)
        if not parts:
            return in_box
        others = np.zeros(shape, bool)
        for other in objects:
            if other is not detection:
                others |= _box_mask(shape, other.box)
        mask = own_pieces(in_box & np.logical_or.reduce(parts),
                          _box_core(shape, detection.box), others)
        if salient is not None:
            mask |= beyond_the_box(mask, salient, detection.box, others)
        return mask

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
    if salient is not None:  # the jaw keeps ISNet's outline, not DeepLab's coarse one
        slack = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * JAW_SALIENT_SLACK_PX + 1,) * 2)
        near_salient = cv2.dilate(salient.astype(np.uint8), slack) > 0
    heads = [head_region(d.box, shape) if d.class_name == "person" else None for d in objects]
    kept = []
    for detection, mask, head in zip(objects, masks, heads, strict=True):
        # fur and feathers are no colour edge either: an animal keeps the network's outline
        snapped = (mask if detection.class_name in FURRED_CLASSES
                   else snap_to_colour_edges(mask, image, salient_map))
        if detection.class_name == "person":  # nor is a jaw's retouched rim: it is kept
            jaw = jaw_region(mask, detection.box)
            snapped = np.where(jaw, mask if salient is None else mask & near_salient, snapped)
            if salient is not None:
                snapped = snapped & ~thin_skirt(snapped, near_salient)
        mask = with_strands(clean_mask(snapped, keep=head), snapped)
        # the face is its main pieces (a stray pixel of it is no face to keep whole)
        face = drop_fragments(mask & head, min_px=0) if head is not None else None
        mask = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
        if face is not None:  # the face is never shaved: it stays whole on its card
            mask |= face
        kept.append((detection, mask, face))
    untangled = untangle_overlaps([mask for _, mask, _ in kept], [face for _, _, face in kept],
                                  image)
    kept = [(detection, mask, face)
            for (detection, _, face), mask in zip(kept, untangled, strict=True)]
    instances = []
    for detection, mask, face in kept:
        for _, _, other_face in kept:  # nor taken by another card
            if other_face is not None and other_face is not face:
                mask = mask & ~other_face
        mask = drop_fragments(mask, face)
        if mask.sum() < max(paper.SALIENT_MASK_MIN_PX, FRAGMENT_MIN_PX):
            continue
        ys, xs = np.nonzero(mask)
        box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
        instances.append(Instance(detection.class_name, detection.score, box, mask, face))
    log.debug("found %d salient instance(s)", len(instances))
    return instances
