"""The daemon as a real process against a hostile user (issue 14): a second photo with a used
name, a read-only inbox, a full outbox, a writer pausing longer than --settle, two daemons."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from kbbatch.journal import Journal

from .conftest import textured_image
from .test_nothing_lost import fill, tiny_mount  # noqa: F401 - a fixture
from .test_watch import (
    clip_parts,
    clips_in,
    finished_jobs,
    preset_file,
    start_daemon,
    stop,
    wait_for,
)

pytestmark = pytest.mark.slow
CLI = [sys.executable, "-m", "kbbatch"]


def photo_bytes(folder: Path, seed: int) -> bytes:
    path = folder / f"seed-{seed}.jpg"
    Image.fromarray(textured_image(180, 320, seed=seed)).save(path)
    return path.read_bytes()


def drop(inbox: Path, name: str, data: bytes) -> None:
    """Write elsewhere, then rename into the inbox: how finished files should arrive."""
    staging = inbox.parent / "staging"
    staging.mkdir(exist_ok=True)
    (staging / name).write_bytes(data)
    os.rename(staging / name, inbox / name)


def folders(tmp_path: Path) -> tuple[Path, Path, Path]:
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    return inbox, outbox, preset_file(tmp_path, 0.4)


def daemon_log(tmp_path: Path) -> str:
    return (tmp_path / "daemon.log").read_text(errors="replace")


def test_a_second_photo_with_a_used_name_gets_its_own_clip(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    first, second = photo_bytes(tmp_path, 1), photo_bytes(tmp_path, 2)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        drop(inbox, "IMG_0001.jpg", first)
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "the first IMG_0001.jpg")
        first_clip = (outbox / "IMG_0001.mp4").read_bytes()
        drop(inbox, "IMG_0001.jpg", second)
        wait_for(lambda: finished_jobs(outbox) == 2, 240, "the second IMG_0001.jpg")
    finally:
        assert stop(daemon) == 0
    clips = clips_in(outbox)
    assert len(clips) == 2 and "IMG_0001.mp4" in clips, clips
    assert (outbox / "IMG_0001.mp4").read_bytes() == first_clip, "the first clip was replaced"
    assert sorted(p.read_bytes() for p in (inbox / "done").iterdir()) == sorted([first, second])
    log = daemon_log(tmp_path)
    assert "named by its content" in log
    depth_lines = [line for line in log.splitlines() if "depth from" in line]
    assert depth_lines and all("IMG_0001.jpg: depth from" in line for line in depth_lines)
    status = subprocess.run([*CLI, "status", str(outbox)], capture_output=True, text=True)
    assert "done 2" in status.stdout, status.stdout


def test_a_read_only_inbox_keeps_its_photos_and_the_daemon_runs_on(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    good = photo_bytes(tmp_path, 3)
    (inbox / "good.jpg").write_bytes(good)
    (inbox / "bad.jpg").write_text("not a photo")
    past = time.time() - 3600  # written long ago: nothing is still writing them
    for name in ("good.jpg", "bad.jpg"):
        os.utime(inbox / name, (past, past))
    read_only = tmp_path / "read-only-inbox"
    read_only.mkdir()
    mounted = subprocess.run(["mount", "--bind", str(inbox), str(read_only)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot bind-mount here: {mounted.stderr.strip()}")
    try:
        subprocess.run(["mount", "-o", "remount,ro,bind", str(read_only)], check=True)
        daemon = start_daemon(read_only, outbox, preset)
        try:
            wait_for(lambda: finished_jobs(outbox) == 2, 240, "both photos")
            wait_for(lambda: (outbox / "failed" / "bad.jpg.error.json").is_file(), 60,
                     "the failure report in the outbox")
            assert daemon.poll() is None, "the daemon died"
        finally:
            assert stop(daemon) == 0
    finally:
        subprocess.run(["umount", str(read_only)], check=False)
    assert clips_in(outbox) == ["good.mp4"]
    assert sorted(p.name for p in inbox.iterdir()) == ["bad.jpg", "good.jpg"]
    log = daemon_log(tmp_path)
    assert "read-only" in log and "Traceback" not in log


def test_a_full_outbox_keeps_the_photo_queued_until_there_is_room(tmp_path, tiny_mount):  # noqa: F811
    """Before, a clip its full disk could not take failed its photo (moved to failed/)."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    outbox = tiny_mount / "outbox"
    outbox.mkdir()
    preset = preset_file(tmp_path, 2.0)
    preset.write_text(preset.read_text().replace("crf = 30", "crf = 0"))  # ~1 MB clips
    daemon = start_daemon(inbox, outbox, preset, log_path=tmp_path / "daemon.log")
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "a.jpg")
        filler = fill(tiny_mount, (outbox / "a.mp4").stat().st_size // 3)
        drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
        wait_for(lambda: (inbox / "failed").exists() or "disk is full" in daemon_log(tmp_path),
                 240, "b.jpg failed or waiting for room")
        time.sleep(3.0)  # the daemon's loop runs on meanwhile
        assert daemon.poll() is None, "the daemon died"
        assert not (inbox / "failed").exists(), "b.jpg was failed for its disk"
        assert (inbox / "b.jpg").is_file() and not (outbox / "b.mp4").exists()
        assert not list(outbox.glob(".*part*"))
        filler.unlink()
        drop(inbox, "c.jpg", photo_bytes(tmp_path, 3))
        wait_for(lambda: clips_in(outbox) == ["a.mp4", "b.mp4", "c.mp4"], 240,
                 "b.jpg and c.jpg once there is room")
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    assert "Traceback" not in log, log
    assert "taking photos again" in log, log
    assert sorted(p.name for p in (inbox / "done").iterdir()) == ["a.jpg", "b.jpg", "c.jpg"]
    journal = Journal(outbox)
    try:
        assert not journal.jobs("running") and not journal.jobs("failed")
        assert journal.counts()["done"] == 3
    finally:
        journal.close()
    assert not list(outbox.glob(".*part*"))


def test_a_writer_pausing_longer_than_settle_leaves_one_whole_photo(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    data = photo_bytes(tmp_path, 4)
    daemon = start_daemon(inbox, outbox, preset)  # --settle 1
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 120, "the daemon to start")
        chunk = len(data) // 4 + 1
        for start in range(0, len(data), chunk):
            with (inbox / "slow.jpg").open("ab") as handle:  # reopened, as a chunked copy does
                handle.write(data[start : start + chunk])
            time.sleep(3.0)  # three settle times: the daemon takes the partial file meanwhile
        wait_for(lambda: (outbox / "slow.mp4").is_file() and (inbox / "done").is_dir()
                 and not (inbox / "slow.jpg").exists(), 240, "the whole photo's clip")
    finally:
        assert stop(daemon) == 0
    assert [p.read_bytes() for p in (inbox / "done").iterdir()] == [data], "one whole copy"
    assert not (inbox / "failed").exists() or not list((inbox / "failed").iterdir())
    assert clips_in(outbox) == ["slow.mp4"]


def test_a_second_daemon_on_the_same_inbox_is_refused(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 120, "the first daemon")
        other = tmp_path / "other" / "deep" / "outbox"
        second = subprocess.run([*CLI, "watch", str(inbox), "--out", str(other), "--preset",
                                 str(preset)], capture_output=True, text=True, timeout=120)
        assert second.returncode != 0
        assert "already watching" in second.stderr and "Traceback" not in second.stderr
        # refused for its busy inbox, it left the output folder it made, with its parents
        assert not (tmp_path / "other").exists()
        # refused for its busy output folder, it made the inbox it named and left it there
        new_inbox = tmp_path / "new-inbox"
        third = subprocess.run([*CLI, "watch", str(new_inbox), "--out", str(outbox),
                                "--preset", str(preset)], capture_output=True, text=True,
                               timeout=120)
        assert third.returncode != 0 and "already writing clips into" in third.stderr
        assert not new_inbox.exists()
    finally:
        assert stop(daemon) == 0


def test_an_output_folder_inside_the_inbox_is_not_warned_of_as_a_subfolder(tmp_path):
    inbox, _, preset = folders(tmp_path)
    (inbox / "trip").mkdir()
    Image.fromarray(textured_image(180, 320)).save(inbox / "a.jpg")
    outbox = inbox / "clips"
    daemon = start_daemon(inbox, outbox, preset, log_path=tmp_path / "daemon.log")
    try:
        wait_for(lambda: clips_in(outbox) == ["a.mp4"], 120, "a.jpg's clip in inbox/clips")
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    assert "trip: subfolders are not watched" in log
    assert "clips: subfolders" not in log, log


def test_subfolders_and_broken_links_in_the_inbox_are_logged(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    (inbox / "holiday").mkdir()
    (inbox / "gone.jpg").symlink_to(tmp_path / "nowhere.jpg")
    os.mkfifo(inbox / "pipe.jpg")  # read, it would block a worker for good
    (inbox / "phone.heic").write_bytes(b"ftypheic")
    (inbox / "crops-previews").mkdir()  # an old `kbbatch plan` wrote these two
    Image.fromarray(textured_image(180, 320, seed=1)).save(inbox / "crops-contact.jpg")
    Image.fromarray(textured_image(180, 320, seed=2)).save(tmp_path / "space.jpg")
    (tmp_path / "space.jpg").rename(inbox / "space.jpg ")  # copied keeping a trailing space
    Image.fromarray(textured_image(180, 320)).save(inbox / "after.jpg")
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "space.jpg : the name ends in a space" in daemon_log(tmp_path)
                 and "holiday: subfolders are not watched" in daemon_log(tmp_path)
                 and "gone.jpg: broken symbolic link" in daemon_log(tmp_path)
                 and "pipe.jpg: not a regular file" in daemon_log(tmp_path)
                 and "phone.heic: a photo format kbbatch does not read" in daemon_log(tmp_path)
                 and "crops-contact.jpg: contact sheet of an earlier" in daemon_log(tmp_path),
                 120, "the six warnings")
        wait_for(lambda: clips_in(outbox) == ["after.mp4"], 120, "the photo after the pipe")
    finally:
        assert stop(daemon) == 0
    assert "ERROR" not in daemon_log(tmp_path)
    assert sorted(p.name for p in inbox.iterdir()) == [
        "crops-contact.jpg", "crops-previews", "done", "gone.jpg", "holiday", "phone.heic",
        "pipe.jpg", "space.jpg "]


def test_sigterm_logs_no_error(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    for round_index in range(3):
        daemon = start_daemon(inbox, outbox, preset)
        started = round_index + 1
        wait_for(lambda n=started: daemon_log(tmp_path).count("watching") >= n, 120,
                 "the daemon")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=60) == 0
    assert "ERROR" not in daemon_log(tmp_path), daemon_log(tmp_path)


def worker_pids(daemon: subprocess.Popen) -> list[int]:
    """The daemon's worker processes (its children)."""
    children = Path(f"/proc/{daemon.pid}/task/{daemon.pid}/children")
    return [int(pid) for pid in children.read_text().split()] if children.exists() else []


def kill_worker_mid_clip(daemon: subprocess.Popen, outbox: Path) -> None:
    wait_for(lambda: clip_parts(outbox) and worker_pids(daemon), 180,
             "a clip being encoded")
    for pid in worker_pids(daemon):
        os.kill(pid, signal.SIGKILL)


def test_a_killed_worker_is_replaced_and_its_photo_retried(tmp_path):
    """Issue 13, item 3: the daemon survives its workers."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 6.0, fps=25.0)  # long enough to be caught mid-encode
    drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
    daemon = start_daemon(inbox, outbox, preset)
    try:
        kill_worker_mid_clip(daemon, outbox)
        wait_for(lambda: finished_jobs(outbox) == 1, 300, "the retried clip")
        assert daemon.poll() is None, "the daemon died with its worker"
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["a.mp4"]
    assert (inbox / "done" / "a.jpg").is_file() and not (inbox / "failed").exists()
    assert "worker process rendering it died" in daemon_log(tmp_path)
    journal = Journal(outbox)
    try:
        assert journal.get(inbox / "done" / "a.jpg").state == "done"
    finally:
        journal.close()


def test_a_photo_that_kills_its_worker_twice_fails_and_the_daemon_goes_on(tmp_path):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 6.0, fps=25.0)
    drop(inbox, "killer.jpg", photo_bytes(tmp_path, 1))
    daemon = start_daemon(inbox, outbox, preset)
    try:
        kill_worker_mid_clip(daemon, outbox)
        wait_for(lambda: "taking it again" in daemon_log(tmp_path), 120, "the retry")
        kill_worker_mid_clip(daemon, outbox)
        wait_for(lambda: (inbox / "failed" / "killer.jpg.error.json").is_file(), 120,
                 "the failure report")
        report = (inbox / "failed" / "killer.jpg.error.json").read_text()
        assert "died 2 times" in report
        drop(inbox, "after.jpg", photo_bytes(tmp_path, 2))
        wait_for(lambda: (outbox / "after.mp4").is_file(), 300, "a photo after the failure")
        assert daemon.poll() is None
    finally:
        assert stop(daemon) == 0
    assert not list(outbox.glob(".*part*"))


def test_photos_in_flight_beside_a_dead_worker_are_not_blamed(tmp_path):
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 6.0, fps=25.0)
    for seed, name in ((1, "a.jpg"), (2, "b.jpg")):
        drop(inbox, name, photo_bytes(tmp_path, seed))
    daemon = start_daemon(inbox, outbox, preset, "--jobs", "2")
    try:
        wait_for(lambda: len(clip_parts(outbox)) == 2
                 and len(worker_pids(daemon)) == 2, 180, "two clips being encoded")
        os.kill(worker_pids(daemon)[0], signal.SIGKILL)  # one worker only
        wait_for(lambda: finished_jobs(outbox) == 2, 400, "both clips")
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["a.mp4", "b.mp4"]
    assert not (inbox / "failed").exists(), "an innocent photo was filed as failed"


def finish_one(tmp_path: Path, name: str, result_status: str, error: str | None = None
               ) -> tuple[Path, Journal, list[Path]]:
    """A real runner, journal and inbox finishing one photo (already gone from the inbox) whose
    worker reported result_status; returns the inbox, the open journal and what was requeued.
    (The races of a deletion cannot be timed in a real run: only the worker's result is made.)"""
    from concurrent.futures import Future

    from kbbatch.pipeline import ClipOptions, ClipResult
    from kbbatch.presets import load_preset
    from kbbatch.watch import InFlight, JobRunner, WatchSettings

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    photo, clip = inbox / name, Path(name).stem + ".mp4"
    settings = WatchSettings(inbox, outbox, load_preset("preview"), ClipOptions())
    journal = Journal(outbox)
    requeued: list[Path] = []
    runner = JobRunner(settings, journal, False, inbox / "failed",
                       lambda path, renamed: requeued.append(path))
    journal.start(photo, "1:1", "settings", clip, "a" * 64)
    if result_status == "done":
        (outbox / clip).write_bytes(b"the first photo's clip")
    future: Future = Future()
    future.set_result(ClipResult(str(photo), str(outbox / clip) if result_status == "done"
                                 else None, result_status, 0.1, error=error))
    runner.in_flight[future] = InFlight(photo, "1:1", clip, True)
    runner.finish_completed({photo})  # the observer saw the deletion
    assert runner.in_flight == {}
    return inbox, journal, requeued


def test_a_photo_deleted_while_it_is_read_is_skipped_not_filed_as_failed(tmp_path):
    """Deleted from the inbox between being taken and being read, a photo failed with a raw
    FileNotFoundError, left an error report and stayed FAILED in the status for good."""
    inbox, journal, requeued = finish_one(tmp_path, "gone.jpg", "failed",
                                          "gone.jpg: FileNotFoundError: no such file")
    assert requeued == []
    assert journal.jobs() == [], "nothing to report about a photo its owner removed"
    assert not (inbox / "failed").exists()
    journal.close()


def test_a_clip_of_a_deleted_photo_is_not_replaced_by_a_new_photo_of_its_name(tmp_path):
    """A photo deleted while its frames rendered still gets its clip; a different photo dropped
    under the same name later replaced that clip, as if it were the first one re-rendered."""
    inbox, journal, _ = finish_one(tmp_path, "del.jpg", "done")
    # a different photo arrives under the same name
    name = journal.clip_name(inbox / "del.jpg", "b" * 64, "del.mp4", tmp_path / "outbox")
    assert name == "del.bbbbbbbb.mp4", name
    [job] = journal.jobs("done")
    assert job.output == "del.mp4" and "removed from the inbox" in job.source
    journal.close()


def test_a_rename_seen_after_the_clip_is_finished_still_gives_the_clip_to_the_photo(
        tmp_path, monkeypatch):
    """A photo renamed just before its clip was finished, the observer's word of it not yet
    read, was taken for deleted: its clip was left to no photo, and the photo under its new
    name got a second clip. A made clip whose photo is gone now waits for that word."""
    from concurrent.futures import Future

    from kbbatch import watch
    from kbbatch.fingerprint import file_sha256
    from kbbatch.pipeline import ClipOptions, ClipResult
    from kbbatch.presets import load_preset
    from kbbatch.watch import InFlight, JobRunner, WatchSettings

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    photo, renamed = inbox / "p.jpg", inbox / "renamed.jpg"
    renamed.write_bytes(photo_bytes(tmp_path, 1))  # p.jpg as it is after the rename
    content = file_sha256(renamed)
    journal = Journal(outbox)
    runner = JobRunner(WatchSettings(inbox, outbox, load_preset("preview"), ClipOptions()),
                       journal, False, inbox / "failed", lambda path, again: None)
    journal.start(photo, "1:1", "settings", "p.mp4", content)
    (outbox / "p.mp4").write_bytes(b"the photo's clip")
    future: Future = Future()
    future.set_result(ClipResult(str(photo), str(outbox / "p.mp4"), "done", 0.1,
                                 content=content))
    runner.in_flight[future] = InFlight(photo, "1:1", "p.mp4", False, False, content)
    runner.finish_completed(set(), {})  # the rename not yet seen
    assert future in runner.in_flight, "finished before the observer could say what happened"
    runner.finish_completed(set(), {photo: renamed})  # the observer's word
    assert runner.in_flight == {}
    [job] = journal.jobs()
    assert (job.state, Path(job.source).name, job.output) == ("done", "renamed.jpg", "p.mp4")
    assert (inbox / "done" / "renamed.jpg").is_file()
    journal.close()

    # no word at all: after EVENT_LAG_S the clip is finished as a deleted photo's
    monkeypatch.setattr(watch, "EVENT_LAG_S", 0.0)
    outbox2 = tmp_path / "second"
    outbox2.mkdir()
    journal2 = Journal(outbox2)
    runner = JobRunner(WatchSettings(inbox, outbox2, load_preset("preview"), ClipOptions()),
                       journal2, False, inbox / "failed", lambda path, again: None)
    journal2.start(photo, "1:1", "settings", "p.mp4", content)
    (outbox2 / "p.mp4").write_bytes(b"the photo's clip")
    runner.in_flight[future] = InFlight(photo, "1:1", "p.mp4", False, False, content)
    runner.finish_completed(set(), {})
    assert runner.in_flight == {} and runner.gone_since == {}
    [job] = journal2.jobs("done")
    assert "removed from the inbox" in job.source
    journal2.close()


def test_deletions_are_kept_only_while_their_photos_are_in_flight(tmp_path):
    """Every photo moved to done/ is a deletion to the observer: kept for good, the record of
    deletions grew with every photo a long-running daemon made."""
    inbox, journal, _ = finish_one(tmp_path, "x.jpg", "done")
    from kbbatch.pipeline import ClipOptions
    from kbbatch.presets import load_preset
    from kbbatch.watch import JobRunner, WatchSettings

    runner = JobRunner(WatchSettings(inbox, tmp_path / "outbox", load_preset("preview"),
                                     ClipOptions()), journal, False, inbox / "failed",
                       lambda path, renamed: None)
    from concurrent.futures import Future

    from kbbatch.watch import InFlight

    rendering = inbox / "z.jpg"  # its clip is still being made: its deletion matters
    runner.in_flight[Future()] = InFlight(rendering, "1:1", "z.mp4", True)
    removed = {inbox / "x.jpg", inbox / "y.jpg", rendering}
    runner.finish_completed(removed)
    assert removed == {rendering}
    journal.close()


def test_a_photo_whose_encoder_is_stopped_again_and_again_is_set_aside(tmp_path):
    """ffmpeg takes SIGXCPU (a CPU-time limit) as it takes SIGTERM: counted as interruptions
    alone, such a photo was taken again for ever."""
    from concurrent.futures import Future

    from kbbatch.pipeline import ClipOptions, ClipResult
    from kbbatch.presets import load_preset
    from kbbatch.watch import ENCODER_STOPS_TO_FAIL, InFlight, JobRunner, WatchSettings

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    photo = inbox / "a.jpg"
    Image.fromarray(textured_image(180, 320)).save(photo)
    journal = Journal(outbox)
    requeued: list[Path] = []
    runner = JobRunner(WatchSettings(inbox, outbox, load_preset("preview"), ClipOptions()),
                       journal, False, inbox / "failed", lambda p, renamed: requeued.append(p))
    from kbbatch.journal import source_fingerprint

    taken = source_fingerprint(photo)  # unchanged since taken: not requeued as still written
    for attempt in range(1, ENCODER_STOPS_TO_FAIL + 1):
        journal.start(photo, taken, "settings", "a.mp4", "a" * 64)
        future: Future = Future()
        future.set_result(ClipResult(str(photo), None, "interrupted", 0.1,
                                     error="ffmpeg was stopped by a signal"))
        runner.in_flight[future] = InFlight(photo, taken, "a.mp4", True)
        runner.finish_completed()
        if attempt < ENCODER_STOPS_TO_FAIL:
            assert requeued == [photo] * attempt and journal.get(photo).state == "queued"
    assert len(requeued) == ENCODER_STOPS_TO_FAIL - 1
    assert (inbox / "failed" / "a.jpg").is_file()
    [failed] = journal.jobs("failed")
    assert f"{ENCODER_STOPS_TO_FAIL} times in a row" in failed.error
    journal.close()


@pytest.mark.parametrize("observer", [(), ("--poll",)], ids=["inotify", "polling"])
def test_a_photo_replaced_under_its_name_while_its_clip_is_made_does_not_take_that_clip(
        tmp_path, observer):
    """Deleted, and a different photo saved under its name before its clip was finished: the
    new photo was taken for an edit of the first (changed while processed), rendered again
    under the first one's clip name, and replaced the first photo's clip."""
    import hashlib
    import shutil

    from .test_watch import held_encoders

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 8.0, fps=25.0)  # held mid-encode below, to act during it
    first, second = photo_bytes(tmp_path, 1), photo_bytes(tmp_path, 2)
    drop(inbox, "a.jpg", first)
    daemon = start_daemon(inbox, outbox, preset, *observer)
    try:
        encoders = held_encoders(outbox, "a")  # so the replacement surely lands mid-clip
        (inbox / "a.jpg").unlink()
        time.sleep(0.5)
        staging = tmp_path / "other.jpg"
        staging.write_bytes(second)
        shutil.copy(staging, inbox / "a.jpg")  # a new file under the same name
        time.sleep(1.0)  # the daemon sees the deletion and the new file
        for pid in encoders:
            os.kill(pid, signal.SIGCONT)
        wait_for(lambda: len(clips_in(outbox)) == 2, 240, "a clip of each photo")
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    by_output = {job.output: job for job in Journal(outbox).jobs("done")}
    second_name = f"a.{hashlib.sha256(second).hexdigest()[:8]}.mp4"
    assert sorted(by_output) == sorted(["a.mp4", second_name]), log
    assert by_output["a.mp4"].content == hashlib.sha256(first).hexdigest(), log
    assert by_output[second_name].content == hashlib.sha256(second).hexdigest()
    assert (inbox / "done" / "a.jpg").read_bytes() == second
    assert "replaced by another photo" in log


def test_a_linked_photo_moved_to_done_still_leads_to_its_file(tmp_path):
    """A relative link (`inbox/x.jpg -> ../photos/x.jpg`) moved into done/ as it was led
    nowhere; an absolute one moves as it is; a broken link in done/ is not replaced."""
    from kbbatch.watch import move_photo, unique_destination

    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "x.jpg").write_bytes(b"the photo")
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    (inbox / "rel.jpg").symlink_to("../photos/x.jpg")
    (inbox / "abs.jpg").symlink_to(photos / "x.jpg")
    (inbox / "done").mkdir()
    (inbox / "done" / "rel.jpg").symlink_to("nowhere.jpg")  # an earlier photo's broken link
    for name in ("rel.jpg", "abs.jpg"):
        destination = unique_destination(inbox / "done", name)
        move_photo(inbox / name, destination)
        assert not os.path.lexists(inbox / name)
        assert destination.read_bytes() == b"the photo", name
    assert os.readlink(inbox / "done" / "rel.jpg") == "nowhere.jpg"
    assert (inbox / "done" / "rel.1.jpg").resolve() == (photos / "x.jpg").resolve()


