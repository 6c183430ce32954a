"""Object boundaries on a synthetic layered scene: ghosts, tears and edge alpha error.

    .venv/bin/python benchmarks/bench_layers.py [--map-long-side N] [PHOTO ...]

A magenta cut-out (a colour absent from the backgrounds) with soft blurred edges, a thin pole,
a thin wire and a spiky star is composited over real photos from ../shared/photos and rendered
at 1920x1080 from its exact depth map (`<stem>.depth.png` beside the composite: the cut-out a
flat card at the nearest depth, the photo a receding plane behind it) and a fixed pair of
crops. The nearest surface follows the crops exactly, so the cut-out's true alpha in any frame
is the 2D crop of its alpha. Per frame:

- ghost: pixels more than 3 px outside the true silhouette (where the true alpha itself would
  leave a visible trace) with a visible trace of magenta (min(R, B) - G above TRACE_LEVEL),
  per 1000 pixels of the silhouette (true alpha >= 0.5);
- tear: pixels more than 3 px inside it whose magenta level fell below half, per 1000;
- edge error: mean |alpha - true alpha| within 4 px of the edge, alpha read from the magenta
  level (the backgrounds' own level makes the start frame's error the baseline);
- fill PSNR: the frame against the truth (the photo alone, rendered over the background plane
  alone: what the cut-out hides) outside the silhouette and within FILL_BAND_PX of it, where
  the fill shows; only the fill, and ghosts, make the two differ there.

Goals at the end view: ghost <= 1, tear <= 1, edge error <= the start frame's + 0.01.

--map-long-side N writes the depth map N px on its long side (area-averaged, so its edges are
soft ramps, as a depth network's output or a phone's depth map is): the path those sources
take, refinement onto the photo's colour edges included. Detail thinner than the map's pixels
(the wire, the star's tips) is then not in the depth at all.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kbbatch.camera import Crop, Plan, crop_at, working_size
from kbbatch.images import read_image
from kbbatch.pipeline import ClipOptions, frame_at, prepare_scene
from kbbatch.presets import Preset, load_preset

SHARED = Path(__file__).resolve().parents[2] / "shared"
PHOTOS = ("33_landscape_sign_in_field.jpg", "22_urban_windmill_village.jpg",
          "36_landscape_lighthouse.jpg")
MAGENTA = np.array([255, 0, 255], np.float32)
TRACE_LEVEL = 24
"""A magenta level (min(R, B) - G) above this is a visible trace: about 10 % of the cut-out."""
OUTSIDE_PX = 3
EDGE_PX = 4
SCENE_LONG_SIDE_PX = 2048
FILL_BAND_PX = 80
"""Fill PSNR is measured this far (output px) around the true silhouette."""
TIMES = (0.0, 0.5, 1.0)
SAVE_FRAMES = Path(os.environ["BENCH_LAYERS_FRAMES"]) if os.environ.get("BENCH_LAYERS_FRAMES") \
    else None
"""Where the frames are written for looking at, when BENCH_LAYERS_FRAMES names a folder."""


@dataclass(frozen=True)
class LayeredScene:
    photo_path: Path
    alpha: np.ndarray  # (H, W) float32, the cut-out's true alpha at the composite's size
    plan: Plan


def cutout_alpha(height: int, width: int) -> np.ndarray:
    """A soft blob, a thin pole, a thin wire and a spiky star, in the middle of the frame."""
    canvas = np.zeros((height, width), np.float32)
    unit = width / 100
    centre = (int(width * 0.42), int(height * 0.55))
    cv2.ellipse(canvas, centre, (int(9 * unit), int(13 * unit)), 0, 0, 360, 1.0, -1,
                cv2.LINE_AA)
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.25 * unit)  # soft edges
    pole_x = int(width * 0.58)
    cv2.line(canvas, (pole_x, int(height * 0.25)), (pole_x, int(height * 0.8)), 1.0,
             max(2, int(0.35 * unit)), cv2.LINE_AA)
    cv2.line(canvas, (int(width * 0.3), int(height * 0.3)), (pole_x, int(height * 0.35)), 1.0,
             max(1, int(0.12 * unit)), cv2.LINE_AA)
    star_centre = np.array([width * 0.66, height * 0.6])
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    radii = np.where(np.arange(24) % 2 == 0, 8 * unit, 2.5 * unit)
    star = star_centre + np.stack([np.cos(angles) * radii, np.sin(angles) * radii], axis=1)
    cv2.fillPoly(canvas, [np.round(star * 16).astype(np.int32)], 1.0, cv2.LINE_AA, shift=4)
    return np.clip(canvas, 0.0, 1.0)


def build_scene(photo_path: Path, folder: Path, end_shift_px: tuple[float, float] = (70, 30),
                map_long_side_px: int | None = None) -> LayeredScene:
    """Composite, depth map (exact, or area-averaged to map_long_side_px) and crops for one
    background photo, written to folder."""
    photo = read_image(photo_path)
    scale = SCENE_LONG_SIDE_PX / max(photo.shape[:2])
    photo = cv2.resize(photo, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    height, width = photo.shape[:2]
    alpha = cutout_alpha(height, width)
    composite = photo * (1 - alpha[..., None]) + MAGENTA * alpha[..., None]
    stem = "cutout_" + photo_path.stem
    path = folder / f"{stem}.png"
    cv2.imwrite(str(path), cv2.cvtColor(np.clip(composite + 0.5, 0, 255).astype(np.uint8),
                                        cv2.COLOR_RGB2BGR))
    rows = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    disparity = np.broadcast_to(0.2 + 0.2 * rows, (height, width)).copy()  # receding plane
    disparity[alpha >= 0.5] = 1.0  # the cut-out: a flat card, the nearest surface
    depth = 1.0 / disparity
    depth_png = np.round(depth / depth.max() * 65535).astype(np.uint16)
    if map_long_side_px:
        factor = map_long_side_px / max(height, width)
        depth_png = cv2.resize(depth_png, None, fx=factor, fy=factor,
                               interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(folder / f"{stem}.depth.png"), depth_png)
    # The control: the photo alone over the same depth and crops, for the photo's own traces.
    cv2.imwrite(str(folder / f"control_{photo_path.stem}.png"),
                cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(folder / f"control_{photo_path.stem}.depth.png"), depth_png)
    # The truth: the photo alone over the plane alone, with a speck of the cut-out's depth far
    # from it (beside a crop's edge), so that both scenes' depths are scaled alike.
    cv2.imwrite(str(folder / f"truth_{photo_path.stem}.png"),
                cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    plane = np.broadcast_to(0.2 + 0.2 * rows, (height, width)).copy()
    speck_y, speck_x = int(0.3 * height), int(0.85 * width)
    plane[speck_y:speck_y + 6, speck_x:speck_x + 6] = 1.0
    truth_png = np.round(1.0 / plane / depth.max() * 65535).astype(np.uint16)
    if map_long_side_px:
        truth_png = cv2.resize(truth_png, depth_png.shape[::-1], interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(folder / f"truth_{photo_path.stem}.depth.png"), truth_png)
    work_w, work_h = working_size(width, height)
    start_w = 0.97 * min(work_w, work_h * 16 / 9)
    start = Crop(work_w / 2, work_h / 2, start_w, start_w * 9 / 16)
    end = Crop(work_w / 2 + end_shift_px[0], work_h / 2 + end_shift_px[1],
               start.width_px / 1.25, start.height_px / 1.25)
    return LayeredScene(path, alpha, Plan(start, end, planner="manifest"))


def true_alpha(scene: LayeredScene, t: float, width: int, height: int) -> np.ndarray:
    """The cut-out's alpha in the frame at t: the crop at t of its alpha, at the output size."""
    crop = crop_at(scene.plan, t)
    to_source = scene.alpha.shape[1] / working_size(*scene.alpha.shape[::-1])[0]
    sx = crop.width_px * to_source / width
    sy = crop.height_px * to_source / height
    matrix = np.array([[sx, 0, crop.left_px * to_source + 0.5 * sx - 0.5],
                       [0, sy, crop.top_px * to_source + 0.5 * sy - 0.5]], np.float32)
    return cv2.warpAffine(scene.alpha, matrix, (width, height),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def magenta_level(frame: np.ndarray) -> np.ndarray:
    pixels = frame.astype(np.float32)
    return np.minimum(pixels[..., 0], pixels[..., 2]) - pixels[..., 1]


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)


