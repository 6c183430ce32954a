"""Real photos from ../shared through the whole pipeline and real ffmpeg."""

import shutil
import subprocess
import sys

import numpy as np

from kbbatch.batch import REPORT_NAME, run_folder
from kbbatch.encode import decode_frames, probe
from kbbatch.pipeline import ClipOptions

from .conftest import shared_photos


def test_two_real_photos_and_a_corrupt_one(tmp_path, quick_preset):
    folder = tmp_path / "photos"
    folder.mkdir()
    sources = shared_photos(2)
    for source in sources:
        shutil.copy(source, folder / source.name)
    (folder / "corrupt.jpg").write_bytes(b"\xff\xd8\xff\xe0 definitely not a whole jpeg")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}

    report = run_folder(folder, tmp_path / "out", quick_preset, ClipOptions(threads=2),
                        show_progress=False)

    assert [r.status for r in report.results].count("done") == 2
    [failed] = report.failed
    assert "corrupt.jpg" in failed.error
    for source in sources:
        clip = tmp_path / "out" / f"{source.stem}.mp4"
        info = probe(clip)
        assert (info.width_px, info.height_px) == (quick_preset.width_px, quick_preset.height_px)
        frames = list(decode_frames(clip, info.width_px, info.height_px))
        assert len(frames) == quick_preset.frames_total
        assert min(f.mean() for f in frames) > 5, "a frame came out black"
        assert np.abs(frames[0].astype(int) - frames[len(frames) // 2].astype(int)).mean() > 1
    assert (tmp_path / "out" / REPORT_NAME).is_file()
    assert not list((tmp_path / "out").glob(".*part*")), "a temporary file was left behind"
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before, "sources changed"


def test_cli_exit_code_and_summary(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    [source] = shared_photos(1)
    shutil.copy(source, folder / source.name)
    (folder / "bad.png").write_bytes(b"")
    command = [sys.executable, "-m", "kbbatch", str(folder), "--preset", "preview",
               "--duration", "0.4", "--fps", "10", "--quiet"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1
    assert "1 clip(s) made" in result.stdout
    assert "bad.png: is empty (0 bytes)" in result.stderr
    assert (folder / "kenburns" / f"{source.stem}.mp4").is_file()


def test_save_depth_writes_a_16_bit_disparity_and_a_preview(tmp_path, quick_preset):
    import cv2

    folder = tmp_path / "photos"
    folder.mkdir()
    [source] = shared_photos(1)
    shutil.copy(source, folder / source.name)
    options = ClipOptions(threads=2, save_depth=True)
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False)
    assert report.results[0].status == "done"
    disparity = cv2.imread(str(tmp_path / "out" / f"{source.stem}.disparity.png"),
                           cv2.IMREAD_UNCHANGED)
    assert disparity.dtype == np.uint16 and disparity.max() == 65535
    assert max(disparity.shape) == 1024 and len(np.unique(disparity)) > 10
    preview = cv2.imread(str(tmp_path / "out" / f"{source.stem}.depth-preview.png"))
    assert preview.shape[:2] == disparity.shape
    # Another photo under that name, made without --save-depth: the maps of the old photo
    # stayed beside the new clip, without a word.
    [_, other] = shared_photos(2)
    shutil.copy(other, folder / source.name)
    report = run_folder(folder, tmp_path / "out", quick_preset, ClipOptions(threads=2),
                        show_progress=False)
    assert report.results[0].status == "done"
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == []


def test_progress_into_a_log_is_a_few_lines_not_a_redraw_per_frame(tmp_path):
    from kbbatch.images import write_image

    from .conftest import textured_image

    folder = tmp_path / "in"
    folder.mkdir()
    write_image(folder / "texture.png", textured_image(360, 640))
    command = [sys.executable, "-m", "kbbatch", str(folder), "--preset", "preview",
               "--duration", "3", "--depth", "ramp"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    refreshes = [part for part in result.stderr.replace("\r", "\n").split("\n")
                 if "frames texture.png" in part]
    assert refreshes, "progress must still be shown"
    assert len(refreshes) <= 4, f"{len(refreshes)} progress refreshes written into a log"