def test_a_photos_depth_map_goes_to_done_with_it(tmp_path):
    """Left in the inbox, b.disparity.png was used for the next, different b.jpg dropped
    there: a wrong depth for that photo, without a word. (The daemon runs with --depth file,
    so the map is what its clip is made from.)"""
    import cv2

    inbox, outbox, preset = folders(tmp_path)
    Image.fromarray(textured_image(180, 320, seed=1)).save(inbox / "b.jpg")
    ramp = np.tile(np.linspace(1000, 60000, 320).astype(np.uint16), (180, 1))
    cv2.imwrite(str(inbox / "b.disparity.png"), ramp)
    for name in ("c.jpg", "c.png"):  # two photos of one map: it stays for the second
        Image.fromarray(textured_image(180, 320, seed=2)).save(inbox / name)
    cv2.imwrite(str(inbox / "c.depth.png"), ramp)
    daemon = start_daemon(inbox, outbox, preset, "--depth", "file")
    try:
        wait_for(lambda: len(clips_in(outbox)) == 3
                 and not [p for p in inbox.iterdir() if p.is_file()], 120,
                 "three clips, and the inbox empty")
    finally:
        assert stop(daemon) == 0
    clips = clips_in(outbox)
    assert clips[0] == "b.mp4" and all(clip.startswith("c.") for clip in clips[1:]), clips
    done = sorted(p.name for p in (inbox / "done").iterdir())
    assert done == ["b.disparity.png", "b.jpg", "c.depth.png", "c.jpg", "c.png"], done
    assert "ERROR" not in daemon_log(tmp_path)


