"""The one-shot batch under re-runs and bad inputs: nothing lost, nothing partial."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from kbbatch.batch import run_folder
from kbbatch.depth import DepthOptions
from kbbatch.images import ImageReadError, read_image
from kbbatch.outputs import OutputFolderError
from kbbatch.pipeline import ClipOptions

from .badinputs import BAD, GOOD, write_corpus
from .conftest import textured_image

FAST = ClipOptions(planner="center", depth=DepthOptions(backend="ramp"), threads=2)


def visible_clips(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("*.mp4") if not p.name.startswith("."))


def test_corpus_every_bad_file_reported_every_good_one_rendered(tmp_path, quick_preset):
    write_corpus(tmp_path / "in")
    before = {p.name: p.read_bytes() for p in (tmp_path / "in").iterdir()}
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    by_name = {Path(r.source).name: r for r in report.results}
    assert all(by_name[name].status == "done" for name in GOOD), report.to_json()
    for name in BAD:
        assert by_name[name].status == "failed" and name in by_name[name].error
    assert len(visible_clips(tmp_path / "out")) == len(GOOD)
    assert {"twin.jpg.mp4", "twin.png.mp4"} <= set(visible_clips(tmp_path / "out"))
    assert {p.name: p.read_bytes() for p in (tmp_path / "in").iterdir()} == before


def two_photos_made(tmp_path: Path, preset) -> Path:
    """A folder of a.jpg and b.jpg whose clips are made into tmp_path / "out"."""
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    Image.fromarray(textured_image(180, 320, seed=1)).save(folder / "b.jpg")
    first = run_folder(folder, tmp_path / "out", preset, FAST, False)
    assert [r.status for r in first.results] == ["done", "done"]
    return folder


def test_rerun_skips_up_to_date_clips_and_force_redoes_them(tmp_path, quick_preset):
    folder = two_photos_made(tmp_path, quick_preset)
    mtime = (tmp_path / "out" / "a.mp4").stat().st_mtime_ns
    second = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in second.results] == ["skipped", "skipped"]
    assert (tmp_path / "out" / "a.mp4").stat().st_mtime_ns == mtime
    Image.fromarray(textured_image(180, 320, seed=5)).save(folder / "b.jpg")  # b changed
    third = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in third.results] == ["skipped", "done"]
    other = ClipOptions(planner="2d", depth=FAST.depth, threads=2)  # settings changed
    assert [r.status for r in run_folder(folder, tmp_path / "out", quick_preset, other,
                                         False).results] == ["done", "done"]
    forced = run_folder(folder, tmp_path / "out", quick_preset, other, False, force=True)
    assert [r.status for r in forced.results] == ["done", "done"]


def test_photos_with_new_times_but_the_same_bytes_are_not_made_again(tmp_path, quick_preset):
    """A folder copied to another disk without its times (cp -r, a sync tool, a zip) has new
    modification times and the same bytes: every clip was made again, for nothing. Other
    bytes under the same size and time (an edit that kept the photo's time) are made again."""
    folder = two_photos_made(tmp_path, quick_preset)
    clip = (tmp_path / "out" / "a.mp4").stat().st_mtime_ns
    later = (folder / "a.jpg").stat().st_mtime_ns + 5_000_000_000
    for photo in folder.iterdir():  # the same bytes, written again five seconds later
        photo.write_bytes(photo.read_bytes())
        os.utime(photo, ns=(later, later))
    again = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in again.results] == ["skipped", "skipped"]
    assert (tmp_path / "out" / "a.mp4").stat().st_mtime_ns == clip
    photo = folder / "b.jpg"
    data = bytearray(photo.read_bytes())
    data[-3] ^= 0xFF  # b edited in place: the same size, its time put back
    photo.write_bytes(bytes(data))
    os.utime(photo, ns=(later, later))
    edited = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in edited.results] == ["skipped", "done"]


