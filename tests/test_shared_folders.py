"""Folders shared by several users of one machine: the journal's modes and side files.

The tests act as another user in a forked child (root only: the suite runs as root on the
development machines and in CI); the child runs kbbatch's own code, already imported, so it
needs no access to the interpreter's files.
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from kbbatch.journal import JOURNAL_NAME, Journal, JournalError

OTHER_UID = OTHER_GID = 65534
"""`nobody`: a user who owns nothing here."""

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="acting as another user needs root")


@pytest.fixture
def shared() -> Iterator[Path]:
    """A folder every user may write (pytest's own are root's, mode 700)."""
    folder = Path(tempfile.mkdtemp(prefix="kbbatch-shared-"))
    folder.chmod(0o777)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def as_other_user(action: Callable[[], str]) -> str:
    """action's result (or its error's words) in a child process of OTHER_UID."""
    read_end, write_end = os.pipe()
    child = os.fork()
    if child == 0:  # pragma: no cover - the child's own process
        os.close(read_end)
        try:
            os.setgroups([])
            os.setgid(OTHER_GID)
            os.setuid(OTHER_UID)
            words = action()
        except BaseException as error:  # noqa: BLE001 - reported to the parent
            words = f"{type(error).__name__}: {error}"
        os.write(write_end, words.encode())
        os._exit(0)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as reader:
        words = reader.read().decode()
    os.waitpid(child, 0)
    return words


def side_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != JOURNAL_NAME)


def test_a_journal_is_made_with_the_umasks_mode(shared):
    """SQLite made it 644 whatever the umask: in a group folder (umask 002) the clips were
    group-writable and the journal was not, so the next member's every clip failed."""
    previous = os.umask(0o002)
    try:
        Journal(shared / "out").close()
    finally:
        os.umask(previous)
    assert stat.S_IMODE((shared / "out" / JOURNAL_NAME).stat().st_mode) == 0o664


def test_a_journal_another_user_cannot_write_is_refused_at_once_leaving_nothing(shared):
    """It opened read-only: every clip of the run failed "attempt to write a readonly
    database" (up-to-date ones too), and it left side files of its own beside the journal,
    which then stopped the journal's owner too."""
    previous = os.umask(0o022)
    try:
        Journal(shared).close()  # root's, mode 644
    finally:
        os.umask(previous)
    words = as_other_user(lambda: str(Journal(shared)))
    assert words.startswith(JournalError.__name__), words
    assert f"{JOURNAL_NAME} belongs to root, mode 644, and this is nobody" in words, words
    assert side_files(shared) == []
    Journal(shared).close()  # its owner writes it as before


def test_looking_at_another_users_journal_leaves_no_files_behind(shared):
    """`kbbatch status` by a colleague left -wal and -shm files of theirs (mode 644), and the
    journal's owner could write it no more."""
    journal = Journal(shared)
    journal.start(shared / "a.jpg", "f", "s", "a.mp4", "c")
    journal.close()

    def look() -> str:
        other = Journal(shared, read_only=True)
        try:
            return str(other.counts())
        finally:
            other.close()

    assert "'running': 1" in as_other_user(look)
    assert side_files(shared) == []
    (shared / JOURNAL_NAME).chmod(0o600)  # a private one: said whose, not SQLite's words
    words = as_other_user(look)
    assert f"{JOURNAL_NAME}: job journal cannot be read: it belongs to root, mode 600, and " \
        "this is nobody" in words, words
    (shared / JOURNAL_NAME).chmod(0o644)
    journal = Journal(shared)
    journal.finish(shared / "a.jpg", "done", 1.0)
    assert journal.counts()["done"] == 1
    journal.close()


def test_another_users_partial_clip_in_a_sticky_folder_is_kept_without_a_crash(shared):
    """A sticky output folder (mode 1777) with a partial clip another user's killed run left:
    every later run crashed at its start with a PermissionError traceback."""
    from kbbatch.outputs import remove_partial_clips

    shared.chmod(0o1777)
    partial = shared / ".a.k3j9x2qa.part.mp4"
    partial.write_bytes(b"half a clip")
    assert as_other_user(lambda: repr(remove_partial_clips(shared))) == "[]"
    assert partial.exists()
    assert remove_partial_clips(shared) == [partial]  # its owner's run removes it