def test_the_daemon_follows_its_manifest_and_leaves_the_maps_it_names(tmp_path):
    """The manifest was read once at start: an exclude saved later (from `kbbatch review`)
    was ignored; a depth map the manifest names, dropped in the inbox, became a clip."""
    inbox, outbox, preset = folders(tmp_path)
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {
        "map-user.jpg": {"depth": "inbox/user.map.png"}}}))
    cv2.imwrite(str(inbox / "user.map.png"), np.tile(np.arange(320, dtype=np.uint8)[None],
                                                     (180, 1)))
    (inbox / "trip").mkdir()  # said once in the log, and (before) again at each manifest change
    (inbox / "phone.heic").write_bytes(b"\0\0\0\x18ftypheic")
    daemon = start_daemon(inbox, outbox, preset, "--manifest", str(manifest))
    try:
        wait_for(lambda: "user.map.png: the depth map of map-user.jpg in the manifest" in
                 daemon_log(tmp_path), 120, "the map left alone")
        time.sleep(0.5)  # a later second on coarse file-time clocks
        manifest.write_text(json.dumps({"version": 1, "images": {"late.jpg": {"exclude": True}}}))
        wait_for(lambda: "m.json: changed; read again" in daemon_log(tmp_path), 120, "the reread")
        Image.fromarray(textured_image(180, 320, seed=2)).save(inbox / "late.jpg")
        wait_for(lambda: "late.jpg: excluded by the manifest" in daemon_log(tmp_path), 120,
                 "the exclude saved after the start")
        wait_for(lambda: clips_in(outbox) == ["user.map.mp4"], 120,
                 "the map, no longer named by the manifest, taken as a photo")
        assert "late.mp4" not in clips_in(outbox)
        time.sleep(0.5)
        manifest.write_text(json.dumps({"version": 1, "images": {
            "late.jpg": {"exclude": True, "duration_s": 3}}}))
        wait_for(lambda: daemon_log(tmp_path).count("m.json: changed; read again") == 2, 120,
                 "the second reread")
        time.sleep(2.0)  # loops of the daemon after it
        assert "late.mp4" not in clips_in(outbox)
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    for said_once in ("trip: subfolders are not watched", "phone.heic:",
                      "late.jpg: excluded by the manifest"):
        assert log.count(said_once) == 1, (said_once, log)


