"""The watch-folder daemon as a real process: arrivals, bad inputs, kill -9, SIGTERM."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kbbatch.journal import Journal

from .badinputs import BAD, GOOD, write_corpus
from .conftest import shared_photos

pytestmark = pytest.mark.slow


def preset_file(folder: Path, duration_s: float, fps: float = 10.0) -> Path:
    path = folder / "test-preset.toml"
    path.write_text(f"""description = "test"
width_px = 320
height_px = 180
fps = {fps}
duration_s = {duration_s}
easing = "linear"
zoom = 1.25
zoom_direction = "in"
max_shift_px = 100
codec = "libx264"
crf = 30
pix_fmt = "yuv420p"
encoder_preset = "ultrafast"
""")
    return path


def start_daemon(inbox: Path, outbox: Path, preset: Path, *extra: str,
                 log_path: Path | None = None, preexec_fn=None) -> subprocess.Popen:
    command = [sys.executable, "-m", "kbbatch", "watch", str(inbox), "--out", str(outbox),
               "--preset", str(preset), "--settle", "1", "--depth", "ramp", "--planner",
               "center", *extra]
    log = open(log_path or outbox.parent / "daemon.log", "ab")  # noqa: SIM115 - the child keeps it open
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, preexec_fn=preexec_fn)


def clip_parts(folder: Path) -> list[Path]:
    """Clips being written: their temporary files (any `.part` file is not enough: the daemon
    writes its inbox note through one at its start, and a kill -9 timed by it came before any
    job had started)."""
    return list(folder.glob(".*.part.mp4"))


def clips_in(folder: Path) -> list[str]:
    """Finished clips: visible .mp4 files (temporary ones are hidden)."""
    return sorted(p.name for p in folder.glob("*.mp4") if not p.name.startswith("."))


def wait_for(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def process_state(pid: int) -> str:
    """The state letter of a process (R running, S sleeping, T stopped, Z ended, ...)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat.rsplit(")", 1)[1].split()[0]


def held_encoders(outbox: Path, stem: str) -> list[int]:
    """Waits for the encoder of stem's clip and stops it (SIGSTOP; SIGCONT goes on): held
    still, the clip is surely unfinished while a test acts (its encode may last a second)."""
    from .test_encode import encoder_pids

    encoders: list[int] = []

    def encoding() -> bool:
        encoders[:] = encoder_pids(str(outbox / f".{stem}."))
        return bool(encoders)

    wait_for(encoding, 120, f"the encoder of {stem}'s clip")
    for pid in encoders:
        os.kill(pid, signal.SIGSTOP)

    def stopped() -> bool:  # a signal is delivered some time after kill() returns
        try:
            return all(process_state(pid) == "T" for pid in encoders)
        except FileNotFoundError:  # ended and reaped
            return False

    try:
        wait_for(stopped, 10, "the encoder to stop")
    except AssertionError:
        for pid in encoders:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        raise AssertionError(f"the encoder of {stem}'s clip ended before it was held") from None
    return encoders


def finished_jobs(outbox: Path) -> int:
    if not (outbox / ".kbbatch-journal.sqlite").exists():
        return 0
    journal = Journal(outbox)
    try:
        counts = journal.counts()
        return counts["done"] + counts["failed"]
    finally:
        journal.close()


def stop(process: subprocess.Popen) -> int:
    process.send_signal(signal.SIGTERM)
    return process.wait(timeout=60)


