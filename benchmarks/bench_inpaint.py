"""Filling disocclusions: coverage, cost, stability, and quality against real second views.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_inpaint.py

1. Per clip (a few photos, the auto planner, the preview size): uncovered pixels per frame
   rendering the plain cloud and the extended cloud (mean and max over frames), the fill's
   seconds at 1024 px, and the max / median ratio of the mean change between consecutive
   frames (spikes would show flicker), plus whether rendering one time twice is identical.
2. Over ../shared/eval/views: the left image is rendered at the right camera with the true
   disparity, holes filled, and compared with the real right image: PSNR and SSIM over the
   pixels the left view can see, over the disoccluded pixels alone, and in a band of 8 px
   around the depth edges of the rendered view. Rows: no fill, OpenCV
   Telea on the frame, ours (fill once in colour and depth, extend the cloud, render), and
   the true fill (the real right image in every hole): what no fill can beat, since the
   pixels outside the holes are the render's.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from kbbatch import paper
from kbbatch.camera import SceneGeometry, View, depth_from_disparity, output_view, working_view
from kbbatch.images import read_image
from kbbatch.inpaint import build_extended_cloud, extend_at_view, snap_edge_depth
from kbbatch.pipeline import ClipOptions, frame_at, frame_times, prepare_scene
from kbbatch.presets import load_preset
from kbbatch.render import back_project, depth_edges, render, render_frame, to_uint8

SHARED = Path(__file__).resolve().parents[2] / "shared"
EDGE_BAND_PX = 8
"""The band around depth edges in the novel view: this many pixels either side."""
CLIP_PHOTOS = ("03_portrait_two_people_obama_biden.jpg", "10_animal_giraffe.jpg",
               "33_landscape_sign_in_field.jpg")
VIEWS = {
    "middlebury2003_cones_Q": ("im2.png", "im6.png", "disp2.png", 0.25),
    "middlebury2003_teddy_Q": ("im2.png", "im6.png", "disp2.png", 0.25),
    "middlebury2006_aloe_full": ("view1.jpg", "view5.jpg", "disp1.png", 1.0),
    "middlebury2014_motorcycle_Q": ("im0.png", "im1.png", "disp0GT.pfm", 1.0),
    "kitti2015_000046": ("image_2_000046_10.png", "image_3_000046_10.png",
                         "disp_occ_0_000046_10.png", 1 / 256),
}


def read_pfm(path: Path) -> np.ndarray:
    """A PFM image: header, then float32 rows bottom-up; a negative scale is little-endian."""
    with path.open("rb") as handle:
        kind = handle.readline().strip()
        width, height = (int(v) for v in handle.readline().split())
        scale = float(handle.readline())
        channels = 3 if kind == b"PF" else 1
        data = np.fromfile(handle, "<f4" if scale < 0 else ">f4", width * height * channels)
    return np.flipud(data.reshape(height, width, channels).squeeze()).astype(np.float32)


def read_disparity(path: Path) -> np.ndarray:
    if path.suffix == ".pfm":
        return read_pfm(path)
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32)


def clip_rows() -> None:
    preset = load_preset("preview")
    options = ClipOptions(planner="auto")
    print("clip coverage (preview 640x360, auto planner)")
    print(f"{'photo':<40}{'uncov plain':>13}{'max':>8}{'uncov ext':>11}{'max':>8}"
          f"{'fill s @1024':>14}{'flicker':>9}{'same':>6}")
    for name in CLIP_PHOTOS:
        photo_path = SHARED / "photos" / name
        photo = read_image(photo_path)
        prepared = prepare_scene(photo, photo_path, preset, options, {})
        scene, plan = prepared.scene, prepared.plan
        depth = depth_from_disparity(prepared.disparity, scene.focal_px)
        working = cv2.resize(photo, (scene.width_px, scene.height_px), interpolation=cv2.INTER_AREA)
        started = time.perf_counter()
        build_extended_cloud(working, depth, plan, scene)
        fill_seconds = time.perf_counter() - started
        plain = back_project(working, snap_edge_depth(depth), working_view(scene, (0, 0, 0)))
        disparity_scale = scene.focal_px * paper.DISPARITY_MAX_PX
        before, after, changes = [], [], []
        previous = None
        for t in frame_times(preset):
            view = output_view(plan, scene, t, preset.width_px, preset.height_px)
            before.append(int((~render(plain, view, disparity_scale).covered).sum()))
            after.append(int((~render(prepared.cloud, view, disparity_scale).covered).sum()))
            frame = frame_at(prepared, preset, t).astype(np.float32)
            if previous is not None:
                changes.append(float(np.abs(frame - previous).mean()))
            previous = frame
        same = np.array_equal(frame_at(prepared, preset, 0.37),
                              frame_at(prepared, preset, 0.37))
        flicker = max(changes) / max(np.median(changes), 1e-9)
        print(f"{name[:39]:<40}{np.mean(before):>13.0f}{max(before):>8}{np.mean(after):>11.1f}"
              f"{max(after):>8}{fill_seconds:>14.2f}{flicker:>9.2f}{str(same):>6}")


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Structural similarity per pixel (Gaussian window, sigma 1.5) on grey levels."""
    a, b = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64) for x in (a, b))
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, (11, 11), 1.5)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    covariance = blur(a * b) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * covariance + c2)
            / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    error = np.mean((a[mask].astype(np.float64) - b[mask].astype(np.float64)) ** 2)
    return float(10 * np.log10(255**2 / max(error, 1e-9)))