def test_watch_refuses_a_file_named_done_an_empty_out_and_a_thousand_workers(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    (inbox / "done").write_text("my notes")
    made = tmp_path / "made" / "clips"  # refused, it left the output folder it made
    refused = subprocess.run([*CLI, "watch", str(inbox), "--out", str(made), "--preset",
                              str(preset)], capture_output=True, text=True, timeout=120)
    assert refused.returncode == 1 and "done: not a folder; the daemon moves finished photos" \
        in refused.stderr and "Traceback" not in refused.stderr
    assert (inbox / "done").read_text() == "my notes"
    assert not (tmp_path / "made").exists()
    empty = subprocess.run([*CLI, "watch", str(inbox), "--out", "", "--preset", str(preset)],
                           capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert empty.returncode == 2 and "an empty path" in empty.stderr
    many = subprocess.run([*CLI, "watch", str(inbox), "--out", str(outbox), "--jobs", "100000"],
                          capture_output=True, text=True, timeout=120)
    assert many.returncode == 2 and "--jobs 100000: at most" in many.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inbox", "outbox", "test-preset.toml"]


def test_a_file_named_done_made_after_the_start_is_said_and_the_daemon_goes_on(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 120, "the start")
        (inbox / "done").write_text("my notes")
        Image.fromarray(textured_image(180, 320)).save(inbox / "a.jpg")
        wait_for(lambda: "a.jpg: cannot be moved to done/" in daemon_log(tmp_path), 120,
                 "the move refused")
        assert daemon.poll() is None, daemon_log(tmp_path)  # it crashed here
        assert clips_in(outbox) == ["a.mp4"] and (inbox / "a.jpg").is_file()
    finally:
        assert stop(daemon) == 0
    assert (inbox / "done").read_text() == "my notes"
    assert "Traceback" not in daemon_log(tmp_path)


def test_workers_forked_after_the_start_up_model_check_make_their_clips(tmp_path, monkeypatch):
    """The check at start loaded each unpinned network (its tensors) into a session that was
    still alive when the daemon forked its workers: they hung at their first photo."""
    from .test_models import tiny_depth_model

    inbox, outbox, preset = folders(tmp_path)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "depth_anything_v2_small.onnx").write_bytes(tiny_depth_model())
    monkeypatch.setenv("KBBATCH_MODELS", str(tmp_path / "models"))
    for seed in range(2):
        Image.fromarray(textured_image(180, 320, seed)).save(inbox / f"p{seed}.jpg")
    daemon = start_daemon(inbox, outbox, preset, "--depth", "onnx", "--jobs", "2")
    try:
        wait_for(lambda: clips_in(outbox) == ["p0.mp4", "p1.mp4"], 120, "both clips")
    finally:
        assert stop(daemon) == 0
    assert "depth from onnx (depth-anything-v2-small)" in daemon_log(tmp_path)


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_a_photo_renamed_while_its_clip_is_made_gets_one_clip(tmp_path, jobs):
    """Renamed in the inbox while its clip was made, a photo got a second clip under its new
    name (with --jobs 2 started at once beside the first), and the first clip was left with
    no photo of its name in done/."""
    from .test_watch import held_encoders

    inbox, outbox, _ = folders(tmp_path)
    preset = preset_file(tmp_path, 4.0, fps=25.0)  # an encode long enough to be held
    daemon = start_daemon(inbox, outbox, preset, "--jobs", jobs)
    try:
        drop(inbox, "p.jpg", photo_bytes(tmp_path, 1))
        encoders = held_encoders(outbox, "p")
        os.rename(inbox / "p.jpg", inbox / "renamed.jpg")
        time.sleep(1.0)  # the rename is seen while the clip is unfinished
        for pid in encoders:
            os.kill(pid, signal.SIGCONT)
        wait_for(lambda: (inbox / "done" / "renamed.jpg").is_file(), 120, "the photo in done/")
        time.sleep(3.0)  # a second clip would be started meanwhile
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["p.mp4"]
    assert sorted(p.name for p in (inbox / "done").iterdir()) == ["renamed.jpg"]
    assert "p.jpg was renamed renamed.jpg while its clip was made" in daemon_log(tmp_path)
    journal = Journal(outbox)
    try:
        [job] = journal.jobs()
        assert (job.state, Path(job.source).name, job.output) == ("done", "renamed.jpg", "p.mp4")
    finally:
        journal.close()


def test_status_counts_the_photos_waiting_in_the_inbox(tmp_path):
    """`kbbatch status` said "queued 0" while 29 photos waited in the daemon's inbox, and after
    a stop never mentioned the photos left there."""
    from .test_watch import held_encoders

    inbox, outbox, _ = folders(tmp_path)
    preset = preset_file(tmp_path, 4.0, fps=25.0)  # an encode long enough to be held
    daemon = start_daemon(inbox, outbox, preset)
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        encoders = held_encoders(outbox, "a")
        for seed in (2, 3):
            drop(inbox, f"w{seed}.jpg", photo_bytes(tmp_path, seed))
        status = subprocess.run([*CLI, "status", str(outbox)], capture_output=True, text=True)
        for pid in encoders:
            os.kill(pid, signal.SIGCONT)
    finally:
        assert stop(daemon) == 0
    assert "queued 2, running 1, done 0" in status.stdout, status.stdout
    assert f"WAITING 2 photo(s) in the inbox {inbox}, taken as they settle" in status.stdout
    # stopped while a.jpg's clip was made (one job): the other two were never started
    assert sorted(p.name for p in inbox.iterdir() if p.is_file()) == ["w2.jpg", "w3.jpg"]
    assert (inbox / "done" / "a.jpg").is_file()
    status = subprocess.run([*CLI, "status", str(outbox)], capture_output=True, text=True)
    assert "queued 2, running 0, done 1" in status.stdout, status.stdout
    assert f"WAITING 2 photo(s) in the inbox {inbox}, taken when the daemon runs again" in \
        status.stdout, status.stdout
    assert "NOTE" not in status.stdout
    inbox.rename(tmp_path / "renamed")  # status said nothing of the inbox it names
    status = subprocess.run([*CLI, "status", str(outbox)], capture_output=True, text=True)
    assert f"NOTE the daemon's inbox {inbox} is not there (renamed or removed?)" in \
        status.stdout, status.stdout


def test_status_does_not_count_the_photos_the_daemons_manifest_excludes(tmp_path):
    """A photo the daemon's manifest excludes is left in the inbox for good, yet `kbbatch
    status` counted it as queued and waiting to be taken."""
    inbox, outbox, preset = folders(tmp_path)
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"skip.jpg": {"exclude": True},
                                                             "NEAR.JPG": {"exclude": True}}}))
    drop(inbox, "skip.jpg", photo_bytes(tmp_path, 1))
    drop(inbox, "near.jpg", photo_bytes(tmp_path, 2))  # a near miss: made, but said
    daemon = start_daemon(inbox, outbox, preset, "--manifest", str(manifest))
    try:
        wait_for(lambda: "skip.jpg: excluded by the manifest" in daemon_log(tmp_path)
                 and (outbox / "near.mp4").is_file(), 120, "the photos passed over and made")
    finally:
        assert stop(daemon) == 0
    assert "near.jpg: the manifest's entry 'NEAR.JPG' is not its exact file name, so it does " \
        "not apply" in daemon_log(tmp_path)
    drop(inbox, "new.jpg", photo_bytes(tmp_path, 3))
    status = subprocess.run([*CLI, "status", str(outbox)], capture_output=True, text=True)
    assert "queued 1, running 0, done 1" in status.stdout, status.stdout
    assert f"WAITING 1 photo(s) in the inbox {inbox}" in status.stdout, status.stdout


