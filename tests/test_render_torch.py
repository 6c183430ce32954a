"""The torch frame renderer (the GPU backend) against the numba one, run on torch's CPU device."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from kbbatch import pipeline
from kbbatch.batch import run_folder
from kbbatch.camera import working_view
from kbbatch.device import TORCH_CPU
from kbbatch.images import read_image
from kbbatch.pipeline import ClipOptions, frame_times, prefetched, prepare_scene, render_view
from kbbatch.presets import with_overrides
from kbbatch.render import PointCloud, back_project, render_frame

from .conftest import shared_photos
from .test_crowds import real_models_or_skip
from .test_render import (
    DISPARITY_SCALE,
    FAR,
    NEAR,
    SCENE,
    H,
    W,
    card_scene,
    faint_veil_over_a_wall_with_gaps,
    shifted_view,
    soft_rim_on_a_card,
)

torch = pytest.importorskip("torch", reason="torch is not installed (pip install "
                            "'kbbatch[torch]'): the GPU renderer is not tested")
from kbbatch.render_torch import TorchRenderer, render_batches  # noqa: E402

MIN_PSNR_DB = 50.0
"""The torch renderer must make the same frames as the numba one, to this PSNR."""


REAL_PHOTOS = ("03_portrait_two_people_obama_biden", "10_animal_giraffe",
               "22_urban_windmill_village")
"""People, an animal against the sky over a ground plane, thin sails: soft layers and fill."""


def psnr_db(first: np.ndarray, second: np.ndarray) -> float:
    error = np.mean((first.astype(np.float64) - second.astype(np.float64)) ** 2)
    return float("inf") if error == 0 else float(10 * np.log10(255.0**2 / error))


def soft_card_cloud() -> PointCloud:
    """The test card scene with a soft-edged card: a ring of half-transparent points in front of
    the far plane's own points (as kbbatch.layers makes them), plus the plain opaque cloud."""
    image, depth = card_scene()
    view = working_view(SCENE, (0.0, 0.0, 0.0))
    solid = back_project(image, depth, view)
    ring = np.zeros(depth.shape, bool)
    ring[38:82, 58:102] = True
    ring[41:79, 61:99] = False
    alpha = np.where(ring, 120, 255).astype(np.uint8)
    near = np.full(depth.shape, NEAR, np.float32)
    fringe = back_project(np.full_like(image, (250, 20, 20)), near, view, keep=ring,
                          alpha=alpha)
    behind = back_project(image, np.full(depth.shape, FAR, np.float32), view, keep=ring)
    return solid.extended(fringe).extended(behind)


def test_soft_card_frames_match_numba_at_every_move():
    cloud = soft_card_cloud()
    assert cloud.opaque_count < len(cloud), "the scene must have soft points"
    views = [shifted_view(shift, zoom) for shift in (0.0, 6.0, -9.0, 14.0)
             for zoom in (1.0, 1.6)]
    frames = TorchRenderer(cloud, "cpu", DISPARITY_SCALE).render_frames(views).numpy()
    for view, frame in zip(views, frames, strict=True):
        expected = render_frame(cloud, view, DISPARITY_SCALE)
        assert psnr_db(frame, expected) >= MIN_PSNR_DB, view
        # A magnified view opens cracks and holes: both renderers fill them the same way.
        assert (np.abs(frame.astype(int) - expected.astype(int)).max(axis=-1) > 2).mean() < 1e-3


def test_a_faint_soft_edge_over_a_gap_is_composited_over_its_fill_as_numba_does():
    cloud, view = faint_veil_over_a_wall_with_gaps()
    for shifted in (view, shifted_view(3.0, 1.3)):
        frame = TorchRenderer(cloud, "cpu", DISPARITY_SCALE).render_frames([shifted]).numpy()[0]
        expected = render_frame(cloud, shifted, DISPARITY_SCALE)
        assert np.abs(frame.astype(int) - expected.astype(int)).max() <= 1, shifted
    assert frame[..., 1].min() >= 150, "a gap shows the veil's own colour"
    cloud, _, _, view = soft_rim_on_a_card()
    frame = TorchRenderer(cloud, "cpu", DISPARITY_SCALE).render_frames([view]).numpy()[0]
    np.testing.assert_array_equal(frame, render_frame(cloud, view, DISPARITY_SCALE))