def boundary_scores(frame: np.ndarray, alpha: np.ndarray, control: np.ndarray | None = None
                    ) -> tuple[float, float, float]:
    """(ghost per 1000, tear per 1000, mean edge alpha error) of one frame. With a control
    frame (the photo alone, same depth and view), a trace the photo itself has there within
    1 px (a red jacket, a pink roof) is not counted as ghost."""
    level = magenta_level(frame)
    silhouette = (alpha >= 0.5).astype(np.uint8)
    area = max(1, int(silhouette.sum()))

    any_trace = (alpha > TRACE_LEVEL / 255).astype(np.uint8)  # the soft edge's visible tail
    outside = cv2.dilate(any_trace, _disk(OUTSIDE_PX)) == 0
    inside = cv2.erode(silhouette, _disk(OUTSIDE_PX)) > 0
    edge = (cv2.dilate(silhouette, _disk(EDGE_PX)) > 0) & (cv2.erode(silhouette, _disk(EDGE_PX))
                                                         == 0)
    if control is not None:
        own = cv2.dilate((magenta_level(control) > TRACE_LEVEL).astype(np.uint8), _disk(1)) > 0
        outside &= ~own
    ghost = 1000 * float((outside & (level > TRACE_LEVEL)).sum()) / area
    tear = 1000 * float((inside & (level < 127.5)).sum()) / area
    estimated = np.clip(level / 255.0, 0.0, 1.0)
    edge_error = float(np.abs(estimated - alpha)[edge].mean())
    return ghost, tear, edge_error


