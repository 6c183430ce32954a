"""Fill in the first frame: how much of it the extension's fill changes, and how far it is
from the photo.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_start_frame.py [PHOTO ...]

The fill is what the photo does not show, so at the start of the move (the photo's own view
for the planners' start crop) it should stay hidden behind the photo's own points. Per photo
(default: all of ../shared/photos, slideshow preset), the first frame is rendered from the
extended cloud and from the same scene with the extension switched off (kbbatch.inpaint's
extend_at_view made to add nothing), and the share of pixels that differ by more than 10
and by more than 30 levels is printed. Before session 24, fill made inside the move lay level
with a farther object's soft rim where three depths meet, and showed there (0.086 % of a
photo of rowing boats, 0.063 % of one of cups, 0.006 % of photo 15).

The last column compares the first frame with the photo itself, cut to the start crop and
resampled to the frame (area-averaged, then bilinear): the share of pixels more than 30 levels
apart, away from the frame's border. Resampling differs from the renderer's splats at fine
texture, so this is not zero; what the layers or the renderer get wrong adds to it (before
session 37, a card's soft edge near its foot blended into the ground and left grey blocks,
100 levels off, along the lantern's lower edge).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from kbbatch import inpaint
from kbbatch.images import read_image
from kbbatch.pipeline import ClipOptions, PreparedScene, frame_at, prepare_scene
from kbbatch.presets import load_preset
from kbbatch.render import PointCloud

SHARED_PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"
LEVELS = (10, 30)
PHOTO_LEVEL = LEVELS[-1]
BORDER_PX = 4


def no_extension(cloud, view, disparity_scale, region, working_scale, inpainter=None):
    """extend_at_view's stand-in: the view's holes are left as they are."""
    empty = np.empty(0, np.float32)
    return PointCloud(empty, empty, empty, np.empty((0, 3), np.uint8)), 0


def first_frame(photo_path: Path, photo: np.ndarray, extended: bool
                ) -> tuple[np.ndarray, PreparedScene]:
    preset = load_preset("slideshow")
    options = ClipOptions(threads=2, cache_depth=True)
    real = inpaint.extend_at_view
    if not extended:
        inpaint.extend_at_view = no_extension
    try:
        prepared = prepare_scene(photo, photo_path, preset, options, {})
    finally:
        inpaint.extend_at_view = real
    return frame_at(prepared, preset, 0.0).astype(np.int16), prepared


def photo_at_start(photo: np.ndarray, prepared: PreparedScene, width: int, height: int
                   ) -> np.ndarray:
    """The photo cut to the start crop at the frame's size: area-averaged to the frame's
    scale, then sampled bilinearly at the frame's pixel centres."""
    crop = prepared.plan.start
    # each side its own ratio: the working height is rounded
    to_photo_x = photo.shape[1] / prepared.scene.width_px
    to_photo_y = photo.shape[0] / prepared.scene.height_px
    step_x = crop.width_px * to_photo_x / width
    step_y = crop.height_px * to_photo_y / height
    small_size = (max(1, round(photo.shape[1] / step_x)), max(1, round(photo.shape[0] / step_y)))
    small = cv2.resize(photo, small_size, interpolation=cv2.INTER_AREA)
    shrink_x = small_size[0] / photo.shape[1]
    shrink_y = small_size[1] / photo.shape[0]
    to_small = np.float32([
        [step_x * shrink_x, 0, (crop.left_px * to_photo_x + 0.5 * step_x) * shrink_x - 0.5],
        [0, step_y * shrink_y, (crop.top_px * to_photo_y + 0.5 * step_y) * shrink_y - 0.5]])
    return cv2.warpAffine(small, to_small, (width, height), flags=cv2.INTER_LINEAR
                          | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def main() -> int:
    photos = [Path(p) for p in sys.argv[1:]] or sorted(
        p for p in SHARED_PHOTOS.glob("*") if p.suffix.lower() in (".jpg", ".png"))
    if not photos:
        print(f"no photos given and none in {SHARED_PHOTOS} (../shared is only on developer "
              "and CI machines)")
        return 2
    print(f"{'photo':<40}" + "".join(f"{f'> {level} levels':>16}" for level in LEVELS)
          + f"{f'photo > {PHOTO_LEVEL}':>16}")
    for photo in photos:
        pixels = read_image(photo)
        frame, prepared = first_frame(photo, pixels, True)
        change = np.abs(frame - first_frame(photo, pixels, False)[0]).max(axis=-1)
        height, width = frame.shape[:2]
        expected = photo_at_start(pixels, prepared, width, height).astype(np.int16)
        off = np.abs(frame - expected).max(axis=-1)[BORDER_PX:-BORDER_PX, BORDER_PX:-BORDER_PX]
        print(f"{photo.name[:39]:<40}"
              + "".join(f"{100 * np.mean(change > level):>15.3f}%" for level in LEVELS)
              + f"{100 * np.mean(off > PHOTO_LEVEL):>15.3f}%", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