def test_another_users_photo_in_a_sticky_inbox_is_not_copied_into_done(shared):
    """The daemon's move fell back to a copy where the rename was refused: every start left
    one more copy of the photo in done/ (`x.jpg`, `x.1.jpg`, ...) and the photo in the inbox."""
    from kbbatch.watch import move_photo

    shared.chmod(0o1777)
    photo = shared / "bob.jpg"
    photo.write_bytes(b"a photo")
    done = shared / "done"
    done.mkdir(mode=0o777)
    done.chmod(0o777)
    words = as_other_user(lambda: repr(move_photo(photo, done / "bob.jpg")))
    assert words.startswith("PermissionError"), words
    assert photo.read_bytes() == b"a photo" and list(done.iterdir()) == []


def test_a_new_users_compiled_code_goes_where_it_will_stay(shared):
    """A new home has no ~/.cache yet: it was taken for unwritable, so the first run compiled
    every kernel into the temporary folder and the second, into ~/.cache/numba, again."""
    import kbbatch

    home = shared / "home"
    home.mkdir()
    assert kbbatch._writable(home / ".cache" / "numba", home)
    # a home that does not exist is no place to make one (root's service with HOME=/nonexistent)
    assert not kbbatch._writable(shared / "nonexistent" / ".cache" / "numba",
                                 shared / "nonexistent")


def test_a_compiled_code_folder_name_taken_by_another_user_gets_the_next_one(shared):
    """A service account with no writable home found its folder's name taken (another
    user's, or a stale uid's): every run compiled again into a new folder, left behind."""
    import kbbatch

    squatted = shared / f"kbbatch-numba-{OTHER_UID}"
    squatted.mkdir(mode=0o700)

    def choose() -> str:
        os.environ.pop("NUMBA_CACHE_DIR", None)
        os.environ.update(HOME="/nonexistent", TMPDIR=str(shared), XDG_CACHE_HOME="/nonexistent")
        tempfile.tempdir = None
        kbbatch._compiled_code_cache()
        return os.environ.get("NUMBA_CACHE_DIR", "")

    chosen = as_other_user(choose)
    assert chosen == str(shared / f"kbbatch-numba-{OTHER_UID}.1"), chosen
    assert as_other_user(choose) == chosen  # the next run's too
    assert sorted(p.name for p in shared.iterdir()) == [squatted.name, Path(chosen).name]


def test_a_manifest_lock_holds_across_users_and_leaves_no_file(shared, monkeypatch):
    """Each user's lock file was 0600, so another user's review never waited for a save in
    progress (and said so); and the files were never removed: hundreds piled up in /tmp."""
    from kbbatch.web import app
    from kbbatch.web.app import RequestError, manifest_lock

    shared.chmod(0o1777)  # as /tmp is
    monkeypatch.setattr(tempfile, "tempdir", str(shared))
    monkeypatch.setattr(app, "MANIFEST_LOCK_WAIT_S", 0.3)
    manifest = shared / "manifest.json"

    def try_to_save() -> str:
        try:
            with manifest_lock(manifest):
                return "saved"
        except RequestError as error:
            return f"refused: {error.message}"

    with manifest_lock(manifest):
        [lock] = shared.glob("kbbatch-manifest-*.lock")
        assert as_other_user(try_to_save) == \
            f"refused: {manifest}: another review is saving it (it holds {lock}); try again"
    assert list(shared.glob("kbbatch-manifest-*.lock")) == []
    assert as_other_user(try_to_save) == "saved"
    assert list(shared.glob("kbbatch-manifest-*.lock")) == []


