"""Contact sheets of the last forward frame of every shared photo, cropped at full size where
the depth changes most, for looking at object boundaries (ghosts, halos, tears, stair steps,
cracks, smeared fill).

    KBBATCH_MODELS=/work/shared/models .venv/bin/python benchmarks/contact_sheet.py OUT_DIR \
        [--preset slideshow] [PHOTO ...]

Writes OUT_DIR/sheet-N.png (a grid of CROP_WIDTH_PX x CROP_HEIGHT_PX crops, unscaled, each
labelled with the photo's name), OUT_DIR/<stem>.end.png (the whole end frame) and prints a table
of the crop's place and the seconds per stage. The crop is centred on the window of the end
view with the most depth-discontinuity pixels (the paper's test, mapped through the end crop),
which is where a broken boundary would show first.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from kbbatch.camera import Crop
from kbbatch.images import is_image_file, read_image
from kbbatch.pipeline import ClipOptions, frame_at, prepare_scene
from kbbatch.presets import Preset, load_preset
from kbbatch.render import depth_edges

SHARED_PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"
CROP_WIDTH_PX = 640
CROP_HEIGHT_PX = 360
SHEET_COLUMNS = 3
SHEET_ROWS = 3
LABEL_HEIGHT_PX = 22


def edge_window_origin(disparity: np.ndarray, end: Crop, preset: Preset) -> tuple[int, int]:
    """Top-left corner (x, y) in the end frame of the crop window holding the most depth-edge
    strength; parallax moves edges by a few pixels only, so the end crop maps them well."""
    # the paper's depth discontinuities, mapped to the end frame through the end crop
    scale_x = preset.width_px / end.width_px
    scale_y = preset.height_px / end.height_px
    affine = np.array([[scale_x, 0, -end.left_px * scale_x],
                       [0, scale_y, -end.top_px * scale_y]], np.float32)
    edges = depth_edges(1.0 / np.maximum(disparity, 1e-6)).astype(np.float32)
    strength = cv2.warpAffine(edges, affine, (preset.width_px, preset.height_px),
                              flags=cv2.INTER_LINEAR, borderValue=0)
    summed = cv2.boxFilter(strength, -1, (CROP_WIDTH_PX, CROP_HEIGHT_PX), normalize=False,
                           borderType=cv2.BORDER_CONSTANT)
    # only windows wholly inside the frame
    half_w, half_h = CROP_WIDTH_PX // 2, CROP_HEIGHT_PX // 2
    inner = summed[half_h:preset.height_px - half_h + 1, half_w:preset.width_px - half_w + 1]
    if inner.max() <= 0:  # no depth discontinuity in view: the centre
        return (preset.width_px - CROP_WIDTH_PX) // 2, (preset.height_px - CROP_HEIGHT_PX) // 2
    y, x = np.unravel_index(int(np.argmax(inner)), inner.shape)
    return int(x), int(y)


def labelled(crop: np.ndarray, label: str) -> np.ndarray:
    banner = np.full((LABEL_HEIGHT_PX, crop.shape[1], 3), 255, np.uint8)
    cv2.putText(banner, label, (4, LABEL_HEIGHT_PX - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([banner, crop])


def write_png(path: Path, rgb: np.ndarray) -> None:
    temporary = path.with_name(f".{path.name}.partial.png")
    if not cv2.imwrite(str(temporary), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write")
    temporary.replace(path)


def sheets(tiles: list[np.ndarray]) -> list[np.ndarray]:
    per_sheet = SHEET_COLUMNS * SHEET_ROWS
    blank = np.full_like(tiles[0], 128)
    out = []
    for start in range(0, len(tiles), per_sheet):
        group = tiles[start:start + per_sheet]
        group += [blank] * (-len(group) % SHEET_COLUMNS)
        rows = [np.hstack(group[i:i + SHEET_COLUMNS]) for i in range(0, len(group), SHEET_COLUMNS)]
        out.append(np.vstack(rows))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("photos", nargs="*", type=Path)
    parser.add_argument("--preset", default="slideshow")
    args = parser.parse_args()
    photos = args.photos or sorted(p for p in SHARED_PHOTOS.glob("*") if is_image_file(p))
    if not photos:
        print(f"no photos found in {SHARED_PHOTOS} (../shared is only on developer machines)")
        return 2
    preset = load_preset(args.preset)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    options = ClipOptions()
    tiles = []
    print(f"{'photo':<40}{'backend':>10}{'x':>6}{'y':>6}{'depth':>7}{'plan':>7}{'fill':>7}"
          f"{'end frame':>10}")
    for path in photos:
        timings: dict[str, float] = {}
        try:
            photo = read_image(path)
            prepared = prepare_scene(photo, path, preset, options, timings)
            clock = time.perf_counter()
            frame = frame_at(prepared, preset, 1.0)
            render_s = time.perf_counter() - clock
        except (ValueError, OSError) as error:
            print(f"{path.name}: skipped: {error}")
            continue
        x, y = edge_window_origin(prepared.disparity, prepared.plan.end, preset)
        write_png(args.out_dir / f"{path.stem}.end.png", frame)
        crop = frame[y:y + CROP_HEIGHT_PX, x:x + CROP_WIDTH_PX]
        tiles.append(labelled(crop, f"{path.stem} ({x},{y})"))
        print(f"{path.name[:39]:<40}{prepared.depth_backend[:9]:>10}{x:>6}{y:>6}"
              f"{timings['depth']:>7.2f}{timings['plan']:>7.2f}{timings['inpaint']:>7.2f}"
              f"{render_s:>10.2f}", flush=True)
    for index, sheet in enumerate(sheets(tiles), 1):
        write_png(args.out_dir / f"sheet-{index}.png", sheet)
    print(f"{len(tiles)} crops in {args.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
