"""Camera planners: plug-ins that choose the start and end crop of each clip.

A planner is any object with a `name` and a `plan(request) -> Plan` method. Register new
ones in PLANNERS; the CLI's --planner and the manifest pick them by name (a manifest
entry with crops may name `2d` only: its crops, rendered without parallax).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from kbbatch.camera import Plan
from kbbatch.presets import Preset


def no_saliency() -> np.ndarray | None:
    return None


@dataclass(frozen=True)
class PlanRequest:
    """Everything a planner may look at, at the working size (long side 1024)."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32, working units (nearest surface at f)
    preset: Preset
    saliency: Callable[[], np.ndarray | None] = no_saliency
    """ISNet's salient-object probability (H, W), or None without the model: worked out on
    the first call (the depth stage's own when it ran), so a planner that does not ask for
    it pays nothing."""
    known_saliency: Callable[[], np.ndarray | None] = no_saliency
    """The same map where the depth stage worked it out (for its cards), else None: free to
    look at, never running ISNet."""


class Planner(Protocol):
    name: str

    def plan(self, request: PlanRequest) -> Plan: ...


class UnknownPlannerError(ValueError):
    pass


def get_planner(name: str) -> Planner:
    """A registered planner by name."""
    if name not in PLANNERS:
        raise UnknownPlannerError(
            f"unknown planner {name!r}; available: {', '.join(PLANNER_NAMES)}"
        )
    return PLANNERS[name]


# The registry: the CLI's --planner choices and the manifest's "planner" both come from it.
# Imported last because the planners import PlanRequest from this module.
from kbbatch.planners.auto import AutoPlanner  # noqa: E402
from kbbatch.planners.center import CenterPlanner, TwoDPlanner  # noqa: E402

PLANNERS: dict[str, Planner] = {p.name: p for p in (AutoPlanner(), CenterPlanner(), TwoDPlanner())}
PLANNER_NAMES = tuple(PLANNERS)