def test_a_photo_saved_again_while_its_clip_is_made_is_not_taken_for_up_to_date(
        tmp_path, quick_preset, monkeypatch):
    """The batch hashed a photo when it started its job and decoded it later: saved again in
    between, the clip was made from the new bytes and journaled under the old ones, and once
    the file held the old bytes again (an undo, a sync conflict), every run took the wrong
    clip for up to date. Now the photo is read once, hashed and decoded from the same bytes:
    that clip is said to be of a changed photo, and the next run makes it again."""
    from kbbatch import pipeline

    folder = tmp_path / "in"
    folder.mkdir()
    first, second = tmp_path / "first.jpg", tmp_path / "second.jpg"
    Image.fromarray(textured_image(180, 320, seed=1)).save(first)
    Image.fromarray(textured_image(180, 320, seed=2)).save(second)
    photo = folder / "a.jpg"
    photo.write_bytes(first.read_bytes())
    real_make_clip = pipeline.make_clip

    def saved_again_once_begun(*args, **kwargs):  # the user's save lands after the job began
        photo.write_bytes(second.read_bytes())
        return real_make_clip(*args, **kwargs)

    monkeypatch.setattr(pipeline, "make_clip", saved_again_once_begun)
    [made] = run_folder(folder, tmp_path / "out", quick_preset, FAST, False).results
    assert made.status == "failed" and "changed while its clip was made" in made.error
    assert (tmp_path / "out" / "a.mp4").is_file(), "the clip made is kept"
    monkeypatch.setattr(pipeline, "make_clip", real_make_clip)
    photo.write_bytes(first.read_bytes())  # the first bytes are back
    [again] = run_folder(folder, tmp_path / "out", quick_preset, FAST, False).results
    assert again.status == "done", "the clip of the other bytes was taken for up to date"
    reference = run_folder(_copy_of(photo, tmp_path / "ref"), tmp_path / "ref-out",
                           quick_preset, FAST, False).results[0]
    assert Path(again.output).read_bytes() == Path(reference.output).read_bytes()


def _copy_of(photo: Path, folder: Path) -> Path:
    folder.mkdir()
    (folder / photo.name).write_bytes(photo.read_bytes())
    return folder


def test_fail_fast_stops_at_the_first_failure(tmp_path, quick_preset):
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(b"")
    Image.fromarray(textured_image(180, 320)).save(folder / "b.jpg")
    report = run_folder(folder, tmp_path / "out", quick_preset, FAST, False, fail_fast=True)
    assert [r.status for r in report.results] == ["failed"]
    assert not visible_clips(tmp_path / "out")
    # the photo it did not begin is said (the report looked complete, status too)
    assert report.not_started == [str(folder / "b.jpg")]
    from kbbatch.batch import last_run_lines

    [line] = last_run_lines(tmp_path / "out")
    assert "ended at its first failure (--fail-fast)" in line and "1 photo(s) not started" in line


def test_fail_fast_stops_at_a_failure_found_before_any_photo(tmp_path, quick_preset):
    """A broken link or a named pipe in the folder fails before any photo is made: --fail-fast
    went on and made every photo ("5 clip(s) made, 2 failed")."""
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "00_link.jpg").symlink_to(tmp_path / "nowhere.jpg")
    Image.fromarray(textured_image(180, 320)).save(folder / "b.jpg")
    report = run_folder(folder, tmp_path / "out", quick_preset, FAST, False, fail_fast=True)
    assert [r.status for r in report.results] == ["failed"]
    assert report.not_started == [str(folder / "b.jpg")]
    assert not visible_clips(tmp_path / "out")


def test_a_20000_px_jpeg_is_decoded_small_and_a_png_bomb_is_refused(tmp_path):
    Image.new("L", (20000, 20000), 128).save(tmp_path / "huge.jpg", quality=50)
    image = read_image(tmp_path / "huge.jpg")
    assert max(image.shape[:2]) <= 10000 and image.shape[2] == 3
    # A PNG that claims 20000 x 20000 pixels: refused before any pixel is decoded.
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    header = struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
           + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))
    (tmp_path / "bomb.png").write_bytes(png)
    with pytest.raises(ImageReadError, match="bomb.png: is 20000x20000 px"):
        read_image(tmp_path / "bomb.png")