def assert_held_then_made(tmp_path: Path, inbox: Path, outbox: Path, daemon, mend) -> str:
    """b.jpg dropped while the run is at fault stays in the inbox (not in failed/), and is made
    once `mend()` has put the fault right; the daemon's log."""
    drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
    wait_for(lambda: "no photo is taken until that is mended" in daemon_log(tmp_path)
             or (inbox / "failed").exists(), 240, "b.jpg held or failed")
    time.sleep(2.0)  # the daemon's loop runs on meanwhile
    assert daemon.poll() is None, "the daemon died"
    assert not (inbox / "failed").exists(), "b.jpg was failed for the run's fault"
    assert (inbox / "b.jpg").is_file() and not (outbox / "b.mp4").exists()
    mend()
    wait_for(lambda: (inbox / "done" / "b.jpg").is_file(), 240, "b.jpg once mended")
    assert (outbox / "b.mp4").is_file()
    log = daemon_log(tmp_path)
    assert "taking photos again" in log and "Traceback" not in log, log
    return log


def test_an_outbox_made_read_only_while_the_daemon_runs_keeps_its_photos_queued(tmp_path):
    """Its output folder made read-only, every later photo went to failed/ (its clip could not
    be made there), for its owner to move back one by one."""
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: (inbox / "done" / "a.jpg").is_file(), 240, "a.jpg")
        # immutable: no file can be made in it, even by root, whom permission bits let through
        if subprocess.run(["chattr", "+i", str(outbox)], capture_output=True).returncode:
            pytest.skip("chattr +i is not allowed here")
        try:
            log = assert_held_then_made(
                tmp_path, inbox, outbox, daemon,
                lambda: subprocess.run(["chattr", "-i", str(outbox)], check=True))
        finally:
            subprocess.run(["chattr", "-i", str(outbox)], check=False)
    finally:
        assert stop(daemon) == 0
    assert "files can no longer be made in the output folder" in log, log


def test_a_model_damaged_while_the_daemon_runs_keeps_its_photos_queued(tmp_path, monkeypatch):
    """A model file damaged while the daemon ran failed every later photo into failed/."""
    from .test_models import tiny_depth_model

    inbox, outbox, preset = folders(tmp_path)
    model = tmp_path / "models" / "depth_anything_v2_small.onnx"
    model.parent.mkdir()
    model.write_bytes(tiny_depth_model())
    monkeypatch.setenv("KBBATCH_MODELS", str(model.parent))
    daemon = start_daemon(inbox, outbox, preset, "--depth", "onnx")
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: (inbox / "done" / "a.jpg").is_file(), 240, "a.jpg")
        model.write_bytes(b"half a download")
        log = assert_held_then_made(tmp_path, inbox, outbox, daemon,
                                    lambda: model.write_bytes(tiny_depth_model()))
    finally:
        assert stop(daemon) == 0
    assert f"{model}: model depth-anything-v2-small cannot be loaded" in log, log


@pytest.mark.parametrize("removed", ["outbox", "inbox"])
def test_a_folder_removed_under_the_daemon_stops_it_and_fails_no_photo(tmp_path, removed):
    """Its output folder removed, the daemon filed every later photo as failed (its clip found
    no folder); its inbox moved away or made again, it watched nothing, without a word."""
    import shutil

    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: (inbox / "done" / "a.jpg").is_file(), 240, "a.jpg")
        if removed == "outbox":
            shutil.rmtree(outbox)
            drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
        else:
            inbox.rename(tmp_path / "inbox-moved")
            inbox.mkdir()  # made again, as a script that cleans up would
            drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
        daemon.wait(timeout=120)
    finally:
        if daemon.poll() is None:
            stop(daemon)
    assert daemon.returncode == 1, daemon_log(tmp_path)
    log = daemon_log(tmp_path)
    which = "output folder" if removed == "outbox" else "inbox"
    assert f"the {which} was removed, renamed or made again" in log, log
    assert "Traceback" not in log
    assert (inbox / "b.jpg").is_file() and not (inbox / "failed").exists()