def view_rows() -> None:
    print("\nnovel view vs the real right image (PSNR dB / SSIM)")
    columns = ("PSNR seen", "SSIM seen", "PSNR disocc", "SSIM disocc", "PSNR band", "SSIM band")
    print(f"{'pair':<30}{'method':<12}" + "".join(f"{c:>12}" for c in columns)
          + f"{'disocc %':>9}")

    def cells(values: list[float]) -> str:
        return "".join(f"{v:>12.3f}" if i % 2 else f"{v:>12.2f}" for i, v in enumerate(values))

    totals: dict[str, list[list[float]]] = {}
    for folder, (left_name, right_name, disparity_name, scale) in VIEWS.items():
        base = SHARED / "eval" / "views" / folder
        left, right = read_image(base / left_name), read_image(base / right_name)
        disparity = read_disparity(base / disparity_name) * scale
        valid = np.isfinite(disparity) & (disparity > 0)
        height, width = disparity.shape
        focal = width / 2  # any focal works: depth = f * baseline / disparity, baseline 1
        depth = np.where(valid, focal / np.where(valid, disparity, 1), np.inf).astype(np.float32)
        scene = SceneGeometry(width, height, float(depth[valid].min()))
        left_view = working_view(scene, (0.0, 0.0, 0.0))
        right_view = View((1.0, 0.0, 0.0), focal, width / 2, height / 2, width, height)
        cloud = back_project(left, depth, left_view, keep=valid)
        raw = render(cloud, right_view, focal)
        seen = np.ones((height, width), bool)
        # The right camera sits to the right, so a point moves left by its disparity: the
        # right view's last columns (as wide as the largest disparity) are outside the left's.
        seen[:, width - int(np.ceil(disparity[valid].max())):] = False
        disoccluded = ~raw.covered & seen
        # The band around depth edges (holes count as the farthest surface), where a fill
        # meets the objects: EDGE_BAND_PX either side.
        far = float(np.max(raw.depth[raw.covered]))
        edges = depth_edges(np.where(raw.covered, raw.depth, far).astype(np.float32))
        kernel = np.ones((2 * EDGE_BAND_PX + 1,) * 2, np.uint8)
        band = (cv2.dilate(edges.astype(np.uint8), kernel) > 0) & seen
        outputs = {"no fill": to_uint8(raw.colour)}
        outputs["telea"] = cv2.inpaint(outputs["no fill"], (~raw.covered).astype(np.uint8) * 255,
                                       5, cv2.INPAINT_TELEA)
        added, _ = extend_at_view(cloud, right_view, focal, np.ones_like(seen), 1.0)
        outputs["ours"] = render_frame(cloud.extended(added), right_view, focal)
        # The ceiling of any fill: the true right image in every hole, the render elsewhere.
        outputs["true fill"] = np.where(raw.covered[..., None], outputs["no fill"], right)
        for method, image in outputs.items():
            similarity = ssim_map(image, right)
            row = []
            for mask in (seen, disoccluded, band):
                row += [psnr(image, right, mask), float(similarity[mask].mean())]
            totals.setdefault(method, []).append(row)
            print(f"{folder[:29]:<30}{method:<12}" + cells(row)
                  + f"{100 * disoccluded.mean():>9.2f}")
    print("(KITTI's ground truth is sparse LiDAR: most of its 'disoccluded' pixels are simply "
          "unknown)")
    dense = [k for k, folder in enumerate(VIEWS) if not folder.startswith("kitti")]
    for label, picked in (("mean", slice(None)), ("mean, dense truth only", dense)):
        for method, rows in totals.items():
            means = np.mean(np.asarray(rows)[picked], axis=0)
            print(f"{label:<30}{method:<12}" + cells(list(means)))


def main() -> int:
    if not SHARED.is_dir():
        print(f"{SHARED} not found (../shared is developer/CI only)")
        return 2
    clip_rows()
    view_rows()
    return 0


if __name__ == "__main__":
    sys.exit(main())
