import contextlib
import os
import signal
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kbbatch.encode import (
    EncodeError,
    EncoderStoppedError,
    caught_stop,
    check_encoder,
    decode_frames,
    encode_frames,
    encoder_command,
    ffmpeg_exe,
    palindrome_order,
    probe,
)
from kbbatch.presets import builtin_names, load_preset, with_overrides


def test_palindrome_order():
    assert palindrome_order(4) == [0, 1, 2, 3, 2, 1]
    assert palindrome_order(2) == [0, 1]


def test_ffmpeg_runs_and_offers_the_shipped_presets_encoders():
    version = subprocess.run([ffmpeg_exe(), "-version"], capture_output=True, text=True,
                             check=True).stdout
    assert version.startswith("ffmpeg version")
    for name in builtin_names():
        check_encoder(load_preset(name))  # raises EncoderError where this ffmpeg cannot


def test_probe_refuses_what_is_not_a_video(tmp_path):
    (tmp_path / "notes.mp4").write_text("not a video")
    with pytest.raises(EncodeError, match=r"notes.mp4: ffmpeg found no video stream \(.*"
                                          r"Invalid data"):
        probe(tmp_path / "notes.mp4")


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
    with pytest.raises(EncodeError, match=r"frame 0 has shape \(10, 10, 3\) uint8, expected"):
        encode_frames(tmp_path / "x.mp4", [np.zeros((10, 10, 3), np.uint8)], preset)