def test_daemon_makes_a_clip_per_good_photo_and_a_report_per_bad_one(tmp_path):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 0.4)
    photos = shared_photos(2)
    for photo in photos:
        shutil.copy(photo, inbox / photo.name)
    daemon = start_daemon(inbox, outbox, preset, "--jobs", "2")
    try:
        write_corpus(tmp_path / "corpus")
        for path in (tmp_path / "corpus").iterdir():
            os.rename(path, inbox / path.name)  # arrives by rename, as a finished file
        total = len(photos) + len(GOOD) + len(BAD)
        # Bad photos written moments ago are filed once they stayed unchanged a while.
        wait_for(lambda: finished_jobs(outbox) == total
                 and len(list((inbox / "failed").glob("*.error.json"))) == len(BAD), 240,
                 f"{total} finished jobs and {len(BAD)} failure reports")
        # Nothing else arrives: the daemon keeps running until told to stop.
        assert daemon.poll() is None
    finally:
        assert stop(daemon) == 0
    clips = clips_in(outbox)
    assert len(clips) == len(photos) + len(GOOD), clips
    assert "twin.jpg.mp4" in clips or "twin.png.mp4" in clips, "twins must not overwrite"
    assert sorted(p.name for p in (inbox / "failed").glob("*.error.json")) == sorted(
        f"{name}.error.json" for name in BAD)
    report = json.loads((inbox / "failed" / "text.jpg.error.json").read_text())
    assert "not an image" in report["error"]
    assert sorted(p.name for p in (inbox / "done").iterdir()) == sorted(
        [p.name for p in photos] + list(GOOD))
    assert not [p for p in inbox.iterdir() if p.is_file()], "every photo left the inbox"
    assert not list(outbox.glob(".*part*"))
    assert "ERROR" not in (tmp_path / "daemon.log").read_text(), "nothing went wrong"
    status = subprocess.run([sys.executable, "-m", "kbbatch", "status", str(outbox)],
                            capture_output=True, text=True, check=True)
    assert f"done {total - len(BAD)}, failed {len(BAD)}" in status.stdout


def test_kill_9_mid_encode_then_restart_gives_exactly_one_clip(tmp_path):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 12.0, fps=25.0)  # long enough to be caught mid-encode
    [photo] = shared_photos(1)
    shutil.copy(photo, inbox / photo.name)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: clip_parts(outbox), 120, "a clip being encoded")
    finally:
        daemon.send_signal(signal.SIGKILL)
        daemon.wait(timeout=30)
    assert not clips_in(outbox), "no clip may appear before it is complete"
    restarted = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "the interrupted clip")
    finally:
        assert stop(restarted) == 0
    time.sleep(1.0)  # an orphaned worker, had one survived, would write now
    assert clips_in(outbox) == [f"{photo.stem}.mp4"]
    assert not list(outbox.glob(".*part*")), "a partial file was left behind"
    assert (inbox / "done" / photo.name).is_file() and not (inbox / photo.name).exists()
    journal = Journal(outbox)
    try:
        job = journal.get(inbox / "done" / photo.name)
        assert job.state == "done" and job.attempts == 2
    finally:
        journal.close()


def test_sigterm_exits_zero_and_slow_writes_wait_until_complete(tmp_path):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 0.4)
    [photo] = shared_photos(1)
    data = photo.read_bytes()
    daemon = start_daemon(inbox, outbox, preset)
    try:
        time.sleep(1.5)
        target = inbox / "slow.jpg"
        chunk = len(data) // 8 + 1
        with target.open("wb") as handle:  # written in place, in chunks, over ~3 s
            for start in range(0, len(data), chunk):
                handle.write(data[start : start + chunk])
                handle.flush()
                os.fsync(handle.fileno())
                time.sleep(0.4)
                assert finished_jobs(outbox) == 0
                journal_path = outbox / ".kbbatch-journal.sqlite"
                if journal_path.exists():
                    journal = Journal(outbox)
                    assert journal.get(target) is None, "picked up before it was complete"
                    journal.close()
        wait_for(lambda: finished_jobs(outbox) == 1, 120, "the slowly written photo")
        assert (outbox / "slow.mp4").is_file()
    finally:
        assert stop(daemon) == 0


def test_a_hang_up_stops_the_daemon_as_sigterm_does(tmp_path):
    """SIGHUP (the SSH session it was started from dropped) killed the daemon at once: a
    partial clip left behind, the job left running and nothing logged."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    daemon = start_daemon(inbox, outbox, preset_file(tmp_path, 6.0, fps=25.0),
                          preexec_fn=_hang_ups_heard)
    try:
        time.sleep(1.5)
        shutil.copy(shared_photos(1)[0], inbox / "a.jpg")
        wait_for(lambda: clip_parts(outbox), 120, "a clip being encoded")
        daemon.send_signal(signal.SIGHUP)
        assert daemon.wait(timeout=120) == 0
    finally:
        if daemon.poll() is None:
            daemon.kill()
    assert clips_in(outbox) == ["a.mp4"] and not list(outbox.glob(".*part*"))
    assert "stopping" in (tmp_path / "daemon.log").read_text()


def _hang_ups_heard() -> None:
    """In the daemon: SIGHUP as a terminal's process has it (a test run under nohup, as a CI
    job may be, ignores it, and the daemon keeps it so)."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def folders_photo_and_map(tmp_path: Path):
    """Inbox and outbox, a shared photo, and a depth ramp of the photo's aspect (16-bit
    levels as floats; an eighth of its size)."""
    import cv2
    import numpy as np

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    [photo] = shared_photos(1)
    height, width = cv2.imread(str(photo), cv2.IMREAD_REDUCED_GRAYSCALE_8).shape
    ramp = np.linspace(1000, 60000, width, dtype=np.float32)[None, :].repeat(height, 0)
    return inbox, outbox, photo, ramp


