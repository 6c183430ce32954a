"""Output frames of a tight crop: rendered smaller where points land apart, then enlarged."""

import cv2
import numpy as np

from kbbatch.camera import Crop, Plan, View, crop_at, working_size
from kbbatch.depth import DepthOptions
from kbbatch.pipeline import (
    MAX_RENDER_SPACING_PX,
    ClipOptions,
    PreparedScene,
    frame_at,
    frame_times,
    point_spacing_px,
    prepare_scene,
    render_view,
    rendered_view,
)
from kbbatch.presets import Preset, load_preset, with_overrides


def centred_zoom(photo: np.ndarray, zoom: float) -> tuple[Preset, Plan, PreparedScene]:
    """A 1080p clip of the photo zooming into its centre, without parallax."""
    preset = with_overrides(load_preset("slideshow"), width_px=1920, height_px=1080)
    work_w, work_h = working_size(photo.shape[1], photo.shape[0])
    plan = Plan(Crop(work_w / 2, work_h / 2, work_w, work_h),
                Crop(work_w / 2, work_h / 2, work_w / zoom, work_h / zoom),
                planner="manifest", parallax=False)
    prepared = prepare_scene(photo, None, preset, ClipOptions(threads=1, cache_depth=False),
                             {}, plan=plan)
    return preset, plan, prepared


def test_a_frame_is_rendered_smaller_by_the_point_spacing_in_whole_steps():
    view = View((0.0, 0.0, 0.0), 1000.0, 960.0, 540.0, 1920, 1080)
    assert render_view(view, 1.25) is view  # the splats still blend neighbours
    assert render_view(view, 0.7) is view
    small = render_view(view, 1.8)
    assert (small.width_px, small.height_px) == (1376, 774)  # 86 of 120 steps of 16 x 9
    assert 1.28 < 1.8 * small.width_px / 1920 <= MAX_RENDER_SPACING_PX  # points 1.3 px apart
    scale = small.width_px / 1920
    assert small.height_px / 1080 == scale
    assert (small.focal_px, small.principal_x_px, small.principal_y_px) == (
        1000.0 * scale, 960.0 * scale, 540.0 * scale)
    # just past the threshold, one step down: enlarged by a ratio just above 1, linear
    # interpolation would band the frame in sharp and blurred columns
    assert render_view(view, 1.35).width_px == 1728  # 0.9 of the output
    odd = View((0.0, 0.0, 0.0), 1000.0, 500.5, 300.5, 1001, 601)  # no common divisor
    assert render_view(odd, 1.8) is odd


