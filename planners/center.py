"""The reference's plan without search, and the same crops as a plain 2D Ken Burns."""

from __future__ import annotations

from dataclasses import replace

from kbbatch import paper
from kbbatch.camera import Plan, fit_crop, zoomed
from kbbatch.planners import PlanRequest


def centred_plan(request: PlanRequest, name: str) -> Plan:
    """Start on the widest crop of the output aspect inside 97 % of the image, end zoomed."""
    height, width = request.depth.shape
    preset = request.preset
    wide = fit_crop(width, height, preset.aspect, paper.START_CROP_FRACTION)
    tight = zoomed(wide, preset.zoom)
    start, end = (wide, tight) if preset.zoom_direction == "in" else (tight, wide)
    return Plan(start=start, end=end, easing=preset.easing, planner=name)  # type: ignore[arg-type]


class CenterPlanner:
    name = "center"

    def plan(self, request: PlanRequest) -> Plan:
        return centred_plan(request, self.name)


class TwoDPlanner:
    """The paper's baseline: the centred crops, rendered without parallax."""

    name = "2d"

    def plan(self, request: PlanRequest) -> Plan:
        return replace(centred_plan(request, self.name), parallax=False)
