"""Semantic adjustment (paper section 3.1): each salient object becomes one upright card."""

from __future__ import annotations

import numpy as np

from kbbatch import paper
from kbbatch.segment import Instance, group_cards


def ground_contact_disparity(disparity: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """The largest disparity in the bottom 3 % of a box: where the object meets the ground."""
    x0, y0, x1, y1 = box
    rows = max(1, round(paper.GROUND_CONTACT_FRACTION * (y1 - y0)))
    return float(disparity[y1 - rows : y1, x0:x1].max())


def adjust(disparity: np.ndarray, instances: list[Instance]) -> np.ndarray:
    """Give every instance mask one disparity, its ground contact's; nearer objects win.

    Instances that touch at a similar disparity (people standing together) share one card.
    """
    adjusted = disparity.copy()
    values = [ground_contact_disparity(disparity, i.box) for i in instances]
    cards = group_cards([i.mask for i in instances], values)
    for mask, value in sorted(cards, key=lambda card: card[1]):
        adjusted[mask] = value
    return adjusted