def test_a_photo_deleted_while_no_daemon_ran_is_not_resumed_for_ever(tmp_path):
    """kill -9 mid-clip, the photo deleted, the daemon started again: its job is dropped (said
    once), not left running in `kbbatch status` and 'resumed' at every start."""
    inbox, outbox, preset = folders(tmp_path)
    gone = inbox / "gone.jpg"
    elsewhere = tmp_path / "card" / "c.jpg"  # a batch's, on a card out of the reader
    journal = Journal(outbox)
    try:
        journal.start(gone, "fingerprint", "settings", "gone.mp4", "content")  # running
        journal.start(elsewhere, "fingerprint", "settings", "c.mp4", "content")
    finally:
        journal.close()
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 60, "the daemon to start")
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    assert "dropped gone.jpg: the photo was removed" in log and "resuming gone.jpg" not in log
    journal = Journal(outbox)
    try:
        assert journal.get(gone) is None
        assert journal.get(elsewhere).state == "running"  # not the daemon's to drop
    finally:
        journal.close()


def test_the_daemon_keeps_a_clips_name_when_a_same_stem_photo_arrives(tmp_path):
    """--keep-sources, a.jpg made into a.mp4; a.png dropped beside it later and the daemon
    restarted: a.jpg's clip was made again as a.jpg.mp4 (a copy, and a.mp4 left stale)."""
    inbox, outbox, preset = folders(tmp_path)

    def daemon_until(finished: int, what: str) -> None:
        daemon = start_daemon(inbox, outbox, preset, "--keep-sources")
        try:
            wait_for(lambda: finished_jobs(outbox) == finished, 240, what)
        finally:
            assert stop(daemon) == 0

    drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
    daemon_until(1, "a.jpg's clip")
    made = (outbox / "a.mp4").read_bytes()
    drop(inbox, "a.png", photo_bytes(tmp_path, 2))
    daemon_until(2, "a.png's clip")
    assert clips_in(outbox) == ["a.mp4", "a.png.mp4"]
    assert (outbox / "a.mp4").read_bytes() == made
    journal = Journal(outbox)
    try:
        assert journal.get(inbox / "a.jpg").attempts == 1
    finally:
        journal.close()


def test_an_inbox_link_pointed_elsewhere_stops_the_daemon(tmp_path):
    """The daemon follows a link to its inbox (its journal keys the real folder): pointed at
    another folder while it ran, the link left the daemon watching a folder nobody used,
    without a word."""
    inbox, outbox, preset = folders(tmp_path)
    link = tmp_path / "link"
    link.symlink_to(inbox, target_is_directory=True)
    other = tmp_path / "other"
    other.mkdir()
    daemon = start_daemon(link, outbox, preset)
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 60, "the daemon to start")
        link.unlink()
        link.symlink_to(other, target_is_directory=True)
        drop(other, "a.jpg", photo_bytes(tmp_path, 1))
        daemon.wait(timeout=120)
    finally:
        if daemon.poll() is None:
            stop(daemon)
    log = daemon_log(tmp_path)
    assert daemon.returncode == 1, log
    assert f"{link}: the inbox was removed, renamed or made again" in log, log


def test_a_dangling_inbox_link_is_refused_not_made(tmp_path):
    """A link to a share not mounted yet: the daemon made the folder the link names on the
    local disk, under the mount point, which the share then hid."""
    link = tmp_path / "inbox"
    link.symlink_to(tmp_path / "mnt" / "inbox")
    (tmp_path / "mnt").mkdir()
    run = subprocess.run([*CLI, "watch", str(link), "--out", str(tmp_path / "out"), "--depth",
                          "ramp"], capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "the inbox is not a folder" in run.stderr, run.stderr
    assert not (tmp_path / "mnt" / "inbox").exists()


def test_a_link_in_a_loop_as_inbox_is_an_error_not_a_traceback(tmp_path):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    run = subprocess.run([*CLI, "watch", str(loop), "--out", str(tmp_path / "out"), "--depth",
                          "ramp"], capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "Traceback" not in run.stderr, run.stderr
    assert str(loop) in run.stderr


def test_the_daemon_says_a_clip_is_replaced_only_once_it_is(tmp_path):
    """A photo rewritten with a truncated file: the daemon said its clip was replaced when it
    took the photo, then failed it, the old clip untouched."""
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset, "--keep-sources")
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "a.jpg")
        made = (outbox / "a.mp4").stat().st_mtime_ns
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 2)[:3000])
        wait_for(lambda: "failed a.jpg" in daemon_log(tmp_path)
                 or (inbox / "failed" / "a.jpg").exists(), 240, "the truncated photo to fail")
        drop(inbox, "b.jpg", photo_bytes(tmp_path, 3))
        wait_for(lambda: (outbox / "b.mp4").is_file(), 240, "b.jpg")
    finally:
        assert stop(daemon) == 0
    assert (outbox / "a.mp4").stat().st_mtime_ns == made
    assert "changed since a.mp4 was made" not in daemon_log(tmp_path)


def test_a_clip_whose_journal_was_deleted_is_known_by_its_mark(tmp_path):
    """The journal gone, a photo dropped again had its clip made again beside the first under
    a content name; the clip's mark says it is this photo's, made with these settings."""
    from kbbatch.journal import JOURNAL_NAME

    inbox, outbox, preset = folders(tmp_path)
    drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: (inbox / "done" / "a.jpg").exists(), 240, "a.jpg made")
    finally:
        assert stop(daemon) == 0
    made = (outbox / "a.mp4").stat().st_mtime_ns
    for journal_file in outbox.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    os.rename(inbox / "done" / "a.jpg", inbox / "a.jpg")
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: (inbox / "done" / "a.jpg").exists(), 240, "a.jpg taken again")
    finally:
        assert stop(daemon) == 0
    assert "a.jpg: clip already complete" in daemon_log(tmp_path)
    assert clips_in(outbox) == ["a.mp4"] and (outbox / "a.mp4").stat().st_mtime_ns == made


def test_the_same_photo_dropped_again_is_not_made_again(tmp_path):
    """A photo dropped in the inbox a second time (copied again from the card, or put back from
    done/) was made again and its clip rewritten: its clip is complete, so the daemon says so
    and files the photo in done/ beside the first copy; another photo under its name is still
    made, under a name of its own."""
    inbox, outbox, preset = folders(tmp_path)
    first = photo_bytes(tmp_path, 1)
    daemon = start_daemon(inbox, outbox, preset)
    try:
        drop(inbox, "IMG_0001.jpg", first)
        wait_for(lambda: finished_jobs(outbox) == 1 and (inbox / "done" / "IMG_0001.jpg").exists(),
                 240, "the first IMG_0001.jpg")
        made = (outbox / "IMG_0001.mp4").stat().st_mtime_ns
        drop(inbox, "IMG_0001.jpg", first)  # the same bytes again, a new file
        wait_for(lambda: len(list((inbox / "done").iterdir())) == 2, 240,
                 "the second copy in done/")
        drop(inbox, "IMG_0001.jpg", photo_bytes(tmp_path, 2))  # another photo of the name
        wait_for(lambda: len(clips_in(outbox)) == 2, 240, "the other photo's clip")
    finally:
        assert stop(daemon) == 0
    assert (outbox / "IMG_0001.mp4").stat().st_mtime_ns == made, "the clip was made again"
    assert daemon_log(tmp_path).count("start IMG_0001.jpg") == 2
    assert "IMG_0001.jpg: clip already complete" in daemon_log(tmp_path)
    assert sorted(p.read_bytes() for p in (inbox / "done").iterdir()) == sorted(
        [first, first, photo_bytes(tmp_path, 2)])


