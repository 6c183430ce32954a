"""Camera planners: plug-ins that choose the start and end crop of each clip.

A planner is any object with a `name` and a `plan(request) -> Plan` method. Register new
ones in PLANNERS; the CLI's --planner and the manifest pick them by name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from kbbatch.camera import Plan
from kbbatch.presets import Preset


@dataclass(frozen=True)
class PlanRequest:
    """Everything a planner may look at, at the working size (long side 1024)."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32, working units (nearest surface at f)
    preset: Preset


class Planner(Protocol):
    name: str

    def plan(self, request: PlanRequest) -> Plan: ...


class UnknownPlannerError(ValueError):
    pass


def get_planner(name: str) -> Planner:
    """A planner by name."""
    from kbbatch.planners.auto import AutoPlanner
    from kbbatch.planners.center import CenterPlanner, TwoDPlanner

    known: dict[str, Planner] = {
        "auto": AutoPlanner(), "center": CenterPlanner(), "2d": TwoDPlanner(),
    }
    if name not in known:
        raise UnknownPlannerError(
            f"unknown planner {name!r}; available: {', '.join(sorted(known))}"
        )
    return known[name]


PLANNER_NAMES = ("auto", "center", "2d")
