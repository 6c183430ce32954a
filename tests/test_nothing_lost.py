"""The one-shot batch against a hostile user (issue 14): same names from two camera cards,
full disks, kills, tight crops, unreadable files, empty folders, logs. Nothing is lost, nothing
is overwritten, and every case says what happened."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import pytest
from PIL import Image

from kbbatch import batch
from kbbatch.batch import default_jobs, plan_folder, run_folder
from kbbatch.depth import DepthOptions
from kbbatch.images import (
    LONE_MAP_REASON,
    NAME_END_REASON,
    OLD_PLAN_SHEET_REASON,
    UNREAD_FORMAT_REASON,
    ImageReadError,
    read_image,
    scan_folder,
)
from kbbatch.journal import JOURNAL_NAME, FolderBusyError, FolderLock, Journal
from kbbatch.pipeline import ClipOptions, make_clip
from kbbatch.presets import load_preset, with_overrides

from .conftest import textured_image
from .test_watch import wait_for

FAST = ClipOptions(planner="center", depth=DepthOptions(backend="ramp"), threads=2)
CLI = [sys.executable, "-m", "kbbatch"]
FAST_CLI = ["--depth", "ramp", "--planner", "center", "--preset", "preview", "--duration",
            "0.6", "--fps", "10"]


def visible_clips(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("*.mp4") if not p.name.startswith("."))


def photo(path: Path, seed: int, height: int = 180, width: int = 320) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(textured_image(height, width, seed=seed)).save(path)
    return path


@pytest.fixture
def tiny_mount(tmp_path):
    """An 8 MB tmpfs (root only; skipped with the reason where mounting is not allowed)."""
    mount = tmp_path / "small-disk"
    mount.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mount)],
                            capture_output=True, text=True)
    if result.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {result.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(disk: Path, leave_bytes: int) -> Path:
    """Fill a disk until at most leave_bytes are free."""
    filler = disk / "filler"
    with filler.open("wb") as handle:
        try:
            while shutil.disk_usage(disk).free > leave_bytes:
                handle.write(b"\0" * min(65536, shutil.disk_usage(disk).free - leave_bytes
                                         or 4096))
                handle.flush()
        except OSError:
            pass
    return filler


# --- 1: same names --------------------------------------------------------------------------
def test_a_second_card_with_the_same_names_never_replaces_a_clip(tmp_path, quick_preset):
    photo(tmp_path / "card1" / "IMG_0001.jpg", seed=1)
    photo(tmp_path / "card2" / "IMG_0001.jpg", seed=2)
    out = tmp_path / "clips"
    out.mkdir()
    (out / "IMG_0002.mp4").write_bytes(b"someone's own file")
    photo(tmp_path / "card2" / "IMG_0002.jpg", seed=3)
    first = run_folder(tmp_path / "card1", out, quick_preset, FAST, False)
    assert [r.status for r in first.results] == ["done"]
    first_clip = (out / "IMG_0001.mp4").read_bytes()
    second = run_folder(tmp_path / "card2", out, quick_preset, FAST, False)
    assert [r.status for r in second.results] == ["done", "done"], second.to_json()
    assert (out / "IMG_0001.mp4").read_bytes() == first_clip, "card 1's clip was replaced"
    assert (out / "IMG_0002.mp4").read_bytes() == b"someone's own file"
    clips = visible_clips(out)
    assert len(clips) == 4, clips
    renamed = [Path(r.output).name for r in second.results]
    assert all(name.startswith(("IMG_0001.", "IMG_0002.")) and len(name.split(".")) == 3
               for name in renamed), renamed
    assert all(r.note and "named by its content" in r.note for r in second.results)
    report = json.loads((out / "kbbatch-report.json").read_text())
    assert all("named by its content" in c["note"] for c in report["clips"])
    # Re-runs of either card: up to date, nothing re-rendered or renamed.
    for card in ("card1", "card2"):
        again = run_folder(tmp_path / card, out, quick_preset, FAST, False)
        assert {r.status for r in again.results} == {"skipped"}
    assert visible_clips(out) == clips


def test_saved_depth_never_replaces_a_file_kbbatch_did_not_write(tmp_path, quick_preset):
    """A camera card's folder used as the output of another card: its own IMG_1.disparity.png
    (made by the user) was silently replaced by the other photo's map. A new clip is named so
    that its maps fit beside it."""
    from dataclasses import replace

    out = tmp_path / "cardA"
    photo(out / "IMG_1.jpg", seed=1)
    (out / "IMG_1.disparity.png").write_bytes(b"the user's own map")
    photo(tmp_path / "cardB" / "IMG_1.jpg", seed=2)
    with_maps = replace(FAST, save_depth=True)
    [result] = run_folder(tmp_path / "cardB", out, quick_preset, with_maps, False).results
    assert result.status == "done" and "named by its content" in result.note
    assert (out / "IMG_1.disparity.png").read_bytes() == b"the user's own map"
    clip = Path(result.output)
    assert clip.name != "IMG_1.mp4"
    assert (out / (clip.stem + ".disparity.png")).is_file()
    assert (out / (clip.stem + ".depth-preview.png")).is_file()
    # Its own maps it replaces, under the same name.
    again = run_folder(tmp_path / "cardB", out, quick_preset, with_maps, False, force=True)
    assert [r.output for r in again.results] == [str(clip)]
    assert (out / "IMG_1.disparity.png").read_bytes() == b"the user's own map"


def test_a_made_clip_keeps_its_name_when_its_depth_maps_name_is_the_users(tmp_path,
                                                                          quick_preset):
    """A clip made without --save-depth beside the user's IMG_1.disparity.png, then again with
    it: the clip moved to a content name and the first IMG_1.mp4 was left beside it, a stale
    copy of the same photo. It keeps its name; the map the user's file holds the name of is not
    written, and the run says so."""
    from dataclasses import replace

    out = tmp_path / "cardA"
    photo(out / "IMG_1.jpg", seed=1)
    (out / "IMG_1.disparity.png").write_bytes(b"the user's own map")
    photo(tmp_path / "cardB" / "IMG_1.jpg", seed=2)
    first = run_folder(tmp_path / "cardB", out, quick_preset, FAST, False)
    assert [Path(r.output).name for r in first.results] == ["IMG_1.mp4"]
    with_maps = replace(FAST, save_depth=True)
    [result] = run_folder(tmp_path / "cardB", out, quick_preset, with_maps, False).results
    assert result.status == "done" and Path(result.output).name == "IMG_1.mp4"
    assert visible_clips(out) == ["IMG_1.mp4"], "a second clip of the photo was left"
    assert (out / "IMG_1.disparity.png").read_bytes() == b"the user's own map"
    assert "IMG_1.disparity.png not written" in result.note
    assert (out / "IMG_1.depth-preview.png").is_file()  # its other name was free


def test_a_report_that_cannot_be_written_fails_the_run(tmp_path):
    """The clips were made, the report could not be (its name taken, a disk full after the
    last clip): the run ended 0 with a note, and a cron job reading the report read an old
    one."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    for name in ("kbbatch-report.json", "kbbatch-run-report.json"):  # both names taken
        (out / name).mkdir(parents=True)
    run = subprocess.run([*CLI, str(folder), "-o", str(out), "--quiet", *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stderr
    assert "kbbatch-run-report.json: files of another's (not this folder's run reports, or " \
        "another user's in a sticky folder); kept, so no report was written" in run.stderr, \
        run.stderr
    assert visible_clips(out) == ["a.mp4"]


def test_a_file_of_the_users_under_the_reports_name_is_kept(tmp_path):
    """A file kbbatch did not write is never replaced: the user's own kbbatch-report.json in
    the output folder was overwritten by the run report without a word; so was a JSON file
    beginning as a report does, and a report copied in from another folder."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    out.mkdir()
    theirs = [json.dumps({"folder": "holiday 2025", "output_folder": "x", "clips": [],
                          "started_at": "2025"}, indent=2),  # begins as a report does
              '{"my": "own notes"}']
    for content in theirs:
        (out / "kbbatch-report.json").write_text(content)
        run = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        assert (out / "kbbatch-report.json").read_text() == content
        assert "kbbatch-report.json: not this folder's run report (a file of yours, or a " \
            f"report copied from another folder); kept, this run's report is " \
            f"{out / 'kbbatch-run-report.json'}" in run.stderr, run.stderr
        report = json.loads((out / "kbbatch-run-report.json").read_text())
        [clip] = report["clips"]
    assert clip["status"] == "skipped" and clip["plan"], "the first run's report was read"
    # removed, the next run reads its details under the other name, and leaves one report
    (out / "kbbatch-report.json").unlink()
    run = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "not this folder's" not in run.stderr, run.stderr
    [clip] = json.loads((out / "kbbatch-report.json").read_text())["clips"]
    assert clip["status"] == "skipped" and clip["plan"] and clip["preset"], clip
    assert not (out / "kbbatch-run-report.json").exists()
    # a report copied from another output folder is not this one's
    other = tmp_path / "other"
    other.mkdir()
    copied = (out / "kbbatch-report.json").read_text()
    (other / "kbbatch-report.json").write_text(copied)
    run = subprocess.run([*CLI, str(folder), "-o", str(other), *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert (other / "kbbatch-report.json").read_text() == copied
    assert (other / "kbbatch-run-report.json").is_file()
    # ... nor one of a folder that is not here (another machine's, a disk not mounted)
    third = tmp_path / "third"
    third.mkdir()
    elsewhere = json.dumps(json.loads(copied) | {"output_folder": "/mnt/nas/clips"})
    for name in ("kbbatch-report.json", "kbbatch-run-report.json"):
        (third / name).write_text(elsewhere)
    run = subprocess.run([*CLI, str(folder), "-o", str(third), *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 1 and "no report was written" in run.stderr, run.stderr
    for name in ("kbbatch-report.json", "kbbatch-run-report.json"):
        assert (third / name).read_text() == elsewhere


def test_an_output_folder_moved_or_renamed_keeps_its_report(tmp_path):
    """Its report names the folder it was written in: taken for another folder's once the
    folder was renamed, it was kept as a user's file, a second report was written beside
    it, and the clips' plans and presets were dropped from the new one."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    run = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    moved, renamed = tmp_path / "elsewhere" / "moved", tmp_path / "elsewhere" / "renamed"
    moved.parent.mkdir()
    out.rename(moved)
    for here in (moved, renamed):
        if here == renamed:
            moved.rename(renamed)
        run = subprocess.run([*CLI, str(folder), "-o", str(here), *FAST_CLI],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0 and "not this folder's" not in run.stderr, run.stderr
        assert not (here / "kbbatch-run-report.json").exists()
        report = json.loads((here / "kbbatch-report.json").read_text())
        [clip] = report["clips"]
        assert report["output_folder"] == str(here)
        assert clip["status"] == "skipped" and clip["plan"] and clip["preset"], clip


def test_a_photo_edited_after_its_folder_moved_replaces_its_own_clip(tmp_path):
    """The moved photos were found up to date by their bytes, but their records stayed under
    the old paths: an edit then made a second clip under a content name beside the stale
    one, and `status` counted three clips made for two photos."""
    from kbbatch.journal import Journal

    folder, out = tmp_path / "photos", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    photo(folder / "b.jpg", seed=2)
    for step in ("first", "moved", "edited"):
        if step == "moved":
            folder = folder.rename(tmp_path / "moved")
        if step == "edited":
            photo(folder / "a.jpg", seed=3)
        run = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        if step == "moved":
            assert "2 already up to date" in run.stdout + run.stderr
    assert "that clip is replaced" in run.stderr, run.stderr
    assert sorted(path.name for path in out.glob("*.mp4")) == ["a.mp4", "b.mp4"]
    journal = Journal(out, read_only=True)
    try:
        assert journal.counts()["done"] == 2
        assert sorted(Path(job.source).parent.name for job in journal.jobs()) == ["moved"] * 2
    finally:
        journal.close()


def camera_photo(path: Path, seed: int, taken: str) -> Path:
    """A photo as a camera writes it: with the moment it was taken (EXIF DateTimeOriginal)."""
    exif = Image.Exif()
    exif[0x8769] = {0x9003: taken}
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(textured_image(180, 320, seed=seed)).save(path, exif=exif)
    return path


def test_a_new_card_in_an_ingest_folder_made_again_does_not_replace_the_first_cards_clip(
        tmp_path):
    """`mv ingest day1; mkdir ingest` and the next card's IMG_0001.jpg copied in: taken for an
    edit of day 1's photo, it replaced that clip, which a timeline pointed at. An edit in
    place (the same folder), or in a folder restored as a new directory (the moment the photo
    was taken kept), still replaces its own clip."""
    ingest, out = tmp_path / "ingest", tmp_path / "clips"

    def run() -> subprocess.CompletedProcess:
        done = subprocess.run([*CLI, str(ingest), "-o", str(out), *FAST_CLI],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        return done

    camera_photo(ingest / "IMG_0001.jpg", 1, "2026:05:01 10:00:00")
    run()
    first = (out / "IMG_0001.mp4").read_bytes()
    ingest.rename(tmp_path / "day1")
    camera_photo(ingest / "IMG_0001.jpg", 2, "2026:05:02 09:00:00")
    second = run()
    assert (out / "IMG_0001.mp4").read_bytes() == first
    [new] = [path for path in out.glob("IMG_0001.*.mp4")]
    assert "is another photo's" in second.stderr and new.name in second.stderr, second.stderr
    # day 1's folder back at the path is up to date under its own name
    ingest.rename(tmp_path / "day2")
    (tmp_path / "day1").rename(ingest)
    assert "1 already up to date" in run().stdout
    # restored from a copy: another directory, day 1's photo
    ingest.rename(tmp_path / "copy")
    shutil.copytree(tmp_path / "copy", ingest)
    assert {path.name for path in out.glob("*.mp4")} == {"IMG_0001.mp4", new.name}
    # an edit (the moment kept) replaces its own clip, in the restored folder and in place
    for seed in (3, 4):
        camera_photo(ingest / "IMG_0001.jpg", seed, "2026:05:01 10:00:00")
        edited = run()
        assert "that clip is replaced" in edited.stderr, edited.stderr
        assert {path.name for path in out.glob("*.mp4")} == {"IMG_0001.mp4", new.name}
    assert (out / "IMG_0001.mp4").read_bytes() != first


def test_an_earlier_versions_record_or_an_unfinished_one_is_a_first_cards_too(tmp_path):
    """Records of an earlier version (no folder, no moment), found up to date, were never
    told where their photo is now, and a record whose re-make was interrupted was not
    looked at: the next card at the path replaced their clips."""
    import sqlite3

    ingest, out = tmp_path / "ingest", tmp_path / "clips"
    for state in ("done", "queued"):
        shutil.rmtree(ingest, ignore_errors=True)
        shutil.rmtree(out, ignore_errors=True)
        camera_photo(ingest / "IMG_0001.jpg", 1, "2026:05:01 10:00:00")
        done = subprocess.run([*CLI, str(ingest), "-o", str(out), *FAST_CLI],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        journal = sqlite3.connect(out / ".kbbatch-journal.sqlite")
        journal.execute("UPDATE jobs SET folder = NULL, taken = NULL")  # an earlier version's
        journal.commit()
        if state == "done":  # found up to date, it is told where it is
            done = subprocess.run([*CLI, str(ingest), "-o", str(out), *FAST_CLI],
                                  capture_output=True, text=True, timeout=300)
            assert "1 already up to date" in done.stdout, done.stdout + done.stderr
        else:  # its re-make (--force) interrupted
            journal.execute("UPDATE jobs SET folder = ?, taken = '2026:05:01 10:00:00',"
                            " state = 'queued', clip = NULL",
                            (f"{os.stat(ingest).st_dev}:{os.stat(ingest).st_ino}",))
            journal.commit()
        journal.close()
        first = (out / "IMG_0001.mp4").read_bytes()
        ingest.rename(tmp_path / f"day1-{state}")
        camera_photo(ingest / "IMG_0001.jpg", 2, "2026:05:02 09:00:00")
        done = subprocess.run([*CLI, str(ingest), "-o", str(out), *FAST_CLI],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert (out / "IMG_0001.mp4").read_bytes() == first, state
        assert len(list(out.glob("IMG_0001.*.mp4"))) == 1, state


def test_status_says_a_clip_deleted_by_hand(tmp_path):
    """`status` counted it done, from the journal alone, as if it were there."""
    folder, out = tmp_path / "photos", tmp_path / "out"
    source = photo(folder / "a.jpg", seed=1)
    run = subprocess.run([*CLI, str(folder), "-o", str(out), *FAST_CLI],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr

    def status() -> str:
        return subprocess.run([*CLI, "status", str(out)], capture_output=True,
                              text=True).stdout

    assert "MISSING" not in status() and "CHANGED" not in status()
    whole = (out / "a.mp4").read_bytes()
    (out / "a.mp4").write_bytes(whole[:3000])  # cut short: said too (it said nothing)
    assert "CHANGED 1 clip(s) counted done are not as written (cut short, or saved over?): " \
        "a.mp4; the next run" in status()
    (out / "a.mp4").write_bytes(whole)
    assert "CHANGED" not in status()
    (out / "a.mp4").unlink()
    assert f"MISSING 1 clip(s) counted done are not in {out} (deleted?): a.mp4; the next " \
        "run of their photos' folder makes them again" in status()
    source.unlink()  # nothing to make it again from
    assert "MISSING" not in status()


def test_status_counts_the_failures_found_before_a_job_began(tmp_path):
    """A broken link (or a pipe, or a manifest's missing photo) fails the run, exit 1, before
    any job is started for it: `status`, counting the journal alone, said "failed 0"."""
    folder, out = tmp_path / "photos", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    (folder / "b.jpg").write_bytes(b"not a photo")  # fails in its job first
    (tmp_path / "via").symlink_to(folder)

    def run(photos: Path) -> None:
        run = subprocess.run([*CLI, str(photos), "-o", str(out), *FAST_CLI],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 1, run.stderr

    def status() -> list[str]:
        status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
        assert status.returncode == 0 and "Traceback" not in status.stderr, status.stderr
        return status.stdout.splitlines()

    run(folder)
    (folder / "b.jpg").unlink()
    (folder / "b.jpg").symlink_to(tmp_path / "nowhere.jpg")
    run(tmp_path / "via")  # the folder as typed is not the journal's key: one photo, once
    lines = status()
    assert "done 1" in lines[0] and "failed 1" in lines[0], lines
    [failed] = [line for line in lines if line.startswith("FAILED")]
    assert failed.startswith(f"FAILED {folder / 'b.jpg'}: ") and "before its job began" in failed
    (folder / "c.jpg").symlink_to(tmp_path / "nowhere either.jpg")
    run(folder)
    lines = status()
    assert "failed 2" in lines[0], lines
    # mended, and not yet made again: no longer failing
    photo(tmp_path / "nowhere either.jpg", seed=2)
    lines = status()
    assert "failed 1" in lines[0] and "c.jpg" not in "\n".join(lines), lines
    # a report whose clips are not a list (hand-edited): counted from the journal alone
    report = json.loads((out / "kbbatch-report.json").read_text())
    (out / "kbbatch-report.json").write_text(json.dumps(report | {"clips": 1}))
    assert "failed 1" in status()[0]


def test_a_run_whose_final_report_fails_leaves_no_report_saying_it_never_finished(
        tmp_path, quick_preset, monkeypatch):
    """The disk filled between the report written at the start and the final one: the first
    stayed, and `kbbatch status` said the run did not finish. (The final write fails here by
    hand: a disk that fills at that moment and no other cannot be had reliably.)"""
    from kbbatch.batch import RunReport, last_run_lines

    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    writes = []
    real_write = RunReport.write

    def write_then_fail(report, output_folder):
        writes.append(report.finished_at)
        if report.finished_at is None:
            return real_write(report, output_folder)
        return f"{output_folder / 'kbbatch-report.json'}: report could not be written (full)"

    monkeypatch.setattr(RunReport, "write", write_then_fail)
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert writes[0] is None and writes[1] is not None and report.unwritten
    assert not (out / "kbbatch-report.json").exists()
    assert last_run_lines(out) == []


def test_a_stopped_run_whose_final_report_fails_keeps_the_one_saying_it_did_not_finish(
        tmp_path, quick_preset, monkeypatch):
    """A run stopped by a full disk, whose final report the disk could not take either: the
    report written at the start was removed too, and `kbbatch status` had no word of the
    photos the run never started. (The stop here is --fail-fast's, and the final write fails
    by hand, as above.)"""
    from kbbatch.batch import RunReport, last_run_lines

    folder, out = tmp_path / "in", tmp_path / "out"
    (folder / "a.jpg").parent.mkdir(parents=True)
    (folder / "a.jpg").write_bytes(b"not a photo")
    photo(folder / "b.jpg", seed=1)
    real_write = RunReport.write

    def write_then_fail(report, output_folder):
        if report.finished_at is None:
            return real_write(report, output_folder)
        return f"{output_folder / 'kbbatch-report.json'}: report could not be written (full)"

    monkeypatch.setattr(RunReport, "write", write_then_fail)
    report = run_folder(folder, out, quick_preset, FAST, False, fail_fast=True)
    assert report.unwritten and report.not_started == [str(folder / "b.jpg")]
    [line] = last_run_lines(out)
    assert "did not finish" in line and "run again to finish" in line, line


def test_a_skipped_clip_keeps_what_the_report_said_of_it(tmp_path, quick_preset):
    """Each re-run's report gave the clips it skipped no crops, depth backend or preset: a tool
    reading the report lost them at the first re-run."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    [made] = run_folder(folder, out, quick_preset, FAST, False).results
    photo(folder / "b.jpg", seed=2)
    run_folder(folder, out, quick_preset, FAST, False)
    clips = {Path(c["source"]).name: c
             for c in json.loads((out / "kbbatch-report.json").read_text())["clips"]}
    assert clips["a.jpg"]["status"] == "skipped" and clips["b.jpg"]["status"] == "done"
    assert clips["a.jpg"]["plan"] == json.loads(json.dumps(made.plan))
    assert (clips["a.jpg"]["depth_backend"], clips["a.jpg"]["preset"]) == (
        made.depth_backend, made.preset)
    (out / "kbbatch-report.json").unlink()  # nothing to carry: skipped, said as before
    [a_again] = [r for r in run_folder(folder, out, quick_preset, FAST, False).results
                 if Path(r.source).name == "a.jpg"]
    assert a_again.status == "skipped" and a_again.plan is None


def test_a_plain_run_after_save_depth_keeps_the_clips_and_their_maps(tmp_path, quick_preset):
    """A user saved maps for compositing, then ran again without --save-depth to pick up one
    new photo: every clip was made again and every map removed, without a word. The clips are
    up to date and the maps stay; a clip made again for another reason says that its maps,
    now stale, went."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    with_maps = replace(FAST, save_depth=True)
    assert [r.status for r in run_folder(folder, out, quick_preset, with_maps, False).results
            ] == ["done"]
    maps = sorted(p.name for p in out.glob("a.*.png"))
    assert maps == ["a.depth-preview.png", "a.disparity.png"]
    photo(folder / "b.jpg", seed=2)
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert {Path(r.source).name: r.status for r in report.results} == {"a.jpg": "skipped",
                                                                       "b.jpg": "done"}
    assert sorted(p.name for p in out.glob("a.*.png")) == maps
    photo(folder / "a.jpg", seed=3)  # edited: its maps would show the old photo's depth
    [edited] = [r for r in run_folder(folder, out, quick_preset, FAST, False).results
                if r.status == "done"]
    assert not list(out.glob("a.*.png"))
    assert "a.disparity.png and a.depth-preview.png removed" in edited.note
    again = run_folder(folder, out, quick_preset, with_maps, False)  # asked for again: made
    assert [r.status for r in again.results if Path(r.source).name == "a.jpg"] == ["done"]
    assert sorted(p.name for p in out.glob("a.*.png")) == maps
    (out / "a.disparity.png").unlink()  # deleted: the clip, up to date, was skipped for good
    again = run_folder(folder, out, quick_preset, with_maps, False)
    assert [r.status for r in again.results if Path(r.source).name == "a.jpg"] == ["done"]
    assert sorted(p.name for p in out.glob("a.*.png")) == maps


def test_ray_driver_never_writes_a_workers_map_over_the_users_file(tmp_path):
    """A worker makes its files in a folder of its own, so the driver writing them beside the
    clip is where a user's file of a map's name would be replaced."""
    from kbbatch.pipeline import ClipJob, ClipResult
    from kbbatch.ray_executor import WorkerOutcome, write_outcome

    out = tmp_path / "out"
    out.mkdir()
    (out / "IMG_1.disparity.png").write_bytes(b"the user's own map")
    job = ClipJob(photo(tmp_path / "in" / "IMG_1.jpg", seed=1), out / "IMG_1.mp4", None)
    files = {"IMG_1.mp4": b"clip", "IMG_1.disparity.png": b"map",
             "IMG_1.depth-preview.png": b"picture"}
    outcome = WorkerOutcome(ClipResult(str(job.source), "x", "done", 1.0), files, "node", 1)
    result = write_outcome(job, outcome)
    assert result.status == "done" and (out / "IMG_1.mp4").read_bytes() == b"clip"
    assert (out / "IMG_1.disparity.png").read_bytes() == b"the user's own map"
    assert (out / "IMG_1.depth-preview.png").read_bytes() == b"picture"
    assert "IMG_1.disparity.png not written" in result.note


def test_a_manifest_entrys_preset_file_is_found_beside_the_manifest_and_is_an_input(
        tmp_path, quick_preset, monkeypatch):
    """Found from the current folder, the same manifest worked or failed by where it was run
    (a daemon under systemd runs from /); and an edit to that file left the clip stale."""
    import cv2

    from kbbatch.manifest import load_manifest

    photo(tmp_path / "in" / "a.jpg", seed=1)
    (tmp_path / "m").mkdir()
    look = tmp_path / "m" / "look.toml"
    look.write_text('base = "preview"\nwidth_px = 320\nheight_px = 180\nfps = 10\n'
                    'duration_s = 0.5\n')
    manifest_path = tmp_path / "m" / "manifest.json"
    manifest_path.write_text('{"version": 1, "images": {"a.jpg": {"preset": "look.toml"}}}')
    monkeypatch.chdir("/")

    def render() -> list[str]:
        report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False,
                            manifest=load_manifest(manifest_path))
        made = [r.preset for r in report.results if r.status == "done"]
        assert made in ([], ["look"]), made  # the report says which preset made it
        return [r.status for r in report.results]

    assert render() == ["done"]
    assert render() == ["skipped"]
    look.write_text(look.read_text().replace("width_px = 320\nheight_px = 180",
                                             "width_px = 384\nheight_px = 216"))
    assert render() == ["done"]
    capture = cv2.VideoCapture(str(tmp_path / "out" / "a.mp4"))
    assert capture.get(cv2.CAP_PROP_FRAME_WIDTH) == 384
    capture.release()


def test_a_preset_renamed_or_reworded_makes_no_clip_again(tmp_path, quick_preset):
    """A preset's name and description label it: renaming its file (and the manifest entry
    naming it) or rewording its description made every clip of the folder again."""
    from kbbatch.manifest import load_manifest

    photo(tmp_path / "in" / "a.jpg", seed=1)
    photo(tmp_path / "in" / "b.jpg", seed=2)
    settings = 'base = "preview"\nwidth_px = 320\nheight_px = 180\nfps = 10\nduration_s = 0.5\n'
    mine = tmp_path / "mine.toml"
    mine.write_text(f'description = "first words"\n{settings}')
    (tmp_path / "look.toml").write_text(settings)
    manifest_path = tmp_path / "manifest.json"

    def render(preset_file: Path, entry_preset: str) -> list[str]:
        manifest_path.write_text(json.dumps(
            {"version": 1, "images": {"b.jpg": {"preset": entry_preset}}}))
        report = run_folder(tmp_path / "in", tmp_path / "out", load_preset(str(preset_file)),
                            FAST, False, manifest=load_manifest(manifest_path))
        return [r.status for r in report.results]

    assert render(mine, "look.toml") == ["done", "done"]
    renamed = mine.rename(tmp_path / "ours.toml")
    renamed.write_text(f'description = "better words"\n{settings}')
    (tmp_path / "look.toml").rename(tmp_path / "grade.toml")
    assert render(renamed, "grade.toml") == ["skipped", "skipped"]
    # A setting is not a label: the clips are made again.
    renamed.write_text(f'description = "better words"\n{settings}crf = 30\n')
    assert render(renamed, "grade.toml") == ["done", "skipped"]
    # An entry naming a preset file that is gone fails: it is not taken for up to date.
    (tmp_path / "grade.toml").unlink()
    assert render(renamed, "grade.toml") == ["skipped", "failed"]


def test_an_edited_photo_replaces_its_own_clip(tmp_path, quick_preset):
    path = photo(tmp_path / "in" / "a.jpg", seed=1)
    run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    photo(path, seed=7)
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["done"]
    assert visible_clips(tmp_path / "out") == ["a.mp4"]
    # said, since it may be another photo under the same name (one import folder for every
    # card): the clip it replaces is named
    [result] = report.results
    assert result.note and "a.jpg changed since a.mp4 was made from it" in result.note
    again = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False, force=True)
    assert [(r.status, r.note) for r in again.results] == [("done", None)]  # same bytes



def test_a_clip_of_a_deleted_photo_is_kept_from_another_photo_saved_later_under_its_name(
        tmp_path, quick_preset):
    """One import folder for every card: IMG_0001.jpg made, deleted, a run, then the next
    card's IMG_0001.jpg copied in. Taken for an edit of the deleted photo, it replaced its
    clip, though the run between had seen that photo gone."""
    folder, out = tmp_path / "in", tmp_path / "out"
    path = photo(folder / "IMG_0001.jpg", seed=1)
    photo(folder / "IMG_0002.jpg", seed=3)
    run_folder(folder, out, quick_preset, FAST, False)
    first_clip = (out / "IMG_0001.mp4").read_bytes()
    path.unlink()
    run_folder(folder, out, quick_preset, FAST, False)
    photo(path, seed=2)  # the next card's photo of that name
    report = run_folder(folder, out, quick_preset, FAST, False)
    [result] = [r for r in report.results if r.status != "skipped"]
    assert result.status == "done" and Path(result.output).name != "IMG_0001.mp4"
    assert "is another photo's" in result.note and "changed since" not in result.note
    assert (out / "IMG_0001.mp4").read_bytes() == first_clip
    assert len(visible_clips(out)) == 3


def test_a_deleted_photo_put_back_is_up_to_date(tmp_path, quick_preset):
    """Its record set aside when a run saw it gone, the photo put back is still known by its
    bytes: not made again, no second clip."""
    folder, out = tmp_path / "in", tmp_path / "out"
    path = photo(folder / "a.jpg", seed=1)
    photo(folder / "b.jpg", seed=2)
    run_folder(folder, out, quick_preset, FAST, False)
    kept = path.read_bytes()
    path.unlink()
    run_folder(folder, out, quick_preset, FAST, False)
    path.write_bytes(kept)
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["skipped", "skipped"]
    assert visible_clips(out) == ["a.mp4", "b.mp4"]


def test_an_edited_photo_named_by_its_content_replaces_its_own_clip(tmp_path, quick_preset):
    """A clip once named by content (its name was another card's) keeps that name when its
    photo is edited: the edit replaces it, no second, stale clip beside it."""
    photo(tmp_path / "card1" / "IMG_0001.jpg", seed=1)
    path = photo(tmp_path / "card2" / "IMG_0001.jpg", seed=2)
    out = tmp_path / "clips"
    run_folder(tmp_path / "card1", out, quick_preset, FAST, False)
    first = run_folder(tmp_path / "card2", out, quick_preset, FAST, False)
    named = Path(first.results[0].output).name
    assert named != "IMG_0001.mp4"
    before = (out / named).read_bytes()
    photo(path, seed=8)  # edited in place
    edited = run_folder(tmp_path / "card2", out, quick_preset, FAST, False)
    assert [(r.status, Path(r.output).name) for r in edited.results] == [("done", named)]
    assert (out / named).read_bytes() != before
    assert sorted(visible_clips(out)) == sorted(["IMG_0001.mp4", named])


def test_a_content_name_kept_through_an_edit_is_not_taken_by_the_original_again(
        tmp_path, quick_preset):
    """IMG_0001.<digest of P1>.mp4, kept through an edit, holds the edit's clip: the original
    P1 imported again from another folder took that name and replaced the edit's clip."""
    out = tmp_path / "clips"
    out.mkdir()
    (out / "IMG_0001.mp4").write_bytes(b"the user's own file")
    path = photo(tmp_path / "card" / "IMG_0001.jpg", seed=1)
    named = Path(run_folder(tmp_path / "card", out, quick_preset, FAST, False)
                 .results[0].output).name
    photo(path, seed=2)  # edited: its clip keeps the name
    run_folder(tmp_path / "card", out, quick_preset, FAST, False)
    edit = (out / named).read_bytes()
    photo(tmp_path / "reimport" / "IMG_0001.jpg", seed=1)  # the original's very bytes
    again = run_folder(tmp_path / "reimport", out, quick_preset, FAST, False)
    [result] = again.results
    assert result.status == "done" and Path(result.output).name not in (named, "IMG_0001.mp4")
    assert (out / named).read_bytes() == edit, "the edit's clip was replaced"
    assert (out / "IMG_0001.mp4").read_bytes() == b"the user's own file"

def test_a_photo_keeps_its_clip_name_when_a_same_stem_photo_comes_and_goes(tmp_path,
                                                                          quick_preset):
    """a.png put beside a.jpg (and taken away again) neither renames a.jpg's clip nor makes
    it again: a clip an editing project refers to stays where it is."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    run_folder(folder, out, quick_preset, FAST, False)
    clip = (out / "a.mp4").read_bytes()
    photo(folder / "a.png", seed=2)
    added = run_folder(folder, out, quick_preset, FAST, False)
    statuses = {Path(r.source).name: (r.status, Path(r.output).name) for r in added.results}
    assert statuses == {"a.jpg": ("skipped", "a.mp4"), "a.png": ("done", "a.png.mp4")}
    assert not any(r.note for r in added.results), [r.note for r in added.results]
    (folder / "a.png").unlink()
    removed = run_folder(folder, out, quick_preset, FAST, False)
    assert [(r.status, Path(r.output).name) for r in removed.results] == [("skipped", "a.mp4")]
    assert visible_clips(out) == ["a.mp4", "a.png.mp4"]
    assert (out / "a.mp4").read_bytes() == clip


def test_a_queued_photo_deleted_before_the_rerun_leaves_no_job_behind(tmp_path, quick_preset):
    """Killed while a.jpg's clip was remade, then a.jpg taken away: the next run settles its
    job (it stayed queued in `kbbatch status` for ever) keeping its earlier clip its own, so
    a.jpg put back is made again under that name, not a second one beside it with a note that
    a.mp4 was another photo's. A job without a clip is forgotten; another folder's queued job
    (a card not in the reader) is left alone."""
    folder, out = tmp_path / "in", tmp_path / "out"
    gone = photo(folder / "a.jpg", seed=1)
    photo(folder / "b.jpg", seed=2)
    never = photo(folder / "d.jpg", seed=3)
    elsewhere = tmp_path / "card" / "c.jpg"
    run_folder(folder, out, quick_preset, FAST, False)
    (out / "d.mp4").unlink()
    journal = Journal(out)
    try:
        journal.finish(gone, "queued", 0.0, "interrupted")
        journal.finish(never, "queued", 0.0, "interrupted")
        journal.start(elsewhere, "fingerprint", "settings", "c.mp4", "content")
        journal.finish(elsewhere, "queued", 0.0, "interrupted")
    finally:
        journal.close()
    aside = tmp_path / "aside.jpg"
    gone.rename(aside)
    never.unlink()
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert [(Path(r.source).name, r.status) for r in report.results] == [("b.jpg", "skipped")]
    journal = Journal(out)
    try:
        assert journal.counts()["queued"] == 1  # the other folder's
        assert journal.get(gone).state == "done" and journal.get(never) is None
        assert journal.get(elsewhere).state == "queued"
    finally:
        journal.close()
    assert visible_clips(out) == ["a.mp4", "b.mp4"]
    aside.rename(gone)
    back = run_folder(folder, out, quick_preset, FAST, False)
    statuses = {Path(r.source).name: (r.status, Path(r.output).name, r.note)
                for r in back.results}
    assert statuses == {"a.jpg": ("done", "a.mp4", None), "b.jpg": ("skipped", "b.mp4", None)}
    assert visible_clips(out) == ["a.mp4", "b.mp4"]


def test_photos_named_in_255_bytes_get_clips_depth_maps_and_content_names(tmp_path,
                                                                          quick_preset):
    """The names made from a photo's longest valid name (its depth maps', its content name)
    are cut to fit, each marked by a digest of the whole: they failed after the render."""
    name = "N" * 251 + ".jpg"
    for card, seed in (("card1", 1), ("card2", 2)):
        photo(tmp_path / card / name, seed=seed)
    out = tmp_path / "out"
    plain = run_folder(tmp_path / "card1", out, quick_preset, FAST, False)
    assert [(r.status, r.error) for r in plain.results] == [("done", None)]
    saving = replace(FAST, save_depth=True)
    for card in ("card1", "card2"):  # card 2's clip is named by content: a longer name
        report = run_folder(tmp_path / card, out, quick_preset, saving, False, force=True)
        assert [(r.status, r.error) for r in report.results] == [("done", None)], card
    assert len(visible_clips(out)) == 2
    assert len(list(out.glob("*.disparity.png"))) == 2
    assert len(list(out.glob("*.depth-preview.png"))) == 2
    assert all(len(os.fsencode(p.name)) <= 255 for p in out.iterdir())
    # made again without --save-depth, its maps go (found by the same cut names)
    again = run_folder(tmp_path / "card1", out, quick_preset, FAST, False, force=True)
    assert [(r.status, r.error) for r in again.results] == [("done", None)]
    assert len(list(out.glob("*.disparity.png"))) == 1


def test_a_cut_name_keeps_characters_whole_and_long_stems_apart():
    from kbbatch.images import fitted_name

    assert fitted_name("short", ".mp4") == "short.mp4"
    long_a, long_b = "é" * 200 + "a", "é" * 200 + "b"  # 401 bytes each, differing at the end
    cut_a, cut_b = fitted_name(long_a, ".disparity.png"), fitted_name(long_b, ".disparity.png")
    assert cut_a != cut_b
    for cut in (cut_a, cut_b):
        assert len(os.fsencode(cut)) <= 255 and cut.endswith(".disparity.png")
        cut.encode("utf-8")  # no character cut in half
        assert cut.startswith("é" * 100)

# --- 2: full disk ---------------------------------------------------------------------------
@pytest.mark.slow
def test_a_full_disk_stops_the_batch_cleanly_and_a_rerun_finishes(tmp_path, tiny_mount):
    folder = tmp_path / "in"
    for index in range(2):  # a photo after the one the disk stopped
        photo(folder / f"p{index}.jpg", seed=index)
    for leave_kb in (0, 8, 40, 120, 200, 300):
        out = tiny_mount / f"out-{leave_kb}"
        filler = fill(tiny_mount, leave_kb * 1024)
        run = subprocess.run([*CLI, str(folder), "-o", str(out), "--quiet", *FAST_CLI],
                             capture_output=True, text=True, timeout=300)
        assert "Traceback" not in run.stderr, f"{leave_kb} KB free:\n{run.stderr}"
        # the journal's disk full too: the batch stops; each photo after it failed in turn
        assert " 0 failed" in run.stdout or not run.stdout, f"{leave_kb} KB free: {run.stdout}"
        assert run.returncode in (0, 1) and (leave_kb > 0 or run.returncode == 1), (
            f"{leave_kb} KB free: {run.stdout}{run.stderr}")
        if run.returncode == 1:  # what stopped it says why; no photo is failed for it
            assert "full" in run.stderr or "No space" in run.stderr, run.stderr
        filler.unlink()
        if out.is_dir():
            journal = Journal(out)
            try:
                assert not journal.jobs("failed"), f"{leave_kb} KB free: {run.stderr}"
            finally:
                journal.close()
        rerun = subprocess.run([*CLI, str(folder), "-o", str(out), "--quiet", *FAST_CLI],
                               capture_output=True, text=True, timeout=300)
        assert rerun.returncode == 0, rerun.stderr
        assert visible_clips(out) == ["p0.mp4", "p1.mp4"]
        assert not list(out.glob(".*part*"))
        journal = Journal(out)
        try:
            assert journal.counts()["done"] == 2 and not journal.jobs("running")
        finally:
            journal.close()
        shutil.rmtree(out)


def test_status_reads_the_journal_of_a_full_disk(tmp_path, tiny_mount, quick_preset):
    """`kbbatch status` only reads: on a full disk it said the journal could not be written."""
    photo(tmp_path / "in" / "a.jpg", seed=1)
    out = tiny_mount / "out"
    run_folder(tmp_path / "in", out, quick_preset, FAST, False)
    fill(tiny_mount, 0)
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert status.returncode == 0, status.stderr
    assert "done 1" in status.stdout

@pytest.mark.slow
def test_a_clip_its_disk_cannot_take_stops_the_batch_and_fails_no_photo(tmp_path, tiny_mount):
    """Room for the journal, not for a lossless clip: before, every photo failed in turn."""
    folder = tmp_path / "in"
    for index in range(3):
        photo(folder / f"p{index}.jpg", seed=index, height=360, width=640)
    preset = tmp_path / "lossless.toml"
    preset.write_text((Path(batch.__file__).parents[1] / "presets" / "preview.toml")
                      .read_text().replace("crf = 28", "crf = 0")
                      .replace("width_px = 640", "width_px = 320")
                      .replace("height_px = 360", "height_px = 180"))
    options = ["--quiet", "--depth", "ramp", "--planner", "center", "--preset", str(preset)]
    probe = subprocess.run([*CLI, str(folder), "-o", str(tmp_path / "probe"), *options],
                           capture_output=True, text=True, timeout=300)
    assert probe.returncode == 0, probe.stderr
    size_bytes = min(p.stat().st_size for p in (tmp_path / "probe").glob("*.mp4"))
    out = tiny_mount / "out"
    command = [*CLI, str(folder), "-o", str(out), *options]
    filler = fill(tiny_mount, size_bytes // 3)
    run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "Traceback" not in run.stderr
    assert "its disk is full" in run.stderr and "p0.jpg" in run.stderr, run.stderr
    assert "run again" in run.stderr and "0 failed" in run.stdout, run.stdout + run.stderr
    assert not list(out.glob(".*part*")) and visible_clips(out) == []
    filler.unlink()
    journal = Journal(out)
    try:
        assert [job.name for job in journal.jobs("queued")] == ["p0.jpg"]  # the rest not started
        assert not journal.jobs("failed")
    finally:
        journal.close()
    rerun = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert visible_clips(out) == ["p0.mp4", "p1.mp4", "p2.mp4"]


@pytest.mark.slow
def test_a_temporary_folder_too_small_for_the_frames_stops_the_batch_without_a_crash(
        tmp_path, tiny_mount):
    """Frames over the memory budget went to a sparse file in TMPDIR: when that disk filled,
    the batch died of SIGBUS, with no report, a partial clip and the photo left running."""
    folder = tmp_path / "in"
    for index in range(2):
        photo(folder / f"p{index}.jpg", seed=index)
    preset = tmp_path / "big.toml"  # 180 forward frames of 1080p: 1.1 GB, over the 1 GiB budget
    preset.write_text('base = "preview"\nwidth_px = 1920\nheight_px = 1080\nfps = 120\n'
                      'duration_s = 1.5\n')
    out = tmp_path / "out"
    run = subprocess.run([*CLI, str(folder), "-o", str(out), "--quiet", "--depth", "ramp",
                          "--planner", "center", "--preset", str(preset)],
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "TMPDIR": str(tiny_mount)})
    assert run.returncode == 1, (run.returncode, run.stderr)
    assert "Traceback" not in run.stderr
    assert f"{tiny_mount}: its disk is full" in run.stderr and "TMPDIR" in run.stderr, run.stderr
    assert json.loads((out / batch.REPORT_NAME).read_text())["stopped_by"] == batch.DISK_FULL
    assert list(tiny_mount.iterdir()) == [] and not list(out.glob(".*part*"))
    journal = Journal(out)
    try:
        assert [job.name for job in journal.jobs("queued")] == ["p0.jpg"]
        assert not journal.jobs("failed") and not journal.jobs("running")
    finally:
        journal.close()


# --- 4: kills -------------------------------------------------------------------------------
def hang_ups_heard() -> None:
    """In a child: SIGHUP as a terminal's process has it, not as this test run's (under nohup,
    as a CI job may be, it is ignored, and the batch keeps it so)."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def start_batch(folder: Path, out: Path, *extra: str) -> subprocess.Popen:
    command = [*CLI, str(folder), "-o", str(out), "--depth", "ramp", "--planner", "center",
               "--preset", "preview", "--quiet", *extra]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=hang_ups_heard)


def encoding(out: Path) -> bool:
    """Whether ffmpeg is writing a clip in out: its temporary file holds data. (Any `.part`
    file is not enough: the run report's is one, written before the run sets up its signal
    handling, and a clip's is made before ffmpeg starts.)"""
    for partial in out.glob(".*.part.mp4"):
        with contextlib.suppress(OSError):
            if partial.stat().st_size > 0:
                return True
    return False


def act_while_encoding(folder: Path, out: Path, duration_s: float, act) -> tuple[int, str]:
    """Start a batch of --duration clips, act(process) once one is being encoded, and give
    the batch's exit status and stderr."""
    process = start_batch(folder, out, "--duration", str(duration_s), "--fps", "25")
    try:
        wait_for(lambda: encoding(out), 180, "a clip being encoded")
        act(process)
        _, stderr = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, stderr


def slow_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "in"
    for index in range(2):
        photo(folder / f"p{index}.jpg", seed=index, height=360, width=640)
    return folder


@pytest.mark.slow
def test_a_photo_deleted_during_the_batch_is_said_not_failed(tmp_path):
    """The report said FAILED ("cannot be read") and the run exited 1, while `kbbatch status`
    counted no failure: a photo its owner deleted is no failure of the batch."""
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    code, stderr = act_while_encoding(folder, out, 2.0,
                                      lambda _: (folder / "p1.jpg").unlink())
    assert code == 0, stderr
    assert "FAILED" not in stderr
    assert f"NOTE {folder / 'p1.jpg'}: removed from its folder during the run" in stderr
    report = json.loads((out / batch.REPORT_NAME).read_text())
    assert [(Path(c["source"]).name, c["status"]) for c in report["clips"]] == [
        ("p0.jpg", "done"), ("p1.jpg", "removed")]
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert "done 1, failed 0" in status.stdout, status.stdout


@pytest.mark.slow
def test_a_photo_folder_renamed_during_the_batch_stops_it(tmp_path):
    """Every photo after the rename was reported removed by its owner, and the run exited 0
    with one clip of the folder's made; the photos are where the folder went."""
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    renamed = tmp_path / "renamed"
    code, stderr = act_while_encoding(folder, out, 2.0, lambda _: folder.rename(renamed))
    assert code == 1, stderr
    assert f"stopped: {folder}: removed or renamed during the run" in stderr, stderr
    assert "removed from its folder" not in stderr
    report = json.loads((out / batch.REPORT_NAME).read_text())
    assert report["stopped_by"] == batch.PHOTOS_GONE
    made = {Path(c["source"]).name: c["status"] for c in report["clips"]}
    assert made["p0.jpg"] == "done"
    assert made.get("p1.jpg") == "interrupted" or str(folder / "p1.jpg") in report["not_started"]
    run = subprocess.run([*CLI, str(renamed), "-o", str(out), "--depth", "ramp", "--planner",
                          "center", "--preset", "preview", "--duration", "2.0", "--fps", "25"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert visible_clips(out) == ["p0.mp4", "p1.mp4"]
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert "done 2, failed 0" in status.stdout and "queued 0" in status.stdout, status.stdout


def test_a_photo_deleted_after_its_job_started_leaves_no_job_or_failure(tmp_path, quick_preset):
    """Deleted between its start in the journal and its read: no failure, no job left."""
    folder, out = tmp_path / "in", tmp_path / "out"
    source = photo(folder / "a.jpg", seed=1)
    out.mkdir()
    journal = Journal(out)
    try:
        job = batch.start_job(journal, source, out, "a.mp4", quick_preset, FAST, None, False)
        source.unlink()
        made = make_clip(source, job.output, quick_preset, FAST, False)
        result = batch.finish_job(journal, job, made)
        assert (result.status, result.error) == ("removed", None)
        assert journal.get(source) is None
    finally:
        journal.close()


@pytest.mark.slow
def test_kill_9_of_a_batch_leaves_nothing_after_the_next_run(tmp_path):
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    process = start_batch(folder, out, "--duration", "20", "--fps", "25")
    try:
        wait_for(lambda: encoding(out), 180, "a clip being encoded")
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=60)
    assert list(out.glob(".*.part.mp4")), "the kill left a partial clip (the case under test)"
    users = [out / ".vacation.part1.rar", out / ".notes.partial.txt", out / ".a.b.part.zip"]
    for path in users:  # hidden files of the user's: the clean-up took them too
        path.write_text("precious")
    # nothing runs there now: the killed run's photo is not shown as running
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert "RUNNING" not in status.stdout and "INTERRUPTED" in status.stdout, status.stdout
    # the report is the killed run's, unfinished (an earlier run's report stayed, undated)
    report = json.loads((out / "kbbatch-report.json").read_text())
    assert report["started_at"] and report["finished_at"] is None
    assert "did not finish" in status.stdout, status.stdout
    rerun = subprocess.run([*CLI, str(folder), "-o", str(out), "--quiet", *FAST_CLI],
                           capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    report = json.loads((out / "kbbatch-report.json").read_text())
    assert report["finished_at"] >= report["started_at"] and report["not_started"] == []
    assert sorted(out.glob(".*part*")) == sorted(users), "partial clips are still there"
    assert all(path.read_text() == "precious" for path in users)
    assert visible_clips(out) == ["p0.mp4", "p1.mp4"]
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert "RUNNING" not in status.stdout and "done 2" in status.stdout
    assert "LAST RUN" not in status.stdout, status.stdout


@pytest.mark.slow
def test_a_photo_folder_moved_and_back_keeps_what_the_report_said_of_its_clips(
        tmp_path, quick_preset):
    """Its clips skipped as up to date after the move lost their crops, preset and depth
    backend from the report (matched by the photo's old path), and never got them back."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    [made] = run_folder(folder, out, quick_preset, FAST, False).results
    assert made.status == "done" and made.plan
    for where in (tmp_path / "moved", folder):  # moved, then put back
        (tmp_path / "in" if where != folder else tmp_path / "moved").rename(where)
        [skipped] = run_folder(where, out, quick_preset, FAST, False).results
        assert skipped.status == "skipped", where
        [reported] = json.loads((out / "kbbatch-report.json").read_text())["clips"]
        for field in ("frames", "plan", "depth_backend", "preset"):
            assert reported[field] == asdict(made)[field], (where, field)


def test_a_run_killed_outright_keeps_what_the_report_said_of_the_clips_made_before(tmp_path):
    """The killed run's report had no clips, so the next run reported every clip it skipped
    as 0 frames, with no plan and no depth source, for good."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1, height=360, width=640)
    slow = ("--duration", "20", "--fps", "25")
    first = subprocess.run([*CLI, str(folder), "-o", str(out), "--depth", "ramp", "--planner",
                            "center", "--preset", "preview", "--quiet", *slow],
                           capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    made = json.loads((out / "kbbatch-report.json").read_text())["clips"][0]
    assert made["status"] == "done" and made["frames"] > 0 and made["plan"]
    photo(folder / "b.jpg", seed=2, height=360, width=640)
    process = start_batch(folder, out, *slow)
    try:
        wait_for(lambda: encoding(out), 180, "b's clip being encoded")
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=60)
    killed = json.loads((out / "kbbatch-report.json").read_text())
    assert killed["finished_at"] is None
    rerun = subprocess.run([*CLI, str(folder), "-o", str(out), "--depth", "ramp", "--planner",
                            "center", "--preset", "preview", "--quiet", *slow],
                           capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    clips = {Path(c["source"]).name: c for c in
             json.loads((out / "kbbatch-report.json").read_text())["clips"]}
    assert clips["a.jpg"]["status"] == "skipped" and clips["b.jpg"]["status"] == "done"
    for field in ("frames", "plan", "depth_backend", "preset"):
        assert clips["a.jpg"][field] == made[field], field


def test_ctrl_c_just_after_the_last_clip_still_finishes_the_report(
        tmp_path, quick_preset, monkeypatch):
    """Pressed in the milliseconds after the last clip was made (3 times in 4 at 1 to 3 ms),
    the interrupt was raised in the clean-up: the report kept no clip and no end time, and
    `status` said the run did not finish although every clip was made. (The Ctrl-C is sent
    by the progress bar's close, the clean-up's first step: no timing can aim that well.)"""
    from kbbatch import batch

    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    real_bar = batch.progress_bar

    def bar_interrupted_at_close(*args, **kwargs):
        bar = real_bar(*args, **kwargs)
        if kwargs.get("desc") == "photos":
            close = bar.close
            bar.close = lambda: (os.kill(os.getpid(), signal.SIGINT), close())
        return bar

    monkeypatch.setattr(batch, "progress_bar", bar_interrupted_at_close)
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert report.stopped_by == "SIGINT" and report.not_started == []
    written = json.loads((out / "kbbatch-report.json").read_text())
    assert written["finished_at"] is not None
    assert [clip["status"] for clip in written["clips"]] == ["done"]
    assert visible_clips(out) == ["a.mp4"]


class _KilledError(Exception):
    """What the default SIGTERM would have done: the process gone, no report."""


def test_a_sigterm_as_the_journal_opens_stops_the_run_with_a_report(
        tmp_path, quick_preset, monkeypatch):
    """A SIGTERM between the journal's opening and the batch's signal handlers (1 in about 12
    tries at 1 s) killed the run with no report. Sent here as the deleted photos are settled,
    the step after the opening."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    real_settle = batch.settle_deleted_photos

    def settle_then_terminated(*args):
        real_settle(*args)
        os.kill(os.getpid(), signal.SIGTERM)

    def killed(_number, _frame):
        raise _KilledError

    monkeypatch.setattr(batch, "settle_deleted_photos", settle_then_terminated)
    previous = signal.signal(signal.SIGTERM, killed)
    try:
        report = run_folder(folder, out, quick_preset, FAST, False)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert report.stopped_by == "SIGTERM"
    assert [Path(source).name for source in report.not_started] == ["a.jpg"]
    written = json.loads((out / "kbbatch-report.json").read_text())
    assert written["stopped_by"] == "SIGTERM" and written["finished_at"] is not None
    assert visible_clips(out) == []


@pytest.mark.slow
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_sigterm_and_ctrl_c_stop_a_batch_cleanly(tmp_path, stop_signal):
    """A hang-up (an SSH session dropped) stops it as SIGTERM does: it killed the batch at
    once with no report."""
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    returncode, stderr = act_while_encoding(folder, out, 6,
                                            lambda batch: batch.send_signal(stop_signal))
    assert returncode == 130, stderr
    assert "Traceback" not in stderr and "run again" in stderr, stderr
    assert not list(out.glob(".*part*")), "a partial clip was left"
    clips = visible_clips(out)
    if stop_signal != signal.SIGINT:  # the clip in progress is finished, the next not begun
        assert clips == ["p0.mp4"]
        report = json.loads((out / "kbbatch-report.json").read_text())
        assert report["stopped_by"] == stop_signal.name
    else:  # the report lists the photo that was stopped
        report = json.loads((out / "kbbatch-report.json").read_text())
        [stopped] = [c for c in report["clips"] if c["status"] == "interrupted"]
        assert stopped["source"].endswith("p0.jpg") and "SIGINT" in stopped["error"]
    # ... and the photo not begun (the report listed the made clips alone, status "done 1")
    assert [Path(source).name for source in report["not_started"]] == ["p1.jpg"]
    status = subprocess.run([*CLI, "status", str(out)], capture_output=True, text=True)
    assert "RUNNING" not in status.stdout, status.stdout
    assert f"stopped by {stop_signal.name}" in status.stdout, status.stdout
    assert "1 photo(s) not started: run again to finish" in status.stdout, status.stdout


@pytest.mark.slow
def test_a_sigterm_just_after_ctrl_c_does_not_cut_the_stop_short(tmp_path):
    """A supervisor's SIGTERM (or a second key) 0.05 to 0.2 s after a Ctrl-C killed the
    batch by the signal (status -15) while it cleaned up or shut down."""
    for delay_s in (0.05, 0.1, 0.2):
        folder, out = slow_folder(tmp_path / str(delay_s)), tmp_path / str(delay_s) / "out"

        def interrupt_then_terminate(batch: subprocess.Popen) -> None:
            batch.send_signal(signal.SIGINT)
            time.sleep(delay_s)  # noqa: B023 - used at once, inside the loop
            batch.send_signal(signal.SIGTERM)

        returncode, stderr = act_while_encoding(folder, out, 6, interrupt_then_terminate)
        assert returncode == 130, (delay_s, returncode, stderr)
        assert not list(out.glob(".*part*")), "a partial clip was left"
        report = json.loads((out / "kbbatch-report.json").read_text())
        assert report["finished_at"] and report["stopped_by"] == "SIGINT", (delay_s, report)


def test_a_batch_that_crashed_is_not_reported_as_stopped_by_fail_fast(
        tmp_path, monkeypatch, quick_preset):
    """An unexpected error (a MemoryError, say) ends the batch with its traceback; the report
    it leaves named no reason, with photos not started, which `kbbatch status` read as
    "ended at its first failure (--fail-fast)", an option never given."""
    from kbbatch import batch
    from kbbatch.batch import last_run_lines

    folder, out = tmp_path / "in", tmp_path / "out"
    for index in range(3):
        photo(folder / f"p{index}.jpg", seed=index)
    finish = batch.finish_job

    def crash_after_the_first(journal, job, result):
        if job.source.name != "p0.jpg":
            raise MemoryError
        return finish(journal, job, result)

    monkeypatch.setattr(batch, "finish_job", crash_after_the_first)
    with pytest.raises(MemoryError):
        run_folder(folder, out, quick_preset, FAST, False)
    [line] = last_run_lines(out)
    assert "stopped by an error (MemoryError)" in line and "--fail-fast" not in line, line


def _interrupt_a_library_turned_into_an_import_error():
    """What onnxruntime does with a Ctrl-C that lands while its compiled module loads."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as error:
        raise ImportError("initialization failed") from error


def test_a_ctrl_c_a_library_turned_into_another_error_still_stops_the_run(
        tmp_path, monkeypatch, capsys, quick_preset):
    """CI caught it once: Ctrl-C 0.6 s into `render` landed while onnxruntime loaded, which
    raised "ImportError: initialization failed" from the KeyboardInterrupt: a traceback and
    status 1. In a photo's make, the batch would have failed the photo and gone on."""
    from kbbatch import entry, pipeline

    monkeypatch.setattr(entry, "_run", _interrupt_a_library_turned_into_an_import_error)
    # stopped, the entry point ignores further signals until the process ends: this one must
    # hear them again (left ignored, every process the later tests start inherited that)
    handlers = {number: signal.getsignal(number)
                for number in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        with pytest.raises(SystemExit) as stopped:
            entry.main()
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)
    assert stopped.value.code == entry.EXIT_INTERRUPTED
    assert "interrupted" in capsys.readouterr().err
    source = photo(tmp_path / "in" / "a.jpg", seed=1)
    options = ClipOptions(depth=DepthOptions(backend="popup"), cache_depth=False)
    monkeypatch.setattr(pipeline, "prepare_scene",
                        lambda *args, **kwargs: _interrupt_a_library_turned_into_an_import_error())
    with pytest.raises(KeyboardInterrupt):
        pipeline.make_clip(source, tmp_path / "a.mp4", quick_preset, options, False)
    # any other error still fails that photo alone
    monkeypatch.setattr(pipeline, "prepare_scene",
                        lambda *args, **kwargs: (_ for _ in ()).throw(ImportError("no such")))
    result = pipeline.make_clip(source, tmp_path / "a.mp4", quick_preset, options, False)
    assert result.status == "failed" and "no such" in result.error
    assert not (tmp_path / "a.mp4").exists()


@pytest.mark.parametrize(("importer", "imported"), [("kbbatch", "tempfile"),
                                                  ("kbbatch.entry", "kbbatch.streams")])
def test_ctrl_c_while_the_first_modules_load_ends_with_130_and_no_traceback(importer, imported):
    """Ctrl-C 0.1 s after the start, on a loaded machine, landed in kbbatch/__init__'s own
    imports (tempfile), before kbbatch.entry could take it: a traceback, and death by SIGINT
    (1 full run in 3). Here the import itself is interrupted, every time."""
    code = ("import builtins, sys\n"
            "sys.argv[0] = 'kbbatch'\n"
            "real = builtins.__import__\n"
            "def hooked(name, globals=None, *args, **kwargs):\n"
            f"    if name == {imported!r} and (globals or {{}}).get('__name__') == {importer!r}:\n"
            "        raise KeyboardInterrupt\n"
            "    return real(name, globals, *args, **kwargs)\n"
            "builtins.__import__ = hooked\n"
            "from kbbatch.entry import main\n"
            "main()\n")
    run = subprocess.run([sys.executable, "-c", code, "presets"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 130, run.stderr
    assert "Traceback" not in run.stderr and "run again" in run.stderr, run.stderr


@pytest.mark.parametrize("command", ["render", "plan"])
def test_ctrl_c_while_it_starts_up_ends_with_130_and_no_traceback(tmp_path, command):
    """Ctrl-C while the modules loaded gave a traceback; while a command set up (or, in
    `plan`, planned), click's "Aborted!" and status 1, which says that photos failed."""
    folder = tmp_path / "in"
    photo(folder / "a.jpg", seed=1)
    for delay_s in (0.1, 0.3, 0.6, 1.0):
        target = tmp_path / f"out{delay_s}"
        if command == "plan":
            target = target.with_suffix(".json")
        process = subprocess.Popen([*CLI, command, str(folder), "-o", str(target), *FAST_CLI],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(delay_s)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=120)
        if "written to" in stdout or "made in" in stdout:  # through before the signal came
            continue
        if "init_import_site" in stderr:  # before Python ran any of kbbatch (a loaded machine)
            continue
        assert process.returncode == 130, (delay_s, stderr)
        assert "Traceback" not in stderr and "Aborted" not in stderr, (delay_s, stderr)
        assert "run again" in stderr, (delay_s, stderr)


def test_ctrl_c_in_code_built_from_a_string_still_ends_with_130(tmp_path):
    """A Ctrl-C landing in a dataclass's methods being built (code run from a string) while
    the modules loaded: caught and said, but `python -m kbbatch` then died by SIGINT at exit
    (status -2, not 130; 4 of 60 Ctrl-Cs in `kbbatch plan`'s first half second)."""
    probe = tmp_path / "ctrl_c_probe.py"
    probe.write_text("import kbbatch.entry as entry\n"
                     "def interrupted_while_loading():\n"
                     "    exec('raise KeyboardInterrupt')\n"
                     "entry._run = interrupted_while_loading\n"
                     "entry.main()\n")
    repository = Path(__file__).resolve().parents[1]
    environment = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{repository}"}
    done = subprocess.run([sys.executable, "-m", "ctrl_c_probe"], cwd=tmp_path, env=environment,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 130, (done.returncode, done.stderr)
    assert "run again" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.slow
def test_a_hang_up_of_its_terminal_stops_a_batch_cleanly_unless_it_was_nohup(tmp_path):
    """On a terminal that has hung up, isatty() is false and every write fails (EIO): the
    summary's print failed the run with a traceback (exit 1). Under nohup (SIGHUP ignored
    when it started) a hang-up is no reason to stop."""
    import pty

    folder, out = slow_folder(tmp_path), tmp_path / "out"
    master, terminal = pty.openpty()
    process = subprocess.Popen(
        [*CLI, str(folder), "-o", str(out), *FAST_CLI, "--quiet", "--duration", "6"],
        stdout=terminal, stderr=terminal, preexec_fn=hang_ups_heard)
    os.close(terminal)
    try:
        wait_for(lambda: encoding(out), 180, "a clip being encoded")
        os.close(master)  # the terminal hangs up ...
        process.send_signal(signal.SIGHUP)  # ... and the kernel says so
        assert process.wait(timeout=300) == 130
    finally:
        if process.poll() is None:
            process.kill()
    report = json.loads((out / "kbbatch-report.json").read_text())
    assert report["stopped_by"] == "SIGHUP"
    assert [c["status"] for c in report["clips"]] == ["done"]
    assert visible_clips(out) == ["p0.mp4"]

    nohup = subprocess.Popen(
        [*CLI, str(folder), "-o", str(tmp_path / "nohup"), *FAST_CLI, "--duration", "3"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:
        wait_for(lambda: encoding(tmp_path / "nohup"), 180, "a clip")
        nohup.send_signal(signal.SIGHUP)
        _, stderr = nohup.communicate(timeout=300)
    finally:
        if nohup.poll() is None:
            nohup.kill()
    assert nohup.returncode == 0, stderr
    assert visible_clips(tmp_path / "nohup") == ["p0.mp4", "p1.mp4"]

def test_a_second_batch_into_the_same_folder_is_refused(tmp_path, quick_preset):
    photo(tmp_path / "in" / "a.jpg", seed=1)
    (tmp_path / "out").mkdir()
    lock = FolderLock(tmp_path / "out", "writing clips into")
    try:
        with pytest.raises(FolderBusyError, match="another kbbatch"):
            run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    finally:
        lock.release()
    assert not visible_clips(tmp_path / "out")


def test_a_run_starting_while_status_looks_at_the_folder_is_not_refused(tmp_path):
    """`kbbatch status` takes the output folder's lock for an instant (to tell a killed run
    from a live one): a batch or daemon starting in that instant was refused."""
    import threading

    (tmp_path / "out").mkdir()
    glance = FolderLock(tmp_path / "out", "writing clips into", wait_s=0.0)
    threading.Timer(0.2, glance.release).start()
    FolderLock(tmp_path / "out", "writing clips into").release()  # waits for the glance


# --- 6: crop size ---------------------------------------------------------------------------
def test_a_photo_too_narrow_for_the_output_says_so_not_which_crop_to_give(tmp_path,
                                                                           quick_preset):
    """With no manifest the tool chose the crop: the photo is what is too small."""
    photo(tmp_path / "in" / "thin.png", seed=2, height=4000, width=12)  # cloud too large
    photo(tmp_path / "in" / "wide.png", seed=3, height=12, width=4000)  # enlarged 40x
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    assert len(report.failed) == 2
    for failed in report.failed:
        assert ".png: too small for 640 px wide clips" in failed.error
        assert "use a larger photo" in failed.error and "make the tightest" not in failed.error


@pytest.mark.parametrize("end", [{"center_x": 320, "center_y": 180, "width": 20},
                                 {"center_x": 0.5, "center_y": 0.5, "width": 0.0001},
                                 {"center_x": 0.5, "center_y": 0.5, "width": 1e-300},
                                 {"center_x": 0.5, "center_y": 0.5, "width": 1e-307},
                                 {"center_x": 0.5, "center_y": 0.5, "width": 5e-324}])
def test_a_tiny_manifest_crop_is_refused_with_the_width_that_fits(tmp_path, end):
    """Run under a 4 GB address-space limit: an unbounded cloud fails otherwise, not here.
    At 1e-307 px the message said "an inf M-point cloud", "at least inf px" and came with a
    divide-by-zero warning; at 5e-324 it blamed the crop's aspect."""
    folder = tmp_path / "in"
    photo(folder / "a.jpg", seed=1, height=360, width=640)
    units = "fraction" if end["width"] < 1 else "px"
    start = ({"center_x": 0.5, "center_y": 0.5, "width": 0.9} if units == "fraction"
             else {"center_x": 320, "center_y": 180, "width": 600})
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {
        "units": units, "start": start, "end": end}}}))

    def limit_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    run = subprocess.run([*CLI, str(folder), "-o", str(tmp_path / "out"), "--manifest",
                          str(manifest), "--quiet", "--depth", "ramp", "--preset", "slideshow",
                          "--duration", "0.5"], capture_output=True, text=True, timeout=300,
                         preexec_fn=limit_memory)
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr and "Warning" not in run.stderr, run.stderr
    if end["width"] == 5e-324:  # below floating point's precision (it blamed the aspect)
        assert "field 'end': crop 4.941e-324 wide is too small to frame" in run.stderr
        return
    assert "a.jpg" in run.stderr and "too tight" in run.stderr, run.stderr
    assert "make the tightest crop at least 81 px wide" in run.stderr, run.stderr
    assert "inf" not in run.stderr.replace("info", ""), run.stderr


# --- 8: permissions -------------------------------------------------------------------------
def test_a_photo_without_read_permission_is_not_called_corrupt(tmp_path):
    path = photo(tmp_path / "secret.jpg", seed=1)
    path.chmod(0o000)
    if os.geteuid() != 0:
        with pytest.raises(ImageReadError) as caught:
            read_image(path)
        message = str(caught.value)
    else:  # root reads everything: ask as root without the capabilities that bypass modes
        if shutil.which("setpriv") is None:
            pytest.skip("running as root and util-linux setpriv is missing")
        script = ("from kbbatch.images import read_image\n"
                  f"try:\n    read_image({str(path)!r})\n"
                  "except Exception as e:\n    print(e)\n")
        run = subprocess.run(["setpriv", "--inh-caps=-all", "--ambient-caps=-all",
                              "--bounding-set=-dac_override,-dac_read_search", sys.executable,
                              "-c", script], capture_output=True, text=True)
        message = run.stdout + run.stderr
    assert "secret.jpg" in message and "permission denied" in message, message
    assert "corrupt" not in message


# --- 9: plan previews -----------------------------------------------------------------------
def test_plan_previews_of_same_stem_photos_do_not_collide(tmp_path, quick_preset):
    photo(tmp_path / "in" / "a.jpg", seed=1)
    photo(tmp_path / "in" / "a.png", seed=2)
    photo(tmp_path / "in" / "b.jpg", seed=3)
    photo(tmp_path / "in" / "a.jpg.png", seed=4)  # its stem is the first one's name
    results = plan_folder(tmp_path / "in", tmp_path / "plans" / "manifest.json", quick_preset,
                          FAST, False)
    assert [r.status for r in results] == ["done"] * 4
    previews = sorted(p.name for p in (tmp_path / "plans" / "manifest-previews").iterdir())
    assert previews == ["a.jpg.jpg", "a.jpg.png.jpg", "a.png.jpg", "b.jpg", "contact-sheet.png"]


def test_a_users_file_in_the_previews_folder_is_never_written_over(tmp_path, quick_preset):
    """`<manifest>-previews/` is kbbatch's by name, but a user may keep a file there (an
    edited preview, notes): plan wrote its preview over any file of the preview's name. Its
    own previews (marked) are still replaced by a new plan."""
    from kbbatch.images import is_own_png, own_image_text

    photo(tmp_path / "in" / "a.jpg", seed=1)
    photo(tmp_path / "in" / "b.jpg", seed=2)
    manifest = tmp_path / "plans" / "manifest.json"
    previews = tmp_path / "plans" / "manifest-previews"
    previews.mkdir(parents=True)
    users = previews / "a.jpg"
    users.write_bytes(b"the user's own picture")
    results = plan_folder(tmp_path / "in", manifest, quick_preset, FAST, False)
    assert [r.status for r in results] == ["done", "done"]
    assert users.read_bytes() == b"the user's own picture"
    assert "not written over" in results[0].note and str(users) in results[0].note
    assert results[1].note is None
    assert own_image_text(previews / "b.jpg") == {}, "its preview is no JPEG marked as kbbatch's"
    assert is_own_png(previews / "contact-sheet.png")
    first = (previews / "b.jpg").stat().st_mtime_ns
    again = plan_folder(tmp_path / "in", manifest, quick_preset, FAST, False, replan=True)
    assert again[1].status == "done" and again[1].note is None
    assert (previews / "b.jpg").stat().st_mtime_ns > first, "its own preview was not renewed"
    assert users.read_bytes() == b"the user's own picture"


@pytest.mark.parametrize("names", [
    ("x.jpg", "x.png", "x.jpg.png"),  # a stem that is another photo's full name
    ("A.jpg", "a.jpg", "a.jpg.2.png"),  # names differing in case, and one like their number
    ("IMG_1.JPG", "img_1.png", "IMG_1.jpg.png", "other.jpg"),
    ("N" * 251 + ".jpg", "N" * 251 + ".png", "n" * 251 + ".jpg"),  # names of 255 bytes
])
def test_clip_names_of_a_folder_are_distinct_ignoring_case(names):
    from kbbatch.outputs import output_names

    clips = output_names([Path("/photos") / name for name in names])
    assert len({clip.lower() for clip in clips.values()}) == len(names), clips
    assert clips[Path("/photos") / names[-1]].startswith(Path(names[-1]).stem[:200])
    assert all(len(os.fsencode(clip)) <= 255 for clip in clips.values())


def test_plan_beside_the_photos_adds_no_photo_and_survives_a_name_that_is_not_utf8(
        tmp_path, quick_preset):
    """A name that is not UTF-8 crashed the whole plan run inside OpenCV's putText (no
    manifest); the contact sheet written beside a manifest in the photo folder became a clip
    of its own on the next render."""
    folder = tmp_path / "photos"
    odd = photo(folder / os.fsdecode(b"caf\xe9.jpg"), seed=1)
    photo(folder / "b.jpg", seed=2)
    manifest = folder / "manifest.json"
    results = plan_folder(folder, manifest, quick_preset, FAST, False)
    assert [r.status for r in results] == ["done", "done"]
    assert odd.name in json.loads(manifest.read_text())["images"]
    assert sorted(p.name for p in scan_folder(folder).photos) == sorted([odd.name, "b.jpg"])


# --- 10: truncated clips, links, subfolders, empty folders, logs -----------------------------
@pytest.mark.parametrize("kept", [1 / 3, 0.0])
def test_a_truncated_clip_is_not_up_to_date(tmp_path, quick_preset, kept):
    """An empty file at the clip's name (a copy that failed at its start) was taken for a
    file of the user's: kept for good, the clip made beside it under a content name."""
    photo(tmp_path / "in" / "a.jpg", seed=1)
    run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    clip = tmp_path / "out" / "a.mp4"
    whole = clip.read_bytes()
    clip.write_bytes(whole[: int(len(whole) * kept)])
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["done"]
    assert [Path(r.output).name for r in report.results] == ["a.mp4"]
    assert clip.stat().st_size == len(whole)


@pytest.mark.parametrize("saved", ["trimmed video", "other file", "four bytes"])
def test_a_file_the_user_saved_over_a_clip_is_never_replaced(tmp_path, quick_preset, saved):
    """The clip trimmed in an editor and saved in place (or any file saved at its name): taken
    for a clip changed since kbbatch wrote it, it was rendered over on the next run."""
    import subprocess

    from kbbatch.encode import ffmpeg_exe

    path = photo(tmp_path / "in" / "a.jpg", seed=1)
    out = tmp_path / "out"
    run_folder(tmp_path / "in", out, quick_preset, FAST, False)
    clip = out / "a.mp4"
    if saved == "trimmed video":
        trimmed = tmp_path / "trimmed.mp4"
        subprocess.run([ffmpeg_exe(), "-v", "error", "-i", str(clip), "-t", "0.5", "-c:v",
                        "libx264", str(trimmed)], check=True)
        clip.write_bytes(trimmed.read_bytes())
    elif saved == "four bytes":  # shorter than an MP4's first box header, and no part of one
        clip.write_text("todo")
    else:
        clip.write_text("the user's notes")
    users = clip.read_bytes()
    report = run_folder(tmp_path / "in", out, quick_preset, FAST, False)
    [result] = report.results
    assert result.status == "done" and Path(result.output).name.startswith("a.")
    assert Path(result.output).name != "a.mp4" and "did not write" in result.note
    photo(path, seed=2)  # and an edit of the photo replaces its clip, not the user's file
    edited = run_folder(tmp_path / "in", out, quick_preset, FAST, False)
    assert [r.output for r in edited.results] == [result.output]
    assert clip.read_bytes() == users
    assert len(visible_clips(out)) == 2


def test_a_clip_touched_or_copied_without_its_time_is_up_to_date(tmp_path, quick_preset):
    """A clip was up to date only with the time it was written: `touch`, or an output folder
    copied without times (`cp -r`), made every clip again."""
    photo(tmp_path / "in" / "a.jpg", seed=1)
    run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    clip = tmp_path / "out" / "a.mp4"
    os.utime(clip, (clip.stat().st_atime + 100, clip.stat().st_mtime + 100))
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["skipped"]


def test_broken_links_and_subfolders_are_reported(tmp_path, quick_preset):
    folder = tmp_path / "in"
    photo(folder / "a.jpg", seed=1)
    (folder / "gone.jpg").symlink_to(tmp_path / "nowhere.jpg")
    photo(folder / "more" / "b.jpg", seed=2)
    os.mkfifo(folder / "pipe.jpg")  # read, it would block the batch for good
    (folder / "loop1.jpg").symlink_to("loop2.jpg")  # each target exists: it is the other
    (folder / "IMG_0002.heic").write_bytes(b"ftypheic")  # a phone's photo, not read
    (folder / "IMG_0003.PEF").write_bytes(b"raw")  # a camera's raw file, not read
    photo(folder / "saved.jfif", seed=5)  # JPEGs by other names: read
    photo(folder / "camera.JPE", seed=6)
    (folder / "notes.txt").write_text("not a photo at all")
    (folder / "loop2.jpg").symlink_to("loop1.jpg")
    photo(folder / "crops-contact.jpg", seed=3)  # an old `kbbatch plan`'s sheet...
    (folder / "crops-previews").mkdir()  # ...beside its previews
    photo(folder / "team-contact.jpg", seed=4)  # a photo so named, with no previews beside it
    (folder / "clips").mkdir()  # earlier clips: no photos, nothing to advise
    photo(folder / "crops-previews" / "a.jpg", seed=8)  # `plan`'s previews: no advice either
    photo(folder / "crops-previews" / "contact-sheet.png", seed=9)
    (folder / "again").symlink_to(folder)  # a link back to the folder itself
    (folder / "clips" / "a.mp4").write_bytes(b"a clip")
    photo(folder / "holiday.depth.png", seed=7)  # a photo saved under a map's name
    report = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    by_name = {Path(r.source).name: r for r in report.results}
    assert by_name["a.jpg"].status == "done"
    assert by_name["team-contact.jpg"].status == "done"
    assert by_name["saved.jfif"].status == by_name["camera.JPE"].status == "done"
    assert "crops-contact.jpg" not in by_name
    assert f"{folder / 'crops-contact.jpg'}: {OLD_PLAN_SHEET_REASON}" in report.notes
    assert "pipe.jpg: is not a regular file" in by_name["pipe.jpg"].error
    assert by_name["gone.jpg"].status == "failed"
    assert "broken symbolic link (its target" in by_name["gone.jpg"].error
    for name in ("loop1.jpg", "loop2.jpg"):
        assert by_name[name].status == "failed"
        assert "symbolic link in a loop" in by_name[name].error
    assert [note for note in report.notes if "subfolder" in note] == [
        f"{folder / 'more'}: subfolder not searched (run kbbatch on it to render its photos)"]
    assert f"{folder / 'holiday.depth.png'}: {LONE_MAP_REASON}" in report.notes
    assert [note for note in report.notes if "format kbbatch does not read" in note] == [
        f"{folder / name}: {UNREAD_FORMAT_REASON}" for name in ("IMG_0002.heic", "IMG_0003.PEF")]


def test_a_photo_whose_name_ends_in_a_space_or_a_dot_is_said_not_passed_over(tmp_path,
                                                                          quick_preset):
    """`IMG_1.jpg ` (copied from a system that kept the space) has no photo's extension: it
    was skipped without a word, and alone gave `no photos here` with no reason."""
    folder = tmp_path / "in"
    photo(folder / "IMG_1.jpg", seed=1).rename(folder / "IMG_1.jpg ")
    run = subprocess.run([*CLI, str(folder), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 3, run.stderr
    assert f"IMG_1.jpg : {NAME_END_REASON}" in run.stderr, run.stderr
    photo(folder / "IMG_2.JPG", seed=2).rename(folder / "IMG_2.JPG.")
    photo(folder / "IMG_3.jpg", seed=3)
    (folder / "notes.txt ").write_text("not a photo, whatever its name")
    for name in ("...", " . "):  # nothing left of them trimmed: no photo (it was a traceback)
        (folder / name).write_text("dots and spaces only")
    report = run_folder(folder, tmp_path / "out", quick_preset, FAST, False)
    assert [(Path(r.source).name, r.status) for r in report.results] == [("IMG_3.jpg", "done")]
    assert [note for note in report.notes if NAME_END_REASON in note] == [
        f"{folder / name}: {NAME_END_REASON}" for name in ("IMG_1.jpg ", "IMG_2.JPG.")]
    assert (folder / "IMG_1.jpg ").is_file() and (folder / "IMG_2.JPG.").is_file()


def test_an_empty_folder_says_so_and_writes_nothing(tmp_path):
    (tmp_path / "empty").mkdir()
    run = subprocess.run([*CLI, str(tmp_path / "empty"), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 3, run.stderr
    assert "no photos" in run.stderr and "empty" in run.stderr
    assert not (tmp_path / "out").exists()
    # photos in subfolders only: the error names what it did not search
    photo(tmp_path / "cards" / "2024-card-a" / "p.jpg", seed=0)
    run = subprocess.run([*CLI, str(tmp_path / "cards"), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 3, run.stderr
    assert "subfolders are not searched: 2024-card-a" in run.stderr
    # a phone's photos only: said as such, not "no photos" alone
    (tmp_path / "phone").mkdir()
    (tmp_path / "phone" / "IMG_0001.HEIC").write_bytes(b"ftypheic")
    run = subprocess.run([*CLI, str(tmp_path / "phone"), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 3, run.stderr
    assert "IMG_0001.HEIC: a photo format kbbatch does not read" in run.stderr


def test_hidden_photos_are_said_not_passed_over_in_silence(tmp_path, quick_preset):
    """`.IMG_0001.jpg` alone gave `no photos here`, beside others it was left out unsaid."""
    photo(tmp_path / "hidden" / ".IMG_0001.jpg", seed=0)
    (tmp_path / "hidden" / "._IMG_0002.jpg").write_bytes(b"\0\5\26\7 mac resource fork")
    run = subprocess.run([*CLI, str(tmp_path / "hidden"), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 3, run.stderr
    assert ".IMG_0001.jpg: hidden (the name starts with a dot)" in run.stderr, run.stderr
    assert "._IMG_0002" not in run.stderr
    photo(tmp_path / "hidden" / "IMG_0003.jpg", seed=1)
    report = run_folder(tmp_path / "hidden", tmp_path / "out", quick_preset, FAST, False)
    assert [Path(r.source).name for r in report.results] == ["IMG_0003.jpg"]
    assert any(".IMG_0001.jpg: hidden" in note for note in report.notes), report.notes


def test_progress_into_a_log_has_no_zero_lines_or_escape_codes(tmp_path):
    for index in range(2):
        photo(tmp_path / "in" / f"p{index}.jpg", seed=index)
    log = tmp_path / "log.txt"
    with log.open("w") as handle:
        run = subprocess.run([*CLI, str(tmp_path / "in"), "-o", str(tmp_path / "out"),
                              *FAST_CLI], stdout=handle, stderr=subprocess.STDOUT)
    text = log.read_text()
    assert run.returncode == 0, text
    assert "\r" not in text and "\x1b" not in text and " 0%" not in text, repr(text)
    assert "photos 2/2" in text


# --- 11: --jobs default ---------------------------------------------------------------------
@pytest.mark.parametrize(("cores", "memory_gib", "jobs"),
                         [(2, 24, 1), (16, 64, 4), (16, 4, 1), (64, 16, 5), (1, 1, 1)])
def test_default_jobs_follows_cores_and_memory(monkeypatch, cores, memory_gib, jobs):
    monkeypatch.setattr(batch.os, "cpu_count", lambda: cores)
    pages = {"SC_PHYS_PAGES": memory_gib * 2**18, "SC_PAGE_SIZE": 4096}
    monkeypatch.setattr(batch.os, "sysconf", lambda name: pages[name])
    assert default_jobs() == jobs


def test_watch_help_states_the_jobs_default():
    run = subprocess.run([*CLI, "watch", "--help"], capture_output=True, text=True, check=True)
    assert f"(here: {default_jobs()})" in " ".join(run.stdout.split())


def test_a_journal_of_the_earlier_version_keeps_its_clip_names(tmp_path, quick_preset):
    """Journals keyed by file name (before issue 14) still own their clips: no duplicates."""
    import sqlite3

    path = photo(tmp_path / "in" / "a.jpg", seed=1)
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.mp4").write_bytes(b"clip of an earlier version")
    legacy = sqlite3.connect(out / ".kbbatch-journal.sqlite")
    legacy.execute("CREATE TABLE jobs (source TEXT PRIMARY KEY, fingerprint TEXT NOT NULL,"
                   " settings TEXT NOT NULL, state TEXT NOT NULL, output TEXT, error TEXT,"
                   " attempts INTEGER NOT NULL DEFAULT 0, seconds REAL, updated REAL NOT NULL)")
    legacy.execute("INSERT INTO jobs VALUES ('a.jpg', ?, 'x', 'done', 'a.mp4', NULL, 1, 1.0, 1.0)",
                   (f"{path.stat().st_size}:{path.stat().st_mtime_ns}",))
    legacy.commit()
    legacy.close()
    report = run_folder(tmp_path / "in", out, quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["done"]
    assert visible_clips(out) == ["a.mp4"] and (out / "a.mp4").stat().st_size > 1000


def test_an_output_folder_removed_mid_run_stops_the_run_and_is_not_made_again(tmp_path):
    """It was made again by the next clip, its journal lost: the re-run then made every clip
    a second time under content names, and a second run could take the new folder's lock."""
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    returncode, stderr = act_while_encoding(folder, out, 4, lambda _: shutil.rmtree(out))
    assert returncode == 1, stderr
    assert f"{out}: removed or renamed during the run; stopped" in stderr
    assert not out.exists()


def test_an_output_folder_renamed_mid_run_does_not_fail_the_photo_in_flight(tmp_path):
    """The clip being encoded lost its temporary file with the folder: the photo was recorded
    FAILED with a raw FileNotFoundError naming that hidden file, not taken again."""
    folder, out = slow_folder(tmp_path), tmp_path / "out"
    moved = tmp_path / "moved"
    returncode, stderr = act_while_encoding(folder, out, 4, lambda _: out.rename(moved))
    assert returncode == 1, stderr
    assert f"{out}: removed or renamed during the run; stopped" in stderr
    status = subprocess.run([*CLI, "status", str(moved)], capture_output=True, text=True)
    assert "failed 0" in status.stdout and "FileNotFoundError" not in status.stdout, \
        status.stdout
    # The run's report went with its clips: it said the run was started, never how it ended.
    assert f"are in {moved}, with this run's report" in stderr, stderr
    report = json.loads((moved / "kbbatch-report.json").read_text())
    assert report["stopped_by"] == batch.FOLDER_GONE and report["finished_at"]
    assert report["output_folder"] == str(moved)
    assert f"{out} was moved to {moved} during the run" in report["notes"]
    assert report["not_started"], report  # the photos after the one in flight
    assert "stopped by the output folder removed or renamed" in status.stdout, status.stdout


def linked_folder(tmp_path: Path) -> tuple[Path, Path, Path]:
    """photos/ with a.jpg, link -> photos, and the output folder's path."""
    real = tmp_path / "photos"
    photo(real / "a.jpg", seed=1)
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    return real, link, tmp_path / "out"


def test_a_folder_run_by_two_spellings_is_not_made_again(tmp_path, quick_preset):
    """Photos run once as `photos/` and once through a link to it (a home-folder link to a
    share, a bind mount): the journal keyed the clips by the first spelling, so the second
    made every clip again, and switching back made them all once more. The link then pointed
    at another card, whose photo has the same name and other bytes: that photo is no spelling
    of the first and gets a clip of its own."""
    real, link, out = linked_folder(tmp_path)
    [first] = run_folder(real, out, quick_preset, FAST, False).results
    assert first.status == "done"
    made = (out / "a.mp4").stat().st_mtime_ns
    for folder in (link, real):
        [again] = run_folder(folder, out, quick_preset, FAST, False).results
        assert again.status == "skipped", f"made again through {folder.name}"
    assert (out / "a.mp4").stat().st_mtime_ns == made
    other = tmp_path / "card2"
    photo(other / "a.jpg", seed=2)
    link.unlink()
    link.symlink_to(other, target_is_directory=True)
    [second] = run_folder(link, out, quick_preset, FAST, False).results
    assert second.status == "done" and Path(second.output).name != "a.mp4"
    assert (out / "a.mp4").stat().st_mtime_ns == made, "the first card's clip was replaced"


def test_an_edit_seen_through_another_spelling_replaces_its_clip_in_place(tmp_path,
                                                                         quick_preset):
    """A photo edited in place, then run through a link to its folder, was taken for a new
    photo: a second clip under a content name beside the old one, and a note calling the old
    one another photo's."""
    real, link, out = linked_folder(tmp_path)
    run_folder(real, out, quick_preset, FAST, False)
    photo(real / "a.jpg", seed=21)  # edited in place
    [result] = run_folder(link, out, quick_preset, FAST, False).results
    assert result.status == "done" and Path(result.output).name == "a.mp4"
    assert "changed since a.mp4 was made" in result.note
    assert visible_clips(out) == ["a.mp4"]
    journal = Journal(out)
    try:
        assert len(journal.jobs()) == 1
    finally:
        journal.close()


def test_a_link_moved_to_another_card_keeps_the_first_cards_clips(tmp_path, quick_preset):
    """A fixed path (a link, a card's mount point) moved from one card to another with the
    same file names: the second card's IMG_1.jpg was taken for an edit of the first card's,
    whose clip it replaced."""
    for card, seed in (("card1", 1), ("card2", 31)):
        photo(tmp_path / card / "IMG_1.jpg", seed=seed)
    link = tmp_path / "SDCARD"
    link.symlink_to(tmp_path / "card1", target_is_directory=True)
    out = tmp_path / "out"
    [first] = run_folder(link, out, quick_preset, FAST, False).results
    made = (out / "IMG_1.mp4").stat().st_mtime_ns
    link.unlink()
    link.symlink_to(tmp_path / "card2", target_is_directory=True)
    [second] = run_folder(link, out, quick_preset, FAST, False).results
    assert second.status == "done" and Path(second.output).name != "IMG_1.mp4"
    assert (out / "IMG_1.mp4").stat().st_mtime_ns == made, "the first card's clip was replaced"
    assert len(visible_clips(out)) == 2


def test_the_daemon_through_a_link_to_its_inbox_does_not_make_its_clips_again(tmp_path):
    """The daemon started once on a link to its inbox, once on the inbox itself, made every
    clip again (and left jobs under the other spelling)."""
    from .test_watch import finished_jobs, preset_file, start_daemon, stop

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    photo(inbox / "a.jpg", seed=1)
    link = tmp_path / "link"
    link.symlink_to(inbox, target_is_directory=True)
    preset = preset_file(tmp_path, 0.6)
    log_path = tmp_path / "daemon.log"
    daemon = start_daemon(link, outbox, preset, "--keep-sources", log_path=log_path)
    try:
        wait_for(lambda: finished_jobs(outbox) == 1, 120, "the clip through the link")
    finally:
        assert stop(daemon) == 0
    made = (outbox / "a.mp4").stat().st_mtime_ns
    log_path.write_bytes(b"")
    daemon = start_daemon(inbox, outbox, preset, "--keep-sources", log_path=log_path)
    try:
        wait_for(lambda: "already complete" in log_path.read_text(), 120,
                 "the daemon to find the clip made")
    finally:
        assert stop(daemon) == 0
    assert (outbox / "a.mp4").stat().st_mtime_ns == made, "the clip was made again"
    journal = Journal(outbox)
    try:
        assert [Path(job.source).parent for job in journal.jobs()] == [inbox]
    finally:
        journal.close()


def test_a_journal_with_a_photo_under_two_spellings_settles_on_one(tmp_path, quick_preset):
    """A journal of a version that kept paths as typed, after runs through a link and by the
    folder's own name, holds one job per spelling, each claiming the clip: every switch made
    it again, and `status` counted the photo twice. The latest record is kept, the other
    dropped, and nothing is made again."""
    real, link, out = linked_folder(tmp_path)
    run_folder(real, out, quick_preset, FAST, False)
    made = (out / "a.mp4").stat().st_mtime_ns
    journal = Journal(out)
    try:  # the same record under the link's spelling, as the earlier version left it
        journal.connection.execute(
            "INSERT INTO jobs SELECT ?, fingerprint, settings, state, output, error, attempts,"
            " seconds, updated + 1, content, clip, folder, taken, kept_settings, kept_clip"
            " FROM jobs WHERE source = ?",
            (str(link / "a.jpg"), str(real / "a.jpg")))
        assert len(journal.jobs()) == 2
    finally:
        journal.close()
    for folder in (link, real):
        [again] = run_folder(folder, out, quick_preset, FAST, False).results
        assert again.status == "skipped", f"made again through {folder.name}"
    assert (out / "a.mp4").stat().st_mtime_ns == made
    journal = Journal(out)
    try:
        assert [job.source for job in journal.jobs()] == [str(real / "a.jpg")]
    finally:
        journal.close()


def test_a_run_killed_mid_encode_leaves_no_depth_maps_of_a_clip_not_made(tmp_path,
                                                                          quick_preset):
    """--save-depth wrote a photo's maps before its clip: a run killed mid-encode left the
    new maps beside no clip (or, after an edit, beside the old photo's clip)."""
    from .test_watch import held_encoders

    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    # a clip of some length: the encoder of a 0.6 s clip may come and go between two looks
    run = subprocess.Popen([*CLI, str(folder), "-o", str(out), "--quiet", "--save-depth",
                            *FAST_CLI, "--duration", "4", "--fps", "25"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        encoders = held_encoders(out, "a")
        assert not list(out.glob("a.*.png")), "maps written before the clip"
    finally:
        run.kill()
        run.wait(timeout=60)
    for pid in encoders:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not list(out.glob("a.*.png")) and not (out / "a.mp4").exists()
    [result] = run_folder(folder, out, quick_preset, replace(FAST, save_depth=True),
                          False).results
    assert result.status == "done"
    assert sorted(p.name for p in out.glob("a.*.png")) == ["a.depth-preview.png",
                                                             "a.disparity.png"]


def test_a_deleted_photos_job_under_an_earlier_spelling_is_settled(tmp_path, quick_preset):
    """A journal of an earlier version keeps a killed run's job under the link it was run
    through; the photo deleted, the next run by the folder's own name compared the job's
    folder as text and left it queued for ever. The report names folders as resolved, as it
    names the photos."""
    real = tmp_path / "photos"
    photo(real / "a.jpg", seed=1)
    photo(real / "b.jpg", seed=2)
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    out = tmp_path / "out"
    journal = Journal(out)
    try:  # as the earlier version left it: running, keyed through the link
        journal.start(link / "b.jpg", "fingerprint", "settings", "b.mp4", "content")
    finally:
        journal.close()
    (real / "b.jpg").unlink()
    report = run_folder(link, out, quick_preset, FAST, False)
    assert [r.status for r in report.results] == ["done"]
    assert report.folder == str(real)
    assert [r.source for r in report.results] == [str(real / "a.jpg")]
    journal = Journal(out)
    try:
        assert [job.source for job in journal.jobs()] == [str(real / "a.jpg")]
    finally:
        journal.close()


def test_an_output_folder_named_through_a_link_and_dot_dot_is_written(tmp_path, quick_preset):
    """`-o x/../out` with x a link to deep/real: the folder was made at deep/out (where the
    kernel resolves it), then the run failed, "not writable"."""
    (tmp_path / "deep" / "real").mkdir(parents=True)
    (tmp_path / "x").symlink_to(tmp_path / "deep" / "real", target_is_directory=True)
    photo(tmp_path / "photos" / "a.jpg", seed=1)
    report = run_folder(tmp_path / "photos", tmp_path / "x" / ".." / "out", quick_preset, FAST,
                        False)
    assert [r.status for r in report.results] == ["done"]
    assert visible_clips(tmp_path / "deep" / "out") == ["a.mp4"]
    assert report.output_folder == str(tmp_path / "deep" / "out")


def test_a_damaged_journal_says_how_to_go_on_and_going_on_keeps_the_clips(tmp_path,
                                                                         quick_preset):
    """A journal that is no longer a database stopped every run into its folder with "file is
    not a database" and nothing more. The advice given is followed here: the clip made
    before stays as it was, known as this photo's by its mark, and up to date."""
    from kbbatch.journal import JOURNAL_NAME
    from kbbatch.outputs import OutputFolderError

    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    run_folder(folder, out, quick_preset, FAST, False)
    made = (out / "a.mp4").read_bytes()
    (out / JOURNAL_NAME).write_bytes(b"\x13garbage, not a database" * 700)
    with pytest.raises(OutputFolderError, match="it is damaged: move it aside and run again"):
        run_folder(folder, out, quick_preset, FAST, False)
    (out / JOURNAL_NAME).rename(tmp_path / "journal.bak")
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert [result.status for result in report.results] == ["skipped"]
    assert (out / "a.mp4").read_bytes() == made
    assert visible_clips(out) == ["a.mp4"]


def test_a_marked_edit_or_a_cut_copy_is_never_made_over_once_the_journal_is_gone(
        tmp_path, quick_preset):
    """An edit saved in place may keep the clip's mark (a trim by stream copy does): taken
    as the clip, it is kept when the clip is made again (--force, other settings), the new
    one beside it. A copy that stopped keeps the mark at its start, and is no clip."""
    import imageio_ffmpeg

    from kbbatch.encode import read_clip_mark
    from kbbatch.journal import JOURNAL_NAME

    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "p0.jpg", seed=0)
    photo(folder / "p1.jpg", seed=1)
    run_folder(folder, out, quick_preset, FAST, False)
    trimmed = tmp_path / "trimmed.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(out / "p0.mp4"),
                    "-t", "0.5", "-c", "copy", "-movflags", "+faststart", str(trimmed)],
                   check=True)
    assert read_clip_mark(trimmed) == read_clip_mark(out / "p0.mp4")  # the edit kept it
    trimmed.replace(out / "p0.mp4")
    edit = (out / "p0.mp4").read_bytes()
    whole = (out / "p1.mp4").read_bytes()
    (out / "p1.mp4").write_bytes(whole[: len(whole) // 2])  # a copy that stopped
    assert read_clip_mark(out / "p1.mp4") is not None
    for journal_file in out.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    report = run_folder(folder, out, quick_preset, FAST, False)
    assert {Path(r.source).name: r.status for r in report.results} == {
        "p0.jpg": "skipped", "p1.jpg": "done"}
    assert len((out / "p1.mp4").read_bytes()) == len(whole) // 2  # kept, the clip beside it
    again = run_folder(folder, out, quick_preset, FAST, False, force=True)
    [p0] = [r for r in again.results if Path(r.source).name == "p0.jpg"]
    assert p0.status == "done" and Path(p0.output).name != "p0.mp4"
    assert (out / "p0.mp4").read_bytes() == edit


def test_clips_whose_journal_was_deleted_are_known_by_their_mark_not_made_again(
        tmp_path, quick_preset):
    """With the journal gone (deleted, the folder copied without it) every clip was taken for
    a file of the user's and made again beside itself under a content name. A clip's mark
    (the photo's sha256 and settings, in its metadata) says whose it is: kept, recorded, up
    to date. A file without it, or with another photo's, is still the user's."""
    from kbbatch.encode import clip_mark, read_clip_mark
    from kbbatch.fingerprint import file_sha256
    from kbbatch.journal import JOURNAL_NAME

    folder, out = tmp_path / "in", tmp_path / "out"
    for index in range(3):
        photo(folder / f"p{index}.jpg", seed=index)
    run_folder(folder, out, quick_preset, FAST, False)
    made = {name: (out / name).read_bytes() for name in visible_clips(out)}
    mark = read_clip_mark(out / "p0.mp4")
    assert mark is not None and mark[0] == file_sha256(folder / "p0.jpg")
    assert clip_mark(*mark).encode() in made["p0.mp4"]
    for journal_file in out.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    (out / "p1.mp4").write_bytes(made["p2.mp4"])  # another photo's clip at p1's name
    (out / "p2.mp4").unlink()
    os.mkfifo(out / "p2.mp4")  # no mark, and read it would block the batch for good
    report = run_folder(folder, out, quick_preset, FAST, False)
    by_name = {Path(r.source).name: r for r in report.results}
    assert by_name["p0.jpg"].status == "skipped"
    assert "p0.mp4: made by kbbatch from this photo with these settings" in by_name[
        "p0.jpg"].note
    assert by_name["p1.jpg"].status == by_name["p2.jpg"].status == "done"
    assert (out / "p0.mp4").read_bytes() == made["p0.mp4"]
    assert (out / "p1.mp4").read_bytes() == made["p2.mp4"]
    assert stat.S_ISFIFO((out / "p2.mp4").stat().st_mode)
    assert len(visible_clips(out)) == 5  # p1 and p2 made under names of their own
    again = run_folder(folder, out, quick_preset, FAST, False)
    assert [r.status for r in again.results] == ["skipped"] * 3
    assert not any(r.note for r in again.results)
    # The journal lost once more: the clips under content names are known too (p1's and p2's
    # were made again beside themselves, under a second content name).
    named = {Path(r.source).name: Path(r.output).name for r in again.results}
    for journal_file in out.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    again = run_folder(folder, out, quick_preset, FAST, False)
    assert [r.status for r in again.results] == ["skipped"] * 3
    assert {Path(r.source).name: Path(r.output).name for r in again.results} == named
    assert named["p1.jpg"] != "p1.mp4" and "made by kbbatch" in again.results[1].note
    assert len(visible_clips(out)) == 5
    # Other settings: the clip is not up to date. Without the journal's record of its size,
    # an edit of it saved in place (which may keep its metadata) cannot be told from it: it
    # is kept, and the new clip made beside it.
    for journal_file in out.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    report = run_folder(folder, out, with_overrides(quick_preset, duration_s=0.8), FAST, False)
    [p0] = [r for r in report.results if Path(r.source).name == "p0.jpg"]
    assert p0.status == "done" and Path(p0.output).name.startswith("p0.")
    assert (out / "p0.mp4").read_bytes() == made["p0.mp4"]
    # said as what it is, not as another photo's or a file of the user's
    assert "p0.mp4, its clip of other settings, is kept" in p0.note, p0.note


def test_force_after_the_journal_was_lost_says_what_the_kept_clip_is(tmp_path, quick_preset):
    """The clip of these very settings, adopted by its mark and made again beside itself by
    --force, was called "another photo's or a file kbbatch did not write"."""
    folder, out = tmp_path / "in", tmp_path / "out"
    photo(folder / "a.jpg", seed=1)
    run_folder(folder, out, quick_preset, FAST, False)
    made = (out / "a.mp4").read_bytes()
    for journal_file in out.glob(JOURNAL_NAME + "*"):
        journal_file.unlink()
    [result] = run_folder(folder, out, quick_preset, FAST, False, force=True).results
    assert result.status == "done" and Path(result.output).name.startswith("a.")
    assert Path(result.output).name != "a.mp4" and (out / "a.mp4").read_bytes() == made
    assert "a.mp4, its clip of these settings, is kept" in result.note, result.note
    assert "another photo's" not in result.note


def test_a_run_that_fails_at_every_photo_leaves_the_clips_there_up_to_date(tmp_path):
    """A run with a preset too wide for the photos failed at each one and wrote over the
    records of their clips, still on disk: the next run with the clips' own preset made
    every clip again (hours, on a large folder), and `status` counted none done."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg")):
        Image.fromarray(textured_image(180, 320, seed)).save(photos / name)
    output = tmp_path / "out"
    small = with_overrides(load_preset("preview"), width_px=160, height_px=90, duration_s=0.4)
    too_wide = with_overrides(small, width_px=8192, height_px=16)
    options = ClipOptions(depth=DepthOptions(backend="ramp"), threads=1)

    def run(preset):
        return run_folder(photos, output, preset, options, show_progress=False)

    assert [r.status for r in run(small).results] == ["done", "done"]
    made = {p.name: p.stat().st_mtime_ns for p in output.glob("*.mp4")}
    for _ in range(2):  # twice: the second attempt keeps what the first kept
        assert [r.status for r in run(too_wide).results] == ["failed", "failed"]
    assert [r.status for r in run(small).results] == ["skipped", "skipped"]
    assert {p.name: p.stat().st_mtime_ns for p in output.glob("*.mp4")} == made
    journal = Journal(output, read_only=True)
    try:
        assert journal.counts()["done"] == 2
    finally:
        journal.close()
    # a clip changed since (cut short) is no longer the one kept: made again
    (output / "a.mp4").write_bytes((output / "a.mp4").read_bytes()[:1000])
    assert [r.status for r in run(too_wide).results] == ["failed", "failed"]
    assert [r.status for r in run(small).results] == ["done", "skipped"]
    # a file of the user's saved over the kept clip after a failed run is never replaced
    assert [r.status for r in run(too_wide).results] == ["failed", "failed"]
    (output / "b.mp4").write_text("the user's notes")
    again = run(small).results
    assert [r.status for r in again] == ["skipped", "done"]
    assert (output / "b.mp4").read_text() == "the user's notes"
    assert Path(again[1].output).name != "b.mp4"
