import numpy as np
import pytest

from kbbatch.encode import decode_frames, encode_frames, ffmpeg_exe, palindrome_order, probe
from kbbatch.presets import load_preset, with_overrides


def test_palindrome_order():
    assert palindrome_order(4) == [0, 1, 2, 3, 2, 1]
    assert palindrome_order(2) == [0, 1]


def test_ffmpeg_is_found():
    assert ffmpeg_exe()


def test_palindromic_clip_decodes_with_the_preset_facts(tmp_path):
    preset = with_overrides(load_preset("preview"), duration_s=0.8, fps=10.0)
    count = preset.frames_forward
    rows, cols = np.mgrid[0:preset.height_px, 0:preset.width_px]
    forward = [
        np.stack([(cols * 0.4 + 25 * k) % 256, (rows * 0.7) % 256,
                  np.full_like(rows, 30 * k % 256)], axis=-1).astype(np.uint8)
        for k in range(count)
    ]
    path = tmp_path / "clip.mp4"
    written = encode_frames(path, (forward[i] for i in palindrome_order(count)), preset)
    assert written == preset.frames_total == 2 * count - 2
    info = probe(path)
    assert (info.width_px, info.height_px) == (preset.width_px, preset.height_px)
    assert info.fps == pytest.approx(preset.fps)
    assert info.codec == "h264"
    assert info.duration_s == pytest.approx(preset.frames_total / preset.fps, abs=0.11)
    frames = [f.astype(np.int16) for f in decode_frames(path, info.width_px, info.height_px)]
    assert len(frames) == preset.frames_total
    n = len(frames)
    for k in range(1, n // 2):
        mirror = np.abs(frames[k] - frames[n - k]).mean()
        neighbour = np.abs(frames[k] - frames[k + 1]).mean()
        assert mirror < 2.0 < neighbour, (k, mirror, neighbour)


def test_wrong_frame_size_is_refused(tmp_path):
    preset = with_overrides(load_preset("preview"), duration_s=0.4, fps=10.0)
    with pytest.raises(Exception, match="expected"):
        encode_frames(tmp_path / "x.mp4", [np.zeros((10, 10, 3), np.uint8)], preset)