def test_frames_rendered_smaller_are_enlarged_as_the_cpu_path_does():
    cloud = soft_card_cloud()
    full = [shifted_view(0.0), shifted_view(4.0)]
    views = full[:1] + [render_view(view, 1.8) for view in full] + full[1:]
    assert views[1].width_px < W, "the test needs views rendered smaller"
    frames = np.concatenate(list(render_batches(cloud, views, DISPARITY_SCALE, "cpu", (W, H))))
    assert frames.shape == (4, H, W, 3)
    for view, frame in zip(views, frames, strict=True):
        expected = render_frame(cloud, view, DISPARITY_SCALE)
        if view.width_px != W:
            expected = cv2.resize(expected, (W, H), interpolation=cv2.INTER_LINEAR)
        assert np.abs(frame.astype(int) - expected.astype(int)).max() <= 1


def test_a_launch_of_several_frames_equals_frames_one_by_one():
    cloud = soft_card_cloud()
    views = [shifted_view(shift) for shift in (0.0, 5.0, 10.0)]
    renderer = TorchRenderer(cloud, "cpu", DISPARITY_SCALE)
    together = renderer.render_frames(views).numpy()
    for view, frame in zip(views, together, strict=True):
        np.testing.assert_array_equal(frame, renderer.render_frames([view]).numpy()[0])
    with pytest.raises(ValueError, match="same size"):
        renderer.render_frames([views[0], shifted_view(0.0).__class__(
            views[0].position, views[0].focal_px, 10.0, 10.0, 20, 20)])


def test_real_photos_every_frame_matches_numba(quick_preset, monkeypatch):
    """Frame by frame over whole (short) clips of real photos, soft layers and fill included
    (the segmentation models make the depth edges that soft layers need)."""
    real_models_or_skip(monkeypatch)
    photos = [p for p in shared_photos(1)[0].parent.iterdir() if p.stem in REAL_PHOTOS]
    if len(photos) < len(REAL_PHOTOS):
        pytest.skip(f"needs the shared photos {', '.join(REAL_PHOTOS)}")
    preset = with_overrides(quick_preset, duration_s=0.3)  # the start, middle and end views
    assert preset.frames_forward == 3
    with_soft_layers = 0
    for path in sorted(photos):
        prepared = prepare_scene(read_image(path), path, preset, ClipOptions(), {})
        with_soft_layers += prepared.cloud.opaque_count < len(prepared.cloud)
        frames = list(pipeline.render_clip_frames(prepared, preset, 2, device=TORCH_CPU))
        assert len(frames) == preset.frames_total
        for index, t in enumerate(frame_times(preset)):
            expected = pipeline.frame_at(prepared, preset, t)
            assert psnr_db(frames[index], expected) >= MIN_PSNR_DB, (path.name, index)
    assert with_soft_layers, "none of the photos has soft layers (depth edges)"


def test_prefetched_keeps_order_raises_errors_and_stops_when_closed():
    assert list(prefetched(iter(range(20)), 2)) == list(range(20))

    def failing():
        yield 1
        raise RuntimeError("launch failed")

    with pytest.raises(RuntimeError, match="launch failed"):
        list(prefetched(failing(), 2))

    produced = []

    def endless():
        for i in range(10_000):
            produced.append(i)
            yield i

    stream = prefetched(endless(), 2)
    assert next(stream) == 0
    stream.close()
    assert len(produced) <= 5, "the producer ran on after the consumer stopped"
    assert not [t for t in threading.enumerate() if t.name == "kbbatch-prefetch"]


def test_a_clip_rendered_by_torch_is_encoded_whole(tmp_path, quick_preset):
    from kbbatch.encode import decode_frames, probe
    from kbbatch.images import write_image

    from .conftest import textured_image

    folder = tmp_path / "photos"
    folder.mkdir()
    write_image(folder / "a.png", textured_image(180, 320, seed=5))
    options = ClipOptions(threads=2, device=TORCH_CPU)
    report = run_folder(folder, tmp_path / "out", quick_preset, options,
                        show_progress=False)
    assert [r.status for r in report.results] == ["done"], report.results[0].error
    assert report.device == TORCH_CPU and report.results[0].device == TORCH_CPU
    clip = tmp_path / "out" / "a.mp4"
    info = probe(clip)
    frames = list(decode_frames(clip, info.width_px, info.height_px))
    assert len(frames) == quick_preset.frames_total
    assert min(f.mean() for f in frames) > 5, "a frame came out black"