def fill_psnr(frame: np.ndarray, truth: np.ndarray, alpha: np.ndarray) -> float:
    """PSNR (dB) of frame against truth outside the silhouette's visible trace and within
    FILL_BAND_PX of it."""
    any_trace = (alpha > TRACE_LEVEL / 255).astype(np.uint8)
    outside = cv2.dilate(any_trace, _disk(OUTSIDE_PX)) == 0
    band = outside & (cv2.dilate(any_trace, _disk(FILL_BAND_PX)) > 0)
    error = frame.astype(np.float32)[band] - truth.astype(np.float32)[band]
    return float(10 * np.log10(255.0 ** 2 / max(float(np.mean(error ** 2)), 1e-6)))


def measure(scene: LayeredScene, preset: Preset, times=TIMES) -> list[tuple[float, ...]]:
    """(ghost, tear, edge error, ghost not photo, fill PSNR) per time for one layered scene,
    rendered through the whole pipeline."""
    options = ClipOptions(threads=1, cache_depth=False)

    def prepared(prefix: str):
        path = scene.photo_path.with_name(scene.photo_path.name.replace("cutout_", prefix, 1))
        ready = prepare_scene(read_image(path), path, preset, options, {}, plan=scene.plan)
        assert ready.depth_backend == "file", ready.depth_backend
        return ready

    cutout, control, truth = (prepared(prefix) for prefix in ("cutout_", "control_", "truth_"))
    rows = []
    for t in times:
        frame = frame_at(cutout, preset, t)
        if SAVE_FRAMES:
            cv2.imwrite(str(SAVE_FRAMES / f"{scene.photo_path.stem}_{t:.2f}.png"),
                        cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        alpha = true_alpha(scene, t, preset.width_px, preset.height_px)
        rows.append((*boundary_scores(frame, alpha),
                     boundary_scores(frame, alpha, frame_at(control, preset, t))[0],
                     fill_psnr(frame, frame_at(truth, preset, t), alpha)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photos", nargs="*", default=list(PHOTOS))
    parser.add_argument("--map-long-side", type=int, default=None,
                        help="depth map size (px, long side); default: exact, as the composite")
    args = parser.parse_args()
    preset = load_preset("slideshow")
    print(f"{'photo':<34}{'t':>5}{'ghost/1000':>12}{'tear/1000':>11}{'edge err':>10}"
          f"{'ghost not photo':>17}{'fill PSNR':>11}")
    with tempfile.TemporaryDirectory() as folder:
        for name in args.photos:
            scene = build_scene(SHARED / "photos" / name, Path(folder),
                                map_long_side_px=args.map_long_side)
            for t, (ghost, tear, edge, excess, fill) in zip(TIMES, measure(scene, preset),
                                                            strict=True):
                print(f"{Path(name).stem[:33]:<34}{t:>5.2f}{ghost:>12.2f}{tear:>11.2f}"
                      f"{edge:>10.3f}{excess:>17.2f}{fill:>11.2f}")


if __name__ == "__main__":
    main()
