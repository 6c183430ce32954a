"""Depth without a network, after the artists' technique the paper describes and "automatic
photo pop-up": a ground plane receding to a horizon, a far backdrop above it, and every salient
object an upright frontal card standing where it touches the ground.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from kbbatch.depth import DepthResult, SceneContext
from kbbatch.depth.ramp import HORIZON_FRACTION, ground_plane_disparity
from kbbatch.segment import (
    SALIENT_THRESHOLD,
    clean_mask,
    enclosed_holes,
    group_cards,
    with_strands,
)

HORIZON_RANGE = (0.15, 0.8)
"""The estimated horizon is kept within these fractions of the height, from the top."""

SKY_MIN_FRACTION = 0.05
"""Below this share of sky-like pixels the horizon falls back to the prior."""

SKY_GRADIENT_MAX = 12.0
"""Sky is smooth: its grey-level gradient (Sobel, blurred) stays under this."""

CARD_MIN_FRACTION = 0.01
"""Salient regions smaller than this share of the image do not become cards."""

CONTACT_MARGIN = 0.03
"""A horizon is kept at least this far (fraction of height) above where objects stand."""

FRAME_HOLE_FRACTION_MAX = 0.25
"""A salient region that encloses more background than this share of its extent is a frame
seen through (a bridge's tunnel of frames, an arch), not an upright object: its inner parts
are rarely at its depth, and as one card they slide over the far scene and tear it."""

LATTICE_SOLIDITY_MIN = 0.2
"""A salient region filling less than this share of its convex hull is a lattice or scattered
thin structure (a launch tower): as one flat card its bars tear from what they stand in."""

FLAT_OUTLINE_MAX = 0.4
"""A card whose outline runs through flat colour (no edge of the photo within 2 px of it) over
more than this share of its length is left on the ground: ISNet, unsure of a shape of one
colour (0.4 to 0.6 over all of it), cut it mid-colour, and the move tore notches into it and
left a strip of it behind. Measured on 34 photos and pictures: cards of photos 0 to 0.26 (a
cat's blurred fur against a blurred room), those torn 0.45 and 0.54."""

EDGE_STEP_MIN_LAB = 2.0
"""An edge a card may be cut along: the photo's colour changes by at least this (Lab units,
its largest channel) per pixel there."""

GROUNDED_EXCEPTIONS = ("bird",)
"""Classes that need not stand on the ground (they do not push the horizon up)."""

NOTCH_MOUTH_PX = 16
"""A salient card's notches and holes whose mouths are narrower than twice this (working px)
are candidates to join the card: ISNet left a guitar's fretboard, sound hole and a wedge of
its body out of the card (half-salient, 0.3 to 0.45), a notch open only to the neck, and the
move slid the card's body off the rest, filling the notch with a grey wedge of wall."""

NOTCH_SALIENCY_MIN = 0.3
"""... and join it where ISNet's map over them is at least this on average: the network was
unsure there, not sure of background (the gaps between a bench's legs, a wall between arms:
0.02 to 0.15)."""

CONTACT_GAP_PX = 8
"""A card stands at the ground's disparity of its lowest row; where its outline ends up to this
many rows (working px) above that row in a column, the ground there, farther than the card,
goes onto the card. Left on the ground, the lantern's bottom edge that its mask cut 3 to 5 px
short was a depth edge of its own, and the move bit dark notches into it."""


def sky_mask(image: np.ndarray) -> np.ndarray:
    """Smooth, bright or blue pixels connected to the top edge."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gradient = cv2.magnitude(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    gradient = cv2.blur(gradient, (9, 9))
    red, green, blue = (image[..., c].astype(np.float32) for c in range(3))
    sky_coloured = (blue >= red) & (blue >= green * 0.9) | (grey > 170)
    candidate = ((gradient < SKY_GRADIENT_MAX) & sky_coloured).astype(np.uint8)
    count, labels = cv2.connectedComponents(candidate, connectivity=4)
    top_labels = np.unique(labels[0][candidate[0] > 0])
    return np.isin(labels, top_labels[top_labels > 0])


def estimate_horizon(image: np.ndarray, contacts: list[float]) -> float:
    """Horizon height (fraction from the top): the sky's lower boundary, else the prior; kept
    above where grounded objects stand."""
    height = image.shape[0]
    sky = sky_mask(image)
    horizon = HORIZON_FRACTION
    if sky.mean() >= SKY_MIN_FRACTION:
        has_sky = sky.any(axis=0)
        lowest_sky = height - 1 - np.argmax(sky[::-1], axis=0)
        horizon = float(np.median(lowest_sky[has_sky])) / height
    if contacts:
        horizon = min(horizon, min(contacts) - CONTACT_MARGIN)
    return float(np.clip(horizon, *HORIZON_RANGE))


def salient_cards(context: SceneContext) -> list[tuple[np.ndarray, bool]]:
    """(mask, grounded) of every object to pop up: instances, else salient-mask components."""
    instances = context.instances
    if instances:
        return [(i.mask, i.class_name not in GROUNDED_EXCEPTIONS) for i in instances]
    saliency = context.saliency
    if saliency is None:
        return []
    binary = (saliency > SALIENT_THRESHOLD).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    minimum = CARD_MIN_FRACTION * binary.size
    large = [k for k in range(1, count) if stats[k, cv2.CC_STAT_AREA] >= minimum]
    cards = [(close_notches(clean_mask(labels == k), saliency,
                            np.isin(labels, [other for other in large if other != k])), k)
             for k in large]
    # Strands joining a card's pieces, and its thin tips, go with it once it is judged
    # upright without them: a dandelion's two stalks would make it a frame around the field
    # between them.
    return [(with_strands(card, labels == k), True) for card, k in cards
            if card.sum() >= minimum and stands_up(card)]


def flat_outline_share(mask: np.ndarray, edge_strength: np.ndarray) -> float:
    """The share of a card's outline (away from the image's border, where it is cut by the
    frame, not by colour) with no edge of the photo (edge_strengths) within 2 px of it."""
    mask_u8 = mask.astype(np.uint8)
    outline = (mask_u8 - cv2.erode(mask_u8, np.ones((3, 3), np.uint8))) > 0
    outline[:2] = outline[-2:] = False
    outline[:, :2] = outline[:, -2:] = False
    if not outline.any():
        return 0.0
    return float(np.mean(edge_strength[outline] < EDGE_STEP_MIN_LAB))


def edge_strengths(image: np.ndarray) -> np.ndarray:
    """Per pixel, the largest colour change per pixel (Lab, any channel) within 2 px."""
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    strength = np.zeros(image.shape[:2], np.float32)
    for channel in cv2.split(lab):
        step_x = cv2.Sobel(channel, cv2.CV_32F, 1, 0, ksize=3)
        step_y = cv2.Sobel(channel, cv2.CV_32F, 0, 1, ksize=3)
        strength = np.maximum(strength, cv2.magnitude(step_x, step_y) / 8)  # Sobel's sum: 8
    return cv2.dilate(strength, np.ones((5, 5), np.uint8))


def cut_along_edges(image: np.ndarray, cards: list[tuple[np.ndarray, bool]]
                    ) -> tuple[list[tuple[np.ndarray, bool]], int]:
    """The cards whose outlines follow the photo's edges (FLAT_OUTLINE_MAX), and how many
    were left on the ground."""
    if not cards:
        return cards, 0
    strength = edge_strengths(image)
    kept = [card for card in cards if flat_outline_share(card[0], strength) <= FLAT_OUTLINE_MAX]
    return kept, len(cards) - len(kept)


def close_notches(mask: np.ndarray, saliency: np.ndarray, others: np.ndarray) -> np.ndarray:
    """mask with its narrow-mouthed notches and holes that ISNet found half-salient, but not
    the pixels of other salient regions (others) lying in them: those are cards of their own."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * NOTCH_MOUTH_PX + 1,) * 2)
    closed = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    added = (closed.astype(bool) | (enclosed_holes(closed)[0] > 0)) & ~mask & ~others
    count, labels = cv2.connectedComponents(added.astype(np.uint8), connectivity=8)
    if count <= 1:
        return mask
    sums = np.bincount(labels.ravel(), weights=saliency.ravel(), minlength=count)
    areas = np.bincount(labels.ravel(), minlength=count)
    joins = sums >= NOTCH_SALIENCY_MIN * areas
    joins[0] = False
    return mask | joins[labels]


def stands_up(mask: np.ndarray) -> bool:
    """Whether a salient region (no detected object) can be an upright card: neither a frame
    enclosing much background nor a sparse lattice; without a card it keeps the ground plane
    and backdrop's depth, which never tears."""
    enclosed = int(enclosed_holes(mask)[1].sum())
    area = int(mask.sum())
    hull = np.zeros(mask.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(cv2.findNonZero(mask.astype(np.uint8))), 1)
    return (enclosed <= FRAME_HOLE_FRACTION_MAX * (area + enclosed)
            and area >= LATTICE_SOLIDITY_MIN * int(hull.sum()))


def popup_disparity(image: np.ndarray, cards: list[tuple[np.ndarray, bool]]) -> np.ndarray:
    """Ground plane and backdrop, with each card at the ground's disparity where it stands."""
    height, width = image.shape[:2]
    bottoms = [height - 1 - int(np.argmax(mask.any(axis=1)[::-1])) for mask, _ in cards]
    contacts = [(b + 1) / height for b, (_, grounded) in zip(bottoms, cards, strict=True)
                if grounded]
    horizon = estimate_horizon(image, contacts)
    ground = ground_plane_disparity(height, width, horizon)
    disparity = ground.copy()
    # Cards touching at a similar depth become one group; far cards first, so that nearer
    # ones cover them where they overlap.
    groups = group_cards([mask for mask, _ in cards], [float(ground[b, 0]) for b in bottoms])
    for mask, value in sorted(groups, key=lambda card: card[1]):
        disparity[down_to_contact(mask, CONTACT_GAP_PX)] = value
    return disparity


def down_to_contact(mask: np.ndarray, gap_px: int) -> np.ndarray:
    """mask, each column's outline extended down to the mask's lowest row where it ends at
    most gap_px rows above it."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return mask
    lowest = rows[-1]
    height = mask.shape[0]
    bottoms = height - 1 - np.argmax(mask[::-1], axis=0)  # each column's lowest pixel
    short = mask.any(axis=0) & (bottoms < lowest) & (lowest - bottoms <= gap_px)
    row_index = np.arange(height)[:, None]
    return mask | (short & (row_index > bottoms) & (row_index <= lowest))


class PopupDepth:
    name = "popup"

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: SceneContext
                  ) -> DepthResult:
        cards, flat = cut_along_edges(image, salient_cards(context))
        return DepthResult(popup_disparity(image, cards), self.name,
                           f"ground plane and {len(cards)} card(s)" + (
                               f"; {flat} salient region(s) left on the ground: its outline "
                               "runs through flat colour, where a card would tear" if flat
                               else ""))