def encoder_pids(path_part: str) -> list[int]:
    """Processes whose command line names path_part (the encoder writing a clip)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and entry.name != str(os.getpid()):
            try:
                if path_part.encode() in (entry / "cmdline").read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


@pytest.mark.parametrize(("sent", "at_frame"), [(signal.SIGTERM, 3), (signal.SIGINT, 3),
                                               (signal.SIGKILL, 3), (signal.SIGTERM, 0)])
def test_an_encoder_stopped_by_a_signal_is_an_interruption_not_a_failure(tmp_path, sent,
                                                                         at_frame):
    """A service manager stops every process of a service: ffmpeg's end is then no fault of the
    photo (it went to failed/ and was never retried)."""
    assert not issubclass(EncoderStoppedError, EncodeError)
    preset = with_overrides(load_preset("preview"), duration_s=2.0, fps=10.0)
    frame = np.full((preset.height_px, preset.width_px, 3), 90, np.uint8)

    def frames():
        for index in range(preset.frames_total):
            if index == at_frame:  # at 0, before ffmpeg has read a frame
                time.sleep(0.3)
                [pid] = encoder_pids(str(tmp_path / "x.mp4"))
                os.kill(pid, sent)
                time.sleep(0.5)
            yield frame

    # SIGKILL is no request to stop (the kernel's out-of-memory killer sends it): a failure
    expected = EncoderStoppedError if sent != signal.SIGKILL else EncodeError
    with pytest.raises(expected, match="stopped by" if sent != signal.SIGKILL else "SIGKILL"):
        encode_frames(tmp_path / "x.mp4", frames(), preset)


def test_a_stop_that_cuts_a_frame_in_half_is_still_a_stop(tmp_path):
    """Under load the signal often lands inside a frame: ffmpeg then reports the short packet
    as well, and the photo was filed as failed (seen in a daemon test under load)."""
    preset = load_preset("preview")
    process = subprocess.Popen(encoder_command(tmp_path / "x.mp4", preset),
                               stdin=subprocess.PIPE, stderr=subprocess.PIPE,
                               start_new_session=True)
    frame = np.zeros((preset.height_px, preset.width_px, 3), np.uint8).tobytes()
    process.stdin.write(frame * 3 + frame[: len(frame) // 7])
    process.stdin.flush()
    time.sleep(0.5)
    process.send_signal(signal.SIGTERM)
    with contextlib.suppress(BrokenPipeError):
        process.stdin.close()
    stderr = process.stderr.read().decode(errors="replace")
    status = process.wait()
    assert "< expected frame_size" in stderr, stderr  # what made it look like a failure
    assert caught_stop(status, stderr)
    assert not caught_stop(1, stderr)  # ffmpeg's own errors exit with 1


def test_an_encoder_that_fails_on_its_own_is_still_a_failure(tmp_path):
    preset = with_overrides(load_preset("preview"), duration_s=0.4, fps=10.0)
    frame = np.zeros((preset.height_px, preset.width_px, 3), np.uint8)
    with pytest.raises(EncodeError, match="ffmpeg failed writing"):
        encode_frames(tmp_path / "no-such-folder" / "x.mp4", [frame] * 4, preset)


def test_frames_beyond_the_memory_budget_go_through_a_scratch_file_that_is_removed(
    tmp_path, monkeypatch, quick_preset
):
    import tempfile

    from kbbatch import pipeline

    from .conftest import textured_image

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    options = pipeline.ClipOptions(threads=2, cache_depth=False,
                                   depth=pipeline.DepthOptions("ramp"))
    prepared = pipeline.prepare_scene(textured_image(240, 320), None, quick_preset, options, {})

    def frames(budget_bytes: int) -> tuple[list[np.ndarray], list[str]]:
        monkeypatch.setattr(pipeline, "FRAME_STORE_RAM_BYTES", budget_bytes)
        seen, scratch = [], []
        for frame in pipeline.render_clip_frames(prepared, quick_preset, threads=2):
            seen.append(frame.copy())
            scratch += [p.name for p in tmp_path.iterdir()]
        return seen, scratch

    in_memory, scratch_in_memory = frames(1 << 30)
    on_disk, scratch_on_disk = frames(1)
    assert not scratch_in_memory, "frames that fit in memory need no scratch folder"
    assert any(name.startswith("kbbatch-frames-") for name in scratch_on_disk)
    assert list(tmp_path.iterdir()) == [], "the scratch folder must be removed"
    assert len(on_disk) == quick_preset.frames_total
    for first, second in zip(in_memory, on_disk, strict=True):
        np.testing.assert_array_equal(first, second)
    for k in range(1, len(on_disk)):  # forward, then back without the two ends
        np.testing.assert_array_equal(on_disk[k], on_disk[len(on_disk) - k])


def test_frame_stores_of_killed_processes_are_removed_by_the_next_run(tmp_path, monkeypatch):
    import subprocess
    import sys
    import tempfile

    from kbbatch.batch import EmptyFolderError, run_folder
    from kbbatch.pipeline import SCRATCH_PREFIX, ClipOptions
    from kbbatch.presets import load_preset

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True, check=True)
    stale = tmp_path / "tmp" / f"{SCRATCH_PREFIX}{finished.stdout.strip()}-abc"
    live = tmp_path / "tmp" / f"{SCRATCH_PREFIX}{os.getpid()}-def"
    for folder in (stale, live):
        folder.mkdir()
        (folder / "frames.npy").write_bytes(b"\0" * 1024)
    (tmp_path / "photos").mkdir()
    with pytest.raises(EmptyFolderError):  # the clean-up comes first, even with no photos
        run_folder(tmp_path / "photos", tmp_path / "out", load_preset("preview"),
                   ClipOptions(threads=1), show_progress=False)
    assert not stale.exists(), "a dead process's frame store must be removed"
    assert live.exists(), "a running process's frame store must be kept"


def test_nvenc_takes_a_constant_quality_where_x264_takes_crf():
    from kbbatch.encode import encoder_command

    slideshow = load_preset("slideshow")
    software = encoder_command(Path("clip.mp4"), slideshow)
    assert software[software.index("-crf") + 1] == str(slideshow.crf)
    nvenc = encoder_command(Path("clip.mp4"), replace(slideshow, codec="h264_nvenc",
                                                      encoder_preset="p5"))
    assert "-crf" not in nvenc
    assert nvenc[nvenc.index("-cq") + 1] == str(slideshow.crf)
    assert nvenc[nvenc.index("-rc") + 1] == "vbr"
    assert nvenc[nvenc.index("-preset") + 1] == "p5"


def test_a_clip_is_written_into_a_folder_whose_name_is_not_utf8(tmp_path):
    """ffmpeg-python hashes the output name as UTF-8: every clip into such a folder failed."""
    preset = with_overrides(load_preset("preview"), duration_s=0.4, fps=10.0)
    folder = tmp_path / os.fsdecode(b"outB\xff")
    folder.mkdir()
    frame = np.full((preset.height_px, preset.width_px, 3), 90, np.uint8)
    path = folder / os.fsdecode(b"clip\xe9.mp4")
    assert encode_frames(path, [frame] * preset.frames_total, preset) == preset.frames_total
    info = probe(path)
    assert (info.width_px, info.height_px) == (preset.width_px, preset.height_px)
    assert len(list(decode_frames(path, info.width_px, info.height_px))) == preset.frames_total


PATCH_COLOURS = [(220, 30, 30), (30, 180, 40), (30, 40, 220), (230, 180, 140), (30, 200, 220)]


@pytest.mark.parametrize("preset_name", ["preview", "slideshow"])
def test_clips_are_converted_and_tagged_as_bt709_so_players_show_the_photos_colours(
        tmp_path, preset_name):
    """Converted with swscale's default BT.601 matrix and untagged, a player that reads HD
    video as BT.709 (as most do) showed a green of 180 as 155."""
    preset = with_overrides(load_preset(preset_name), duration_s=0.2, fps=10.0)
    frame = np.full((preset.height_px, preset.width_px, 3), 128, np.uint8)
    band = preset.width_px // len(PATCH_COLOURS)
    for index, colour in enumerate(PATCH_COLOURS):
        frame[:, index * band:(index + 1) * band] = colour
    path = tmp_path / "chart.mp4"
    encode_frames(path, [frame] * preset.frames_total, preset)
    listing = subprocess.run([ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                             capture_output=True, text=True).stderr
    assert "yuv420p(tv, bt709, progressive)" in listing, listing  # matrix/primaries/transfer
    decoded = subprocess.run(
        [ffmpeg_exe(), "-v", "error", "-i", str(path), "-frames:v", "1", "-vf",
         "scale=in_color_matrix=bt709:in_range=tv:out_range=pc", "-f", "rawvideo",
         "-pix_fmt", "rgb24", "pipe:"], capture_output=True, check=True).stdout
    shown = np.frombuffer(decoded, np.uint8).reshape(preset.height_px, preset.width_px, 3)
    for index, colour in enumerate(PATCH_COLOURS):
        centre = shown[preset.height_px // 2, index * band + band // 2].astype(int)
        assert np.abs(centre - colour).max() <= 4, (colour, centre)


def test_a_ctrl_c_while_the_encoder_starts_leaves_no_encoder_and_no_partial_clip(
        tmp_path, monkeypatch, quick_preset):
    """An interrupt that landed inside subprocess.Popen, after the fork, left an ffmpeg no one
    knew of: it wrote the clip's temporary file after the clean-up had removed it (about
    one Ctrl-C in three left a partial clip on a loaded machine)."""
    from kbbatch import encode
    from kbbatch.batch import stop_signals
    from kbbatch.images import atomic_output

    started = []
    real_popen = subprocess.Popen

    def popen_then_ctrl_c(*args, **kwargs):
        process = real_popen(*args, **kwargs)
        started.append(process)
        os.kill(os.getpid(), signal.SIGINT)  # handled before Popen's caller gets the process
        time.sleep(0.05)
        return process

    monkeypatch.setattr(encode.subprocess, "Popen", popen_then_ctrl_c)
    frame = np.zeros((quick_preset.height_px, quick_preset.width_px, 3), np.uint8)
    clip = tmp_path / "a.mp4"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a command has it
    try:
        with (stop_signals({}), pytest.raises(KeyboardInterrupt),
              atomic_output(clip, ".mp4", make_folder=False) as temp_path):
            encode.encode_frames(temp_path, [frame] * 4, quick_preset)
        [encoder] = started
        assert encoder.wait(timeout=10) != 0  # stopped, not left to finish its clip
        time.sleep(0.5)  # what an encoder left running would write by now
        assert sorted(path.name for path in tmp_path.iterdir()) == []
    finally:
        signal.signal(signal.SIGINT, previous)
        for process in started:
            process.kill()
            process.wait()


def test_an_hevc_clip_is_tagged_hvc1_for_apples_players(tmp_path):
    """ffmpeg tags HEVC in MP4 `hev1`, which QuickTime, Final Cut and iOS refuse to play."""
    preset = with_overrides(load_preset("preview"), duration_s=0.2, fps=10.0)
    preset = replace(preset, codec="libx265", encoder_preset="ultrafast")
    frame = np.full((preset.height_px, preset.width_px, 3), 128, np.uint8)
    path = tmp_path / "hevc.mp4"
    encode_frames(path, [frame] * preset.frames_total, preset)
    listing = subprocess.run([ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                             capture_output=True, text=True).stderr
    assert "hevc" in listing and "(hvc1 /" in listing, listing