def clip_in_sticky_folder(photos: Path, out: Path, preset, monkeypatch) -> bytes:
    """Root's clip of photos/a.jpg (made by a run with QUICK_OPTIONS) in out, then made a
    sticky folder every user may write, its journal too; returns the clip's bytes."""
    from PIL import Image

    from kbbatch.batch import run_folder

    from .conftest import textured_image

    monkeypatch.setenv("KBBATCH_MODELS", str(photos.parent / "no-models"))  # root's: unread
    Image.fromarray(textured_image(180, 320)).save(photos / "a.jpg")
    assert run_folder(photos, out, preset, quick_options(), False).results[0].status == "done"
    out.chmod(0o1777)
    for file in out.iterdir():
        file.chmod(0o666)
    return (out / "a.mp4").read_bytes()


def quick_options(planner: str = "center"):
    from kbbatch.depth import DepthOptions
    from kbbatch.pipeline import ClipOptions

    return ClipOptions(planner=planner, depth=DepthOptions(backend="ramp"), threads=1)


def test_another_users_clip_in_a_sticky_folder_is_refused_before_the_render(
        shared, quick_preset, monkeypatch):
    """A sticky group output folder: a colleague's `--force` run rendered the photo, then
    failed with a raw PermissionError at the rename, and the owner's good clip was recorded
    failed (her next run made it again)."""
    from kbbatch.batch import run_folder

    photos, out = shared / "in", shared / "out"
    photos.mkdir(mode=0o755)
    clip = clip_in_sticky_folder(photos, out, quick_preset, monkeypatch)
    options = quick_options()

    def force() -> str:
        result = run_folder(photos, out, quick_preset, options, False, force=True).results[0]
        return f"{result.status}: {result.error}"

    words = as_other_user(force)
    assert words == (f"failed: {photos / 'a.jpg'}: {out / 'a.mp4'}: belongs to root in a "
                     "sticky folder (mode "
                     "1777): only its owner can replace it; kept"), words
    assert (out / "a.mp4").read_bytes() == clip
    journal = Journal(out, read_only=True)
    assert journal.counts()["done"] == 1
    journal.close()


def test_a_journal_that_cannot_be_made_says_why(shared):
    private = shared / "roots"
    private.mkdir(mode=0o755)
    words = as_other_user(lambda: str(Journal(private)))
    assert words == (f"JournalError: {private / JOURNAL_NAME}: job journal cannot be made "
                     "(Permission denied)"), words


def test_another_users_report_in_a_sticky_folder_sends_this_runs_to_the_other_name(
        shared, quick_preset, monkeypatch):
    """A shared sticky output folder: the run after another user's made its clips, then
    could not replace that user's report, and exited 1 saying only "Operation not
    permitted"."""
    from PIL import Image

    from kbbatch.batch import OTHER_REPORT_NAME, REPORT_NAME, run_folder
    from kbbatch.depth import DepthOptions
    from kbbatch.pipeline import ClipOptions

    from .conftest import textured_image

    monkeypatch.setenv("KBBATCH_MODELS", str(shared / "no-models"))
    options = ClipOptions(planner="center", depth=DepthOptions(backend="ramp"), threads=1)
    out = shared / "out"
    out.mkdir(mode=0o777)
    out.chmod(0o1777)
    for name, seed in (("roots", 0), ("nobodys", 1)):
        (shared / name).mkdir(mode=0o755)
        Image.fromarray(textured_image(180, 320, seed)).save(shared / name / f"{name}.jpg")
    previous = os.umask(0)  # a journal every user may write
    try:
        run_folder(shared / "roots", out, quick_preset, options, False)
    finally:
        os.umask(previous)
    ours = (out / REPORT_NAME).read_bytes()

    def run() -> str:
        report = run_folder(shared / "nobodys", out, quick_preset, options, False)
        return f"{[r.status for r in report.results]} {report.unwritten}"

    assert as_other_user(run) == "['done'] None"
    assert (out / REPORT_NAME).read_bytes() == ours
    assert '"nobodys.jpg"' not in ours.decode()
    assert "nobodys.jpg" in (out / OTHER_REPORT_NAME).read_text()


