"""Planner quality and speed over ../shared/photos.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_planners.py

Per photo: planning seconds of `auto`, and the disoccluded fraction of the (unfilled) end view
for auto, center, and the reference's objective alone (minimum disocclusion, no saliency or
motion terms). Depth is the default backend's (auto), computed once per photo; the planners see
what they see in a render (ISNet's map included).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kbbatch import paper
from kbbatch.camera import depth_from_disparity, working_size
from kbbatch.images import list_images, read_image
from kbbatch.pipeline import ClipOptions, cached_disparity, plan_request, resize_to
from kbbatch.planners import get_planner
from kbbatch.planners.auto import AutoPlanner, plan_disocclusion
from kbbatch.presets import load_preset

PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"


def main() -> int:
    if not PHOTOS.is_dir():
        print(f"photos not found at {PHOTOS} (../shared is developer/CI only)")
        return 2
    preset = load_preset(sys.argv[1] if len(sys.argv) > 1 else "slideshow")
    planners = {
        "auto": get_planner("auto"),
        "center": get_planner("center"),
        "reference objective": AutoPlanner(use_saliency=False, use_motion=False),
    }
    print(f"preset {preset.name}; disoccluded fraction of the end view (lower is better)")
    print(f"{'photo':<42}{'auto s':>8}{'auto':>9}{'center':>9}{'reference':>11}")
    rows = []
    for photo in list_images(PHOTOS):
        image = read_image(photo)
        width, height = working_size(image.shape[1], image.shape[0])
        working = resize_to(image, width, height)
        depth_result = cached_disparity(working, photo, ClipOptions())
        depth = depth_from_disparity(depth_result.disparity, paper.focal_px(max(width, height)))
        request = plan_request(working, depth_result, depth, preset)  # as a render plans
        values, seconds = [], 0.0
        for name, planner in planners.items():
            started = time.perf_counter()
            plan = planner.plan(request)
            if name == "auto":
                seconds = time.perf_counter() - started
            values.append(plan_disocclusion(request, plan))
        rows.append([seconds, *values])
        print(f"{photo.name[:41]:<42}{seconds:>8.2f}" + "".join(
            f"{v:>9.4f}" if i < 2 else f"{v:>11.4f}" for i, v in enumerate(values)))
    table = np.array(rows)
    auto_better = int(np.sum(table[:, 1] < table[:, 2]))
    auto_tied = int(np.sum(table[:, 1] == table[:, 2]))
    print(f"{'mean':<42}{table[:, 0].mean():>8.2f}{table[:, 1].mean():>9.4f}"
          f"{table[:, 2].mean():>9.4f}{table[:, 3].mean():>11.4f}")
    print(f"auto reveals less than center on {auto_better} of {len(rows)} photos "
          f"(tied on {auto_tied}); total planning {table[:, 0].sum():.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