def test_an_output_folder_that_cannot_be_written_is_a_clear_error(tmp_path, quick_preset):
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    blocker = tmp_path / "file-not-folder"
    blocker.write_text("x")
    with pytest.raises(OutputFolderError, match="file-not-folder.*not writable"):
        run_folder(folder, blocker / "out", quick_preset, FAST, False)
    read_only = tmp_path / "read-only"
    read_only.mkdir()
    read_only.chmod(0o555)
    if os.access(read_only, os.W_OK):
        pytest.skip("running as root: a read-only mode does not stop writes here")
    with pytest.raises(OutputFolderError, match="not writable"):
        run_folder(folder, read_only, quick_preset, FAST, False)


def test_disk_full_during_encoding_leaves_no_partial_clip(tmp_path):
    """RLIMIT_FSIZE makes every write past 256 KiB fail, as a full disk would. Python ignores
    SIGXFSZ (as it does under a shell's `ulimit -f`); ffmpeg, started with the default
    handlers, is killed by it, and the error said only "killed by SIGXFSZ"."""
    folder = tmp_path / "in"
    folder.mkdir()
    noise = np.random.default_rng(0).integers(0, 256, (720, 1280, 3), dtype=np.uint8)
    Image.fromarray(noise).save(folder / "a.png")  # noise: the clip needs far over 256 KiB
    out = tmp_path / "out"
    script = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (262144, 262144))\n"
        "from kbbatch.cli import main\n"
        f"sys.argv = ['kbbatch', {str(folder)!r}, '-o', {str(out)!r}, '--preset', 'preview',"
        " '--depth', 'ramp', '--planner', 'center', '--quiet', '--duration', '2', '--fps', '25']\n"
        "main()\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 1, result.stderr
    assert "a.png" in result.stderr and "FAILED" in result.stderr
    assert "SIGXFSZ (the file size limit, `ulimit -f`, was reached)" in result.stderr
    assert not visible_clips(out), "a partial clip was left under the final name"
    assert not list(out.glob(".*part*")), "a temporary file was left behind"


def test_a_clip_is_made_in_an_output_folder_whose_name_is_not_utf8(tmp_path, quick_preset):
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(textured_image(180, 320)).save(folder / "a.jpg")
    output = tmp_path / os.fsdecode(b"outB\xff")
    report = run_folder(folder, output, quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["done"], report.to_json()
    assert visible_clips(output) == ["a.mp4"]
    assert [r.status for r in run_folder(folder, output, quick_preset, FAST, False).results
            ] == ["skipped"]


@pytest.mark.parametrize("width_px, height_px", [(5000, 5), (5, 5000), (5000, 1), (2, 5000),
                                                 (20, 5000)])
def test_a_photo_too_thin_for_the_clip_is_said_to_be_too_small(tmp_path, quick_preset,
                                                               width_px, height_px):
    """A strip a few pixels high broke the planner ("depth does not match the view size")
    where a slightly wider one was said to be too small."""
    from kbbatch.pipeline import make_clip

    photo = tmp_path / f"strip{width_px}x{height_px}.png"
    Image.fromarray(textured_image(height_px, width_px)).save(photo)
    options = ClipOptions(depth=DepthOptions(backend="popup"), threads=2)
    result = make_clip(photo, tmp_path / "out" / "strip.mp4", quick_preset, options,
                       show_progress=False)
    assert result.status == "failed"
    assert result.error.startswith(f"{photo}: too small for 640 px wide clips"), result.error
    assert result.detail is None  # an expected refusal, not an unexpected error


def test_a_strip_a_smaller_clip_takes_is_planned_without_a_view_of_no_rows(tmp_path,
                                                                           quick_preset):
    """5000 x 12 px is 1024 x 2 at the working size and had a planner view of no rows."""
    from kbbatch.pipeline import make_clip
    from kbbatch.presets import with_overrides

    preset = with_overrides(quick_preset, width_px=320, height_px=180)
    photo = tmp_path / "strip.png"
    Image.fromarray(textured_image(12, 5000)).save(photo)
    options = ClipOptions(depth=DepthOptions(backend="popup"), threads=2)
    result = make_clip(photo, tmp_path / "out" / "strip.mp4", preset, options,
                       show_progress=False)
    assert result.detail is None, result.detail
    assert result.error.startswith(f"{photo}: too small for 320 px wide clips"), result.error