def test_a_photo_waits_for_its_depth_map_still_being_written(tmp_path):
    """The settle time watched the photo alone: one that settled while its map was still
    being copied in failed ("not a readable image") and was filed with half its map."""
    import cv2
    import numpy as np

    inbox, outbox, photo, ramp = folders_photo_and_map(tmp_path)
    noise = np.random.default_rng(0).integers(0, 500, ramp.shape)
    encoded = cv2.imencode(".png", (ramp + noise).astype(np.uint16))[1].tobytes()
    daemon = start_daemon(inbox, outbox, preset_file(tmp_path, 0.4), "--depth", "auto")
    try:
        time.sleep(1.5)
        depth_map = inbox / "m.depth.png"
        chunk = len(encoded) // 8 + 1
        with depth_map.open("wb") as handle:  # copied in over about 3 s
            for start in range(0, len(encoded), chunk):
                handle.write(encoded[start : start + chunk])
                handle.flush()
                if start == 0:
                    shutil.copy(photo, inbox / "m.jpg")  # the photo whole at once
                time.sleep(0.4)
        wait_for(lambda: finished_jobs(outbox) == 1, 120, "the photo's clip")
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["m.mp4"]
    assert not list((inbox / "failed").glob("*"))
    assert "depth from file" in (tmp_path / "daemon.log").read_text()


def test_a_depth_map_that_comes_after_its_photos_clip_is_not_taken_for_the_next_photo(
        tmp_path):
    """A map uploaded after its photo's clip was made stayed in the inbox, and the next
    photo dropped under that name (another one) was made with it, without a word."""
    import cv2
    import numpy as np

    inbox, outbox, photo, ramp = folders_photo_and_map(tmp_path)
    daemon = start_daemon(inbox, outbox, preset_file(tmp_path, 0.4), "--depth", "auto")
    log_path = tmp_path / "daemon.log"
    try:
        time.sleep(1.5)
        shutil.copy(photo, inbox / "late.jpg")
        wait_for(lambda: finished_jobs(outbox) == 1, 120, "the first photo's clip")
        cv2.imwrite(str(inbox / "late.depth.png"), ramp.astype(np.uint16))
        wait_for(lambda: (inbox / "done" / "late.depth.png").exists(), 60,
                 "the late map filed beside its photo")
        mirrored = cv2.flip(cv2.imread(str(photo)), 1)
        cv2.imwrite(str(inbox / ".late.jpg"), mirrored)
        (inbox / ".late.jpg").rename(inbox / "late.jpg")  # another photo, the same name
        wait_for(lambda: finished_jobs(outbox) == 2, 120, "the second photo's clip")
    finally:
        assert stop(daemon) == 0
    log = log_path.read_text()
    assert "late.depth.png: came after the clip of late.jpg was made" in log, log
    assert "depth from file" not in log, log
    assert not list((inbox / "failed").glob("*"))