def test_with_keep_sources_a_photo_deleted_and_another_saved_under_its_name_gets_its_own_clip(
        tmp_path):
    """--keep-sources, a phone's upload folder: IMG_0001 made, the inbox cleared, the camera's
    numbering restarted. The new IMG_0001 was taken for an edit of the deleted one and its
    clip replaced the first one's."""
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset, "--keep-sources")
    try:
        drop(inbox, "IMG_0001.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "the first IMG_0001.jpg")
        first_clip = (outbox / "IMG_0001.mp4").read_bytes()
        (inbox / "IMG_0001.jpg").unlink()
        wait_for(lambda: "IMG_0001.jpg was removed from the inbox; its clip IMG_0001.mp4 stays"
                 in daemon_log(tmp_path), 60, "the removal to be seen")
        drop(inbox, "IMG_0001.jpg", photo_bytes(tmp_path, 2))
        wait_for(lambda: len(clips_in(outbox)) == 2, 240, "the second photo's clip")
    finally:
        assert stop(daemon) == 0
    assert (outbox / "IMG_0001.mp4").read_bytes() == first_clip
    assert "changed since" not in daemon_log(tmp_path)


def test_a_photo_saved_over_with_its_size_and_time_kept_is_made_again(tmp_path):
    """A photo saved over while its clip was made, with the same size and time (exiftool -P
    rewriting a tag in place; a fixed-size scan): the daemon filed the new photo in done/
    with the old photo's clip, and the new one never got its own."""
    from .test_watch import held_encoders

    inbox, outbox, _ = folders(tmp_path)
    preset = preset_file(tmp_path, 4.0, fps=25.0)
    first, second = (tmp_path / "first.bmp", tmp_path / "second.bmp")
    Image.fromarray(textured_image(180, 320, seed=1)).save(first)
    Image.fromarray(textured_image(180, 320, seed=2)).save(second)
    assert first.stat().st_size == second.stat().st_size  # BMP: the size of the picture
    drop(inbox, "x.bmp", first.read_bytes())
    taken = (inbox / "x.bmp").stat()
    daemon = start_daemon(inbox, outbox, preset)
    try:
        encoders = held_encoders(outbox, "x")  # read already: its clip is being encoded
        (inbox / "x.bmp").write_bytes(second.read_bytes())
        os.utime(inbox / "x.bmp", ns=(taken.st_atime_ns, taken.st_mtime_ns))
        for pid in encoders:
            os.kill(pid, signal.SIGCONT)
        wait_for(lambda: (inbox / "done" / "x.bmp").exists(), 240, "x.bmp filed in done/")
    finally:
        assert stop(daemon) == 0
    log = daemon_log(tmp_path)
    assert "x.bmp changed while it was processed" in log, log
    assert log.count("start x.bmp") == 2, log
    assert (inbox / "done" / "x.bmp").read_bytes() == second.read_bytes()
    reference = tmp_path / "reference"
    reference.mkdir()
    (reference / "x.bmp").write_bytes(second.read_bytes())
    subprocess.run([*CLI, str(reference), "-o", str(reference / "out"), "--preset", str(preset),
                    "--depth", "ramp", "--planner", "center", "--quiet"], check=True)
    assert (outbox / "x.mp4").read_bytes() == (reference / "out" / "x.mp4").read_bytes(), \
        "the clip is not the new photo's"


def test_a_clip_of_a_photo_replaced_before_its_read_is_journaled_under_the_bytes_read(
        tmp_path):
    """X.jpg (bytes A) taken, then deleted and another X.jpg (bytes B) dropped before the
    worker read it: the clip, made from B, was journaled under A, and A dropped again later
    was called up to date with B's clip. (The worker's result is given, not rendered: the
    race between a take and a worker's read cannot be timed in a real daemon.)"""
    from concurrent.futures import Future

    from kbbatch.fingerprint import file_sha256
    from kbbatch.journal import source_fingerprint
    from kbbatch.pipeline import ClipOptions, ClipResult, clip_fingerprints
    from kbbatch.presets import load_preset
    from kbbatch.watch import InFlight, JobRunner, WatchSettings

    inbox, outbox = tmp_path / "in", tmp_path / "out"
    inbox.mkdir()
    outbox.mkdir()
    preset, options = load_preset("preview"), ClipOptions()
    journal = Journal(outbox)
    requeued: list[Path] = []
    runner = JobRunner(WatchSettings(inbox, outbox, preset, options), journal, False,
                       tmp_path / "reports", lambda path, renamed: requeued.append(path))
    photo = inbox / "X.jpg"
    photo.write_bytes(photo_bytes(tmp_path, 1))
    taken, content_a = source_fingerprint(photo), file_sha256(photo)
    settings = clip_fingerprints(photo, content_a, preset, options, None)
    journal.start(photo, taken, settings[0], "X.mp4", content_a)
    made = Future()
    runner.in_flight[made] = InFlight(photo, taken, "X.mp4", False, False, content_a)
    photo.unlink()
    photo.write_bytes(photo_bytes(tmp_path, 2))  # another photo, read by the worker
    (outbox / "X.mp4").write_bytes(b"the clip of the second photo")
    made.set_result(ClipResult(str(photo), str(outbox / "X.mp4"), "done", 1.0,
                               content=file_sha256(photo)))
    runner.finish_completed(removed={photo})
    assert requeued == [photo], "the second photo is one of its own, taken again"
    photo.unlink()
    photo.write_bytes(photo_bytes(tmp_path, 1))  # the first photo dropped again
    assert not journal.is_up_to_date(photo, source_fingerprint(photo), settings,
                                     outbox / "X.mp4", content_a)
    journal.close()


def test_with_keep_sources_a_depth_map_saved_later_remakes_the_clip_and_clears_its_failure(
        tmp_path):
    """--keep-sources: a depth map saved beside a made photo was taken only after a restart;
    a photo made after it failed kept its failure report, which said it had failed."""
    inbox, outbox, preset = folders(tmp_path)
    daemon = start_daemon(inbox, outbox, preset, "--keep-sources", "--depth", "auto")
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "a.jpg's first clip")
        first = (outbox / "a.mp4").read_bytes()
        (inbox / "b.jpg").write_text("not a photo yet")
        os.utime(inbox / "b.jpg", (time.time() - 3600,) * 2)  # not still being written
        report = inbox / "failed" / "b.jpg.error.json"
        wait_for(report.is_file, 120, "b.jpg's failure report")
        ramp = np.tile(np.linspace(1000, 60000, 320).astype(np.uint16), (180, 1))
        cv2.imwrite(str(inbox / "a.depth.png"), ramp)
        looked_again = "a.jpg: its depth map a.depth.png was saved; looked at again"
        wait_for(lambda: "done a.jpg" in daemon_log(tmp_path).partition(looked_again)[2], 240,
                 "a.jpg's clip made again with its map")
        drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
        wait_for(lambda: (outbox / "b.mp4").is_file() and not report.exists(), 240,
                 "b.jpg made and its failure report removed")
    finally:
        assert stop(daemon) == 0
    assert (outbox / "a.mp4").read_bytes() != first
    log = daemon_log(tmp_path)
    assert "a.jpg: depth from file" in log, log
    assert sorted(p.name for p in inbox.iterdir()) == ["a.depth.png", "a.jpg", "b.jpg",
                                                       "failed"]
    assert not list((inbox / "failed").iterdir())