def test_a_new_file_takes_the_folders_default_acl(shared):
    """A folder shared through a default ACL (group write for its users): the journal got
    it, while clips and reports came out group read-only, the umask applied by hand."""
    import struct

    from kbbatch.images import atomic_output

    read_write, read = 6, 4
    entries = ((0x01, read_write, 0xFFFFFFFF), (0x02, read_write, OTHER_UID),  # owner, nobody
               (0x04, read, 0xFFFFFFFF), (0x10, read_write, 0xFFFFFFFF),  # group, mask
               (0x20, read, 0xFFFFFFFF))  # others
    acl = struct.pack("<I", 2) + b"".join(struct.pack("<HHI", *e) for e in entries)
    try:
        os.setxattr(shared, "system.posix_acl_default", acl)
    except OSError as error:
        pytest.skip(f"no POSIX ACLs on this file system ({error.strerror})")
    previous = os.umask(0o022)
    try:
        with atomic_output(shared / "a.mp4", ".mp4") as temp_path:
            temp_path.write_bytes(b"a clip")
    finally:
        os.umask(previous)
    # with an ACL, the group bits of the mode are its mask: nobody may write the clip
    assert stat.S_IMODE((shared / "a.mp4").stat().st_mode) & 0o060 == 0o060
    assert as_other_user(lambda: str((shared / "a.mp4").open("ab").write(b"!"))) == "1"


def test_the_daemon_refuses_another_users_clip_in_a_sticky_outbox_before_the_render(
        shared, quick_preset, monkeypatch):
    """The batch refused it before the render; the daemon, naming clips by its own copy of
    the rule, started the render (and failed with a raw PermissionError at the rename)."""
    import json
    import threading

    from kbbatch.watch import InboxTracker, JobRunner, WatchSettings

    inbox, out = shared / "inbox", shared / "out"
    inbox.mkdir(mode=0o777)
    inbox.chmod(0o777)
    clip = clip_in_sticky_folder(inbox, out, quick_preset, monkeypatch)
    other_settings = quick_options(planner="auto")

    def daemon_takes_the_photo() -> str:
        journal = Journal(out)
        runner = JobRunner(WatchSettings(inbox, out, quick_preset, other_settings), journal,
                           False, out / "failed", lambda path, renamed: None)
        tracker = InboxTracker(inbox, 0.0)
        tracker.notice(inbox / "a.jpg", renamed=True)
        tracker.collect_events()
        runner.submit_ready(tracker, other_settings, threading.Event())
        journal.close()
        return f"in flight: {len(runner.in_flight)}"

    assert as_other_user(daemon_takes_the_photo) == "in flight: 0"
    assert (out / "a.mp4").read_bytes() == clip
    [report] = (inbox / "failed").glob("a*.error.json")
    assert json.loads(report.read_text())["error"] == (
        f"{inbox / 'a.jpg'}: {out / 'a.mp4'}: belongs to root in a sticky folder (mode 1777): "
        "only its owner can replace it; kept")
    assert (inbox / "failed" / "a.jpg").is_file()
    journal = Journal(out, read_only=True)
    assert journal.counts()["done"] == 1
    journal.close()


def test_status_counts_the_inbox_of_the_daemon_that_started_last_in_a_sticky_outbox(shared):
    """A colleague's daemon could not replace the first user's note of its inbox in a sticky
    outbox: `kbbatch status` went on counting the first user's inbox, not the one in use."""
    from PIL import Image

    from kbbatch.watch import note_inbox, status_lines

    out, first, second = shared / "out", shared / "first", shared / "second"
    for folder in (out, first, second):
        folder.mkdir()
        folder.chmod(0o1777 if folder == out else 0o777)
    Image.new("RGB", (64, 48)).save(first / "root.jpg")
    for name in ("b1.jpg", "b2.jpg"):
        Image.new("RGB", (64, 48)).save(second / name)
    Journal(out).close()
    (out / JOURNAL_NAME).chmod(0o666)
    note_inbox(out, first, None)
    assert f"WAITING 1 photo(s) in the inbox {first}" in "\n".join(status_lines(out))
    assert as_other_user(lambda: repr(note_inbox(out, second, None))) == "None"
    assert f"WAITING 2 photo(s) in the inbox {second}" in "\n".join(status_lines(out))
    note_inbox(out, first, None)  # the first user's daemon again
    assert f"WAITING 1 photo(s) in the inbox {first}" in "\n".join(status_lines(out))