def test_a_stop_that_also_signals_the_encoder_leaves_the_photo_queued_not_failed(tmp_path):
    """systemd's default stop sends SIGTERM to every process of the service, ffmpeg included:
    the photo in progress went to failed/ and was never retried. It stays in the inbox, queued,
    and the next start makes its clip."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 8.0, fps=25.0)
    [photo] = shared_photos(1)
    for attempt in range(3):
        stem = f"a{attempt}"
        shutil.copy(photo, inbox / f"{stem}.jpg")
        daemon = start_daemon(inbox, outbox, preset)
        try:
            # Held still while the signals are sent, so that on a loaded machine it cannot
            # finish the clip between being found and being signalled (it then takes SIGTERM
            # on SIGCONT).
            encoders = held_encoders(outbox, stem)
            daemon.send_signal(signal.SIGTERM)
            for pid in encoders:
                os.kill(pid, signal.SIGTERM)
                os.kill(pid, signal.SIGCONT)
            assert daemon.wait(timeout=60) == 0
        finally:
            if daemon.poll() is None:
                daemon.kill()
        if not (outbox / f"{stem}.mp4").is_file():
            break
        # ffmpeg now and then finishes its clip in spite of the SIGTERM (seen in CI): the
        # photo is then rightly done, and the case under test was not reached: again
        assert (inbox / "done" / f"{stem}.jpg").is_file()
    else:
        raise AssertionError("ffmpeg finished its clip in spite of SIGTERM three times")
    log = (tmp_path / "daemon.log").read_text(errors="replace")
    assert (inbox / f"{stem}.jpg").is_file() and not (inbox / "failed").exists(), log
    journal = Journal(outbox)
    job = journal.get(inbox / f"{stem}.jpg")
    journal.close()
    assert job.state == "queued" and "stopped by" in job.error
    assert f"{stem}.mp4" not in clips_in(outbox)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: finished_jobs(outbox) == attempt + 1, 180,
                 f"{stem}.jpg's clip after the restart")
    finally:
        assert stop(daemon) == 0
    assert f"{stem}.mp4" in clips_in(outbox)
    assert (inbox / "done" / f"{stem}.jpg").is_file()


def test_a_photo_the_manifest_excludes_is_left_in_the_inbox_unrendered(tmp_path):
    """`"exclude": true` left a photo out of the batch, but the daemon rendered it."""
    from PIL import Image

    from .conftest import textured_image

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg")):
        Image.fromarray(textured_image(180, 320, seed=seed)).save(inbox / name)
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"version": 1, "images": {"b.jpg": {"exclude": true}}}')
    log_path = tmp_path / "daemon.log"
    daemon = start_daemon(inbox, outbox, preset_file(tmp_path, 0.4), "--manifest",
                          str(manifest), log_path=log_path)
    try:
        wait_for(lambda: clips_in(outbox) == ["a.mp4"]
                 and "b.jpg: excluded by the manifest" in log_path.read_text(), 120,
                 "a's clip and b's exclusion in the log")
        time.sleep(2.5)  # more than the settle time: b is not taken later either
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["a.mp4"]
    assert (inbox / "b.jpg").is_file() and (inbox / "done" / "a.jpg").is_file()
    assert log_path.read_text().count("b.jpg: excluded by the manifest") == 1


def test_status_drops_a_stopped_runs_advice_once_the_daemon_made_its_photos(tmp_path):
    """A batch run ended at its first failure (--fail-fast) into the daemon's outbox; the
    daemon then made the photo it had not started. `kbbatch status` still said "LAST RUN ...
    1 photo(s) not started: run again to finish"."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    preset = preset_file(tmp_path, 0.4)
    (inbox / "a.jpg").write_bytes(b"")  # fails: the run stops there
    shutil.copy(shared_photos(1)[0], inbox / "b.jpg")
    batch = subprocess.run([sys.executable, "-m", "kbbatch", str(inbox), "-o", str(outbox),
                            "--preset", str(preset), "--depth", "ramp", "--planner", "center",
                            "--fail-fast", "--quiet"], capture_output=True, text=True,
                           timeout=300)
    assert batch.returncode == 1, batch.stderr
    # the summary's counts alone ("0 clip(s) made ..., 1 failed") read as a whole run
    assert "ended at its first failure (--fail-fast): 1 photo(s) not started" in batch.stderr

    def status() -> str:
        return subprocess.run([sys.executable, "-m", "kbbatch", "status", str(outbox)],
                              capture_output=True, text=True, check=True).stdout

    assert "1 photo(s) not started: run again to finish" in status()
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: (inbox / "done" / "b.jpg").exists(), 240, "the daemon to make b.jpg")
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["b.mp4"]
    assert "LAST RUN" not in status()


def test_the_daemon_refuses_an_outbox_in_its_own_done_or_failed_folder(tmp_path):
    """Clips went into the inbox's failed/ (a user scanning it for failures found finished
    clips) or among the photos filed in done/."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for outbox in (inbox / "done", inbox / "failed" / "clips"):
        run = subprocess.run([sys.executable, "-m", "kbbatch", "watch", str(inbox), "--out",
                              str(outbox), "--depth", "ramp"], capture_output=True, text=True,
                             timeout=60)
        assert run.returncode == 2, run.stderr
        assert f"must not be in the inbox's {outbox.relative_to(inbox).parts[0]}/" in run.stderr
        assert not outbox.exists()
