"""What kbbatch prints cannot stop a batch: stderr or stdout gone, full or closed (a hostile
user's finds), and Ctrl-C pressed again and again."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from .test_nothing_lost import (
    CLI,
    FAST_CLI,
    act_while_encoding,
    photo,
    slow_folder,
    visible_clips,
)

FULL_DEVICE = Path("/dev/full")


def two_photos(tmp_path: Path) -> Path:
    folder = tmp_path / "in"
    for index in range(2):
        photo(folder / f"p{index}.jpg", seed=index)
    return folder


def finished_report(out: Path) -> dict:
    report = json.loads((out / "kbbatch-report.json").read_text())
    assert report["finished_at"], report
    return report


def test_a_batch_whose_stderr_pipe_is_closed_goes_on(tmp_path):
    """`kbbatch photos 2>&1 | head -1`: the first progress line after head left raised
    BrokenPipeError inside the frames, which the encoder took for its own pipe breaking; the
    batch then waited for good on ffmpeg, which waited for frames (SIGTERM could not end it)."""
    folder, out = two_photos(tmp_path), tmp_path / "out"
    batch = subprocess.Popen([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    batch.stderr.close()  # the reader gone before the batch writes a line
    try:
        assert batch.wait(timeout=120) == 0
    finally:
        if batch.poll() is None:
            batch.kill()
    assert visible_clips(out) == ["p0.mp4", "p1.mp4"]
    finished_report(out)


@pytest.mark.skipif(not FULL_DEVICE.exists(), reason="needs /dev/full (Linux)")
def test_stderr_or_stdout_on_a_full_disk_makes_every_clip(tmp_path):
    """`2>>log` on a full disk: the failed progress line was taken for the output disk being
    full, and no clip was made; `plan` wrote no manifest. `>>log` on a full one: a traceback
    and status 1 after every clip was made."""
    folder = two_photos(tmp_path)
    with FULL_DEVICE.open("w") as full:
        made = subprocess.run([*CLI, str(folder), "-o", str(tmp_path / "a"), *FAST_CLI],
                              stdout=subprocess.DEVNULL, stderr=full, timeout=120)
        planned = subprocess.run([*CLI, "plan", str(folder), "-o", str(tmp_path / "m.json"),
                                  *FAST_CLI], stdout=subprocess.DEVNULL, stderr=full,
                                 timeout=120)
        summary_lost = subprocess.run([*CLI, str(folder), "-o", str(tmp_path / "b"),
                                       *FAST_CLI], stdout=full, stderr=subprocess.PIPE,
                                      text=True, timeout=120)
    assert made.returncode == 0 and visible_clips(tmp_path / "a") == ["p0.mp4", "p1.mp4"]
    assert planned.returncode == 0 and (tmp_path / "m.json").is_file()
    assert summary_lost.returncode == 0, summary_lost.stderr
    assert "Traceback" not in summary_lost.stderr
    assert "the summary could not be printed (No space left on device)" in summary_lost.stderr
    assert visible_clips(tmp_path / "b") == ["p0.mp4", "p1.mp4"]


def test_a_batch_started_with_stderr_closed_makes_its_clips(tmp_path):
    """A launcher that closes descriptor 2: `sys.stderr` is None, and every photo failed
    (AttributeError) without a word, in the batch and in the daemon alike."""
    folder, out = two_photos(tmp_path), tmp_path / "out"
    made = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                          stdout=subprocess.DEVNULL, preexec_fn=lambda: os.close(2),
                          timeout=120)
    assert made.returncode == 0
    assert visible_clips(out) == ["p0.mp4", "p1.mp4"]
    finished_report(out)


@pytest.mark.slow
def test_ctrl_c_pressed_again_and_again_still_stops_cleanly(tmp_path):
    """Five Ctrl-Cs 10 ms apart: the second one broke off the first one's clean-up (the
    report unfinished in about one run of three) or the interpreter's shut-down ("Exception
    ignored in threading"), and the process died by SIGINT instead of ending with 130."""
    for attempt in range(3):
        folder = slow_folder(tmp_path / str(attempt))
        out = tmp_path / str(attempt) / "out"

        def press_ctrl_c_five_times(batch: subprocess.Popen) -> None:
            for _ in range(5):
                batch.send_signal(signal.SIGINT)
                time.sleep(0.01)

        returncode, stderr = act_while_encoding(folder, out, 6, press_ctrl_c_five_times)
        assert returncode == 130, (attempt, returncode, stderr)
        assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
        assert finished_report(out)["stopped_by"] == "SIGINT"
        assert not list(out.glob(".*part*"))
