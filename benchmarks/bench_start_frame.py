"""Fill in the first frame: how much of it the extension's fill changes.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_start_frame.py [PHOTO ...]

The fill is what the photo does not show, so at the start of the move (the photo's own view
for the planners' start crop) it should stay hidden behind the photo's own points. Per photo
(default: all of ../shared/photos, slideshow preset), the first frame is rendered from the
extended cloud and from the same scene with the extension switched off (kbbatch.inpaint's
extend_at_view made to add nothing), and the share of pixels that differ by more than 10
and by more than 30 levels is printed. Before session 24, fill made inside the move lay level
with a farther object's soft rim where three depths meet, and showed there (0.086 % of a
photo of rowing boats, 0.063 % of one of cups, 0.006 % of photo 15).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from kbbatch import inpaint
from kbbatch.images import read_image
from kbbatch.pipeline import ClipOptions, frame_at, prepare_scene
from kbbatch.presets import load_preset
from kbbatch.render import PointCloud

SHARED_PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"
LEVELS = (10, 30)


def no_extension(cloud, view, disparity_scale, region, working_scale, inpainter=None):
    """extend_at_view's stand-in: the view's holes are left as they are."""
    empty = np.empty(0, np.float32)
    return PointCloud(empty, empty, empty, np.empty((0, 3), np.uint8)), 0


def first_frame(photo_path: Path, extended: bool) -> np.ndarray:
    preset = load_preset("slideshow")
    options = ClipOptions(threads=2, cache_depth=True)
    real = inpaint.extend_at_view
    if not extended:
        inpaint.extend_at_view = no_extension
    try:
        prepared = prepare_scene(read_image(photo_path), photo_path, preset, options, {})
    finally:
        inpaint.extend_at_view = real
    return frame_at(prepared, preset, 0.0).astype(np.int16)


def main() -> int:
    photos = [Path(p) for p in sys.argv[1:]] or sorted(
        p for p in SHARED_PHOTOS.glob("*") if p.suffix.lower() in (".jpg", ".png"))
    if not photos:
        print(f"no photos given and none in {SHARED_PHOTOS} (../shared is only on developer "
              "and CI machines)")
        return 2
    print(f"{'photo':<40}" + "".join(f"{f'> {level} levels':>16}" for level in LEVELS))
    for photo in photos:
        change = np.abs(first_frame(photo, True) - first_frame(photo, False)).max(axis=-1)
        print(f"{photo.name[:39]:<40}"
              + "".join(f"{100 * np.mean(change > level):>15.3f}%" for level in LEVELS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