def test_a_daemon_killed_while_it_remakes_an_edited_photo_makes_it_again(tmp_path):
    """Killed while an edited photo's clip was made again, the daemon's restart found the
    job running and a clip of its name there (the earlier make's) and recorded it as done:
    the edit never got its clip. A clip older than its job is now not taken for it."""
    from .test_watch import held_encoders

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    outbox.mkdir()
    preset = preset_file(tmp_path, 4.0, fps=25.0)
    daemon = start_daemon(inbox, outbox, preset, "--keep-sources")
    try:
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
        wait_for(lambda: finished_jobs(outbox) == 1, 240, "a.jpg's first clip")
        drop(inbox, "a.jpg", photo_bytes(tmp_path, 2))  # edited
        encoders = held_encoders(outbox, "a")
    finally:
        daemon.send_signal(signal.SIGKILL)
        daemon.wait(timeout=30)
    for pid in encoders:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    log = tmp_path / "restarted.log"
    restarted = start_daemon(inbox, outbox, preset, "--keep-sources", log_path=log)
    try:
        wait_for(lambda: log.exists() and ("done a.jpg" in log.read_text()
                                           or "recovered a.jpg" in log.read_text()),
                 240, "the edited photo's clip")
    finally:
        assert stop(restarted) == 0
    assert "recovered a.jpg" not in log.read_text(), log.read_text()
    reference = tmp_path / "reference"
    reference.mkdir()
    (reference / "a.jpg").write_bytes(photo_bytes(tmp_path, 2))
    subprocess.run([*CLI, str(reference), "-o", str(reference / "out"), "--preset", str(preset),
                    "--depth", "ramp", "--planner", "center", "--quiet"], check=True)
    assert (outbox / "a.mp4").read_bytes() == (reference / "out" / "a.mp4").read_bytes()


def test_an_idle_worker_killed_is_replaced_when_the_next_photo_comes(tmp_path):
    """A worker killed while idle (the OOM killer, an admin): the next photo was offered to
    the broken pool five times a second for ever ("start b.jpg", "worker pool broken;
    retrying"), and no clip was made again."""
    inbox, outbox, preset = folders(tmp_path)
    drop(inbox, "a.jpg", photo_bytes(tmp_path, 1))
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: finished_jobs(outbox) == 1, 300, "the first clip")
        wait_for(lambda: worker_pids(daemon), 60, "an idle worker")
        for pid in worker_pids(daemon):
            os.kill(pid, signal.SIGKILL)
        time.sleep(1.0)
        drop(inbox, "b.jpg", photo_bytes(tmp_path, 2))
        wait_for(lambda: finished_jobs(outbox) == 2, 300, "the clip after the death")
        assert daemon.poll() is None
    finally:
        assert stop(daemon) == 0
    assert clips_in(outbox) == ["a.mp4", "b.mp4"]
    log = daemon_log(tmp_path)
    assert "died while idle" in log and log.count("start b.jpg") <= 2, log


def test_room_made_while_the_daemon_paused_counts_towards_the_room_it_waits_for(tmp_path):
    """A clip found the disk full (0 KB free) while the daemon paused on its journal; the user
    freed space then, as the log invited. The daemon read the result after the pause and
    waited for 1 MB more than the room already made: stuck, with megabytes free."""
    from kbbatch.images import free_bytes
    from kbbatch.pipeline import ClipOptions, ClipResult
    from kbbatch.presets import load_preset
    from kbbatch.watch import SPACE_TO_RESUME_BYTES, JobRunner, WatchSettings

    inbox, outbox = tmp_path / "in", tmp_path / "out"
    inbox.mkdir()
    outbox.mkdir()
    journal = Journal(outbox)
    runner = JobRunner(WatchSettings(inbox, outbox, load_preset("preview"), ClipOptions()),
                       journal, False, tmp_path / "reports", lambda path, renamed: None)
    result = ClipResult(str(inbox / "a.jpg"), None, "queued", 0.0)
    free_now = free_bytes(outbox)
    assert free_now is not None and free_now > 2 * SPACE_TO_RESUME_BYTES
    full_then = free_now - 2 * SPACE_TO_RESUME_BYTES  # 2 MB were made since
    result.found_disk_full(outbox, "No space left on device")
    assert result.status == "no_space" and result.full_folder == str(outbox)
    assert result.error.startswith(f"{outbox}: its disk is full (")
    assert result.free_bytes_when_full is not None
    result.free_bytes_when_full = full_then
    runner.wait_for_space(result)
    assert runner.has_space(), "2 MB more than when the clip failed are free"
    result.free_bytes_when_full = free_now  # no room made since: it waits
    runner.wait_for_space(result)
    assert not runner.has_space()
    journal.close()


def test_a_photo_moved_to_a_full_disk_leaves_no_truncated_copy_under_its_name(
        tmp_path, tiny_mount):  # noqa: F811
    """done/ on another disk (a link to it) that cannot take the photo: the move said so and
    kept the photo in the inbox, but left a truncated done/x.jpg, which the next start
    took for a photo of that name (the real one went to x.1.jpg beside it)."""
    from kbbatch.watch import DONE_FOLDER, move_photo

    inbox = tmp_path / "in"
    inbox.mkdir()
    photo = inbox / "x.jpg"
    photo.write_bytes(os.urandom(12 << 20))  # more than the 8 MB disk holds
    (inbox / DONE_FOLDER).symlink_to(tiny_mount)
    with pytest.raises(OSError) as raised:
        move_photo(photo, inbox / DONE_FOLDER / "x.jpg")
    assert raised.value.errno == 28  # ENOSPC
    assert list(tiny_mount.iterdir()) == [], "no copy, whole or partial"
    assert photo.stat().st_size == 12 << 20
    small = inbox / "small.jpg"
    small.write_bytes(b"a small photo")
    move_photo(small, inbox / DONE_FOLDER / "small.jpg")
    assert (tiny_mount / "small.jpg").read_bytes() == b"a small photo"
    assert not small.exists() and [p.name for p in tiny_mount.iterdir()] == ["small.jpg"]


def test_a_copy_to_done_cut_by_a_kill_is_removed_at_the_next_start(tmp_path):
    inbox, outbox, preset = folders(tmp_path)
    (inbox / "done").mkdir()
    partial = inbox / "done" / ".x.k3j9x2qa.part.jpg"  # atomic_output's name for done/x.jpg
    partial.write_bytes(b"half a photo")
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "watching" in daemon_log(tmp_path), 120, "the daemon")
    finally:
        assert stop(daemon) == 0
    assert not partial.exists()
    assert "removed partial copy done/.x.k3j9x2qa.part.jpg" in daemon_log(tmp_path)


@pytest.mark.parametrize("kind", ["named pipe", "link to /dev/zero"])
def test_status_passes_over_an_inbox_note_that_is_no_file_of_ours(tmp_path, kind):
    """Under the inbox note's name, a named pipe hung `kbbatch status` (until killed), and a
    link to /dev/zero filled the memory (6.9 GB in 20 s)."""
    out = tmp_path / "out"
    out.mkdir()
    Journal(out).close()
    note = out / ".kbbatch-inbox.json"
    if kind == "named pipe":
        os.mkfifo(note)
    else:
        note.symlink_to("/dev/zero")
    run = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("queued 0, running 0, done 0, failed 0"), run.stdout


def test_a_link_whose_photo_appears_later_is_taken_and_one_made_again_is_said_again(tmp_path):
    """Watched by inotify, a link in the inbox whose target was written later was never taken
    (nothing in the inbox changes then) until a restart; and a link removed and made again,
    broken, was not said again."""
    inbox, outbox, preset = folders(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (inbox / "later.jpg").symlink_to(elsewhere / "later.jpg")
    daemon = start_daemon(inbox, outbox, preset)
    try:
        wait_for(lambda: "later.jpg: broken symbolic link" in daemon_log(tmp_path), 120,
                 "the first warning")
        (inbox / "again.jpg").symlink_to(elsewhere / "nowhere.jpg")
        wait_for(lambda: "again.jpg: broken symbolic link" in daemon_log(tmp_path), 60,
                 "the warning of the second link")
        (inbox / "again.jpg").unlink()
        time.sleep(3.0)  # longer than a recheck of the entries said
        (inbox / "again.jpg").symlink_to(elsewhere / "still-nowhere.jpg")
        Image.fromarray(textured_image(180, 320, seed=3)).save(elsewhere / "later.jpg")
        wait_for(lambda: clips_in(outbox) == ["later.mp4"], 120, "the linked photo's clip")
        wait_for(lambda: daemon_log(tmp_path).count("again.jpg: broken symbolic link") == 2,
                 60, "the link made again, said again")
    finally:
        assert stop(daemon) == 0
    assert "ERROR" not in daemon_log(tmp_path)