def test_a_tight_crop_of_a_small_photo_has_no_stair_steps_at_1080p():
    """Where points land 1.8 px apart, bilinear splats no longer interpolate between them:
    each pixel took its nearest point, and a slanted edge of a small photo came out as stairs
    of two-pixel steps at 1080p (a shoulder against a wall, photo 03). Without parallax the
    end frame must be the crop of the photo enlarged with linear interpolation."""
    height, width = 90, 160
    rows, cols = np.mgrid[0:height, 0:width]
    photo = np.where(((cols - 0.6 * rows) > 60)[..., None], 230, 30).astype(np.uint8)
    photo = np.repeat(photo, 3, axis=2)
    preset, plan, prepared = centred_zoom(photo, 1.5)
    frame = frame_at(prepared, preset, 1.0).astype(np.float32)
    crop, to_photo = crop_at(plan, 1.0), width / working_size(width, height)[0]
    step_x, step_y = crop.width_px * to_photo / 1920, crop.height_px * to_photo / 1080
    matrix = np.array([[step_x, 0, crop.left_px * to_photo + 0.5 * step_x - 0.5],
                       [0, step_y, crop.top_px * to_photo + 0.5 * step_y - 0.5]], np.float32)
    ideal = cv2.warpAffine(photo.astype(np.float32), matrix, (1920, 1080),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    error = np.abs(frame - ideal).mean(axis=-1)
    edge = cv2.dilate((np.abs(cv2.Sobel(ideal.mean(axis=-1), cv2.CV_32F, 1, 0)) > 1)
                      .astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert edge.sum() > 5000
    assert error[~edge].max() < 1, "the flat sides changed"
    assert error[edge].mean() < 2, f"stair steps: {error[edge].mean():.2f} levels off"


def test_a_straight_upright_line_across_the_horizon_bends_without_a_corner(monkeypatch):
    """Without a depth network the background is a ground plane below the horizon and a
    backdrop above it. Where the two met at one row, a window frame crossing the horizon
    (photo 20), or a launch tower (24), broke into two straight pieces at an angle as the
    camera moved sideways; the ground still shears it, but into a gentle curve. (So much that
    do no harm takes the parallax of such a photo away, tested in test_risk: its line budget
    is lifted here to look at the geometry itself.)"""
    monkeypatch.setattr("kbbatch.risk.LINE_BEND_MAX", float("inf"))
    monkeypatch.setattr("kbbatch.risk.LINE_TILT_MAX_DEG", float("inf"))
    height, width = 360, 640
    photo = np.full((height, width, 3), 90, np.uint8)
    photo[:, 398:402] = 220
    preset = with_overrides(load_preset("slideshow"), width_px=640, height_px=360)
    work_w, work_h = working_size(width, height)
    plan = Plan(Crop(work_w / 2, work_h / 2, work_w, work_h),
                Crop(work_w * 0.6, work_h / 2, work_w / 1.4, work_h / 1.4),
                planner="manifest", parallax=True)
    options = ClipOptions(threads=1, cache_depth=False, depth=DepthOptions(backend="ramp"))
    prepared = prepare_scene(photo, None, preset, options, {}, plan=plan)
    bright = np.clip(frame_at(prepared, preset, 1.0).astype(np.float32).mean(axis=-1) - 90,
                     0, None)
    line_x = (bright * np.arange(width)).sum(axis=1) / bright.sum(axis=1)
    rows = np.arange(height)

    def angle_deg(start: int, stop: int) -> float:
        return float(np.degrees(np.arctan(np.polyfit(rows[start:stop], line_x[start:stop],
                                                     1)[0])))

    total = abs(angle_deg(0, 60) - angle_deg(height - 60, height))
    window = 18
    sharpest = max(abs(angle_deg(row, row + window) - angle_deg(row - window, row))
                   for row in range(window, height - window))
    assert total > 8.0  # the ground does shear the line: there is parallax
    assert sharpest < 0.25 * total  # 17 degrees turned within 18 rows with the corner


def test_a_clip_whose_spacing_crosses_the_threshold_does_not_go_soft_at_one_frame():
    """A 1700 px photo's points land 1.16 px apart at the start of the move and 1.46 at its
    end. Rendered smaller only from the frame that crossed 1.3 px on, that frame went soft at
    once (the variance of the Laplacian fell from 373 to 142 between two frames): a visible
    jump in focus in the middle of the clip. Every frame of such a clip is rendered smaller."""
    height, width = 956, 1700
    rng = np.random.default_rng(7)
    photo = cv2.GaussianBlur(rng.integers(0, 256, (height, width, 3)).astype(np.uint8),
                             (0, 0), 0.8)
    preset, _, prepared = centred_zoom(photo, 1.25)
    times = frame_times(preset)
    spacings = [point_spacing_px(prepared, preset, t) for t in times]
    assert spacings[0] < MAX_RENDER_SPACING_PX < spacings[-1]
    widths = [rendered_view(prepared, preset, t).width_px for t in times]
    assert max(widths) < 1920 and widths == sorted(widths, reverse=True)
    crossing = next(i for i, spacing in enumerate(spacings) if spacing > MAX_RENDER_SPACING_PX)

    def sharpness(index: int) -> float:
        grey = cv2.cvtColor(frame_at(prepared, preset, times[index]), cv2.COLOR_RGB2GRAY)
        return float(cv2.Laplacian(grey.astype(np.float32), cv2.CV_32F).var())

    assert sharpness(crossing) > 0.9 * sharpness(crossing - 1)
