"""A persistent job journal (SQLite in the output folder): what was done, with which settings.

The daemon and the one-shot batch both use it, so a restart (even after kill -9) finishes
interrupted work without redoing what is complete, a re-run skips up-to-date clips, and a clip
name is never given to a second, different photo. Jobs are keyed by the photo's absolute path
(the daemon updates it when it moves the photo to done/ or failed/).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import re
import sqlite3
import stat
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from urllib.parse import quote_from_bytes, unquote_to_bytes

JOURNAL_NAME = ".kbbatch-journal.sqlite"
STATES = ("queued", "running", "done", "failed")
DONE_FOLDER = "done"
"""Where the daemon moves a photo it made a clip of (beside it in its inbox); its job follows
it there."""
CONTENT_NAME_HEX = 8
"""Hex digits of the photo's sha256 in a clip named by content (`IMG_0001.3fa2c9e1.mp4`)."""

COLUMNS = (("source", "TEXT PRIMARY KEY"), ("fingerprint", "TEXT NOT NULL"),
           ("settings", "TEXT NOT NULL"), ("state", "TEXT NOT NULL"), ("output", "TEXT"),
           ("error", "TEXT"), ("attempts", "INTEGER NOT NULL DEFAULT 0"), ("seconds", "REAL"),
           ("updated", "REAL NOT NULL"), ("content", "TEXT"), ("clip", "TEXT"),
           ("folder", "TEXT"), ("taken", "TEXT"), ("kept_settings", "TEXT"),
           ("kept_clip", "TEXT"))


UNDECODABLE_PREFIX = "//bytes:"
"""Marks a stored path or clip name whose bytes are not UTF-8 (a Latin-1 name from a zip file):
SQLite keeps only UTF-8 text, so such a name is stored percent-encoded after this prefix, which
no resolved absolute path and no file name can begin with."""


def photo_key(photo: Path) -> Path:
    """The path a photo's job is kept under: its folder as the file system resolves it
    (links and `..` followed), then its own name (a linked photo stays itself). By the path
    as typed, a folder run through a link and by its own name was two folders (every clip
    made again at each switch), and a link moved to another card made that card's photos
    edits of the first card's, replacing their clips."""
    return folder_key(photo.parent) / photo.name


def folder_key(folder: Path) -> Path:
    """A photo folder as the journal's keys name it (photo_key)."""
    return Path(os.path.realpath(folder))


GONE_MARK = " (removed from the inbox)"
"""Added to the journal's record of a photo deleted from its folder (the inbox, or a batch's)
after its clip was begun (worded for the inbox, as journals already hold it)."""


def aside_name(name: str, folder: str, content: str) -> str:
    """Where the record of a photo (of these bytes) of another directory at the same path
    (folder: its folder_id) is kept: its clip stays its own, and comes back with that
    directory, at this path or another."""
    return f"{name} (of folder {folder}, {content[:CONTENT_NAME_HEX]})"


_ASIDE = re.compile(r" \(of folder \d+:\d+, [0-9a-f]+\)$")


def in_folder(source: Path, folder: Path) -> bool:
    """Whether a job's photo lies in this folder (its key), also by another spelling: a
    journal of an earlier version kept the folder as typed (through a link)."""
    if source.parent == folder:
        return True
    try:
        return os.path.samefile(source.parent, folder)
    except OSError:  # that spelling leads nowhere now
        return False


def _stored(name: str | Path | None) -> str | None:
    """A path or file name as the journal keeps it (reversibly, see UNDECODABLE_PREFIX)."""
    if name is None:
        return None
    text = str(name)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return UNDECODABLE_PREFIX + quote_from_bytes(os.fsencode(text), safe="/")
    return text


def _restored(stored: str | None) -> str | None:
    if stored is None or not stored.startswith(UNDECODABLE_PREFIX):
        return stored
    return os.fsdecode(unquote_to_bytes(stored[len(UNDECODABLE_PREFIX):]))


def _message(text: str | None) -> str | None:
    """An error message as UTF-8 text: undecodable bytes of a name shown as escapes."""
    if text is None:
        return None
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


class JournalError(OSError):
    """The journal cannot be read or written (a full disk, a read-only or broken file)."""

    disk_full = False
    """Whether its disk had no room (SQLite's SQLITE_FULL): every write after would fail too."""


@dataclass(frozen=True)
class Job:
    source: str  # absolute path of the photo
    fingerprint: str
    settings: str
    state: str
    output: str | None  # clip file name in the output folder
    error: str | None
    attempts: int
    seconds: float | None
    updated: float
    content: str | None  # sha256 of the photo's bytes
    clip: str | None  # size and mtime of the finished clip, to notice a truncated one
    folder: str | None = None  # folder_id of the photo's folder when it was started
    taken: str | None = None  # images.capture_time of the photo then
    kept_settings: str | None = None  # the settings and clip of the done clip still at the
    kept_clip: str | None = None  # output while a later attempt is unfinished (restore_kept)

    @property
    def name(self) -> str:
        return Path(self.source).name

    def of_another_folder(self, content: str, taken: str | None) -> bool:
        """Made (or begun), of other bytes taken at another moment (EXIF), from a photo of the
        same path in another directory than the one there now: another card's photo, not an
        edit (its clip was replaced). Both are needed: a folder remounted or restored is a new
        directory too, and its edited photos keep the moment they were taken."""
        return (self.content not in (None, content)  # also unfinished: its clip is there
                and None not in (self.folder, self.taken, taken) and self.taken != taken
                and folder_id(Path(self.source).parent) not in (None, self.folder))

    def made_from_other_bytes(self, name: str, content: str, output: Path) -> bool:
        """Whether making `name` again now replaces a finished clip of this job made from other
        bytes (an edit, or another photo saved under the name: one import folder for every
        card), which the user is told of once the new clip is made."""
        return (self.state == "done" and self.output == name
                and self.content not in (None, content) and output.is_file())


ADOPTED_ATTEMPTS = 0
"""The attempts of a done job that no run made: a clip adopted by its mark
(Journal.adopt_marked_clip). A job made by a run has at least one."""


def folder_id(folder: Path) -> str | None:
    """The directory a folder path is now (device and inode): a folder made again at the same
    path (an ingest folder renamed aside and a new card copied into a new one) is another,
    and its photos are not edits of the first one's."""
    try:
        facts = os.stat(folder)
    except OSError:
        return None
    return f"{facts.st_dev}:{facts.st_ino}"


def source_fingerprint(path: Path) -> str:
    """Size and modification time: a changed photo (or clip) is a new one."""
    stat = path.stat()
    return f"{stat.st_size}:{stat.st_mtime_ns}"


LOW_SPACE_BYTES = 1 << 20
"""Below this much free space, a journal error says how full the disk is."""


def free_space_note(folder: Path) -> str:
    import shutil

    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return ""
    return f"; the disk is full ({free // 1024} KB free)" if free < LOW_SPACE_BYTES else ""


DAMAGE_WORDS = ("not a database", "malformed")
"""What SQLite says of a journal file that is damaged (not merely locked or on a full disk)."""


def _damage_advice(error: sqlite3.Error) -> str:
    """The way forward from a damaged journal: it stopped every run into its folder, and the
    error said only "file is not a database"."""
    if not any(words in str(error) for words in DAMAGE_WORDS):
        return ""
    return ("; it is damaged: move it aside and run again (the clips in the folder are kept; "
            "a photo whose clip name is taken gets one named by its content)")


def _guarded(method):
    """Turn SQLite's errors into a JournalError that names the journal and the reason."""
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except sqlite3.Error as error:
            verb = "read" if getattr(self, "read_only", False) else "written"
            # a run that wrote it while it was looked at as immutable: not damage
            advice = "" if getattr(self, "immutable", False) else _damage_advice(error)
            failure = JournalError(f"{self.path}: job journal cannot be {verb} ({error})"
                                   f"{free_space_note(self.path.parent)}{advice}")
            failure.disk_full = getattr(error, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
            raise failure from error
    wrapper.__doc__ = method.__doc__
    return wrapper


def _side_files(path: Path) -> tuple[Path, Path]:
    """SQLite's write-ahead log and shared memory beside a journal in WAL mode."""
    return path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")


def _unwritable(path: Path) -> str | None:
    """Why this user cannot write the journal or its side files, if so. SQLite opened such a
    journal read-only and every clip failed "attempt to write a readonly database"
    (up-to-date ones too, and the run's report said so), and it left side files of this
    user's, which its own owner could then not write either."""
    for file in (path, *_side_files(path)):
        if not os.path.lexists(file) or os.access(file, os.W_OK):
            continue
        try:
            facts = file.stat()
        except OSError:
            continue
        return (f"{file.name} belongs to {user_name(facts.st_uid)}, mode "
                f"{stat.S_IMODE(facts.st_mode):o}, and this is {user_name(os.getuid())}: "
                "run kbbatch on this folder as its owner, or give the users who share it a "
                "group of theirs with write access to its files (chgrp, chmod g+w; then "
                "umask 002 keeps new files so)")
    return None


def user_name(uid: int) -> str:
    """A user's login name, for messages about whose file is in the way."""
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"user {uid}"


class Journal:
    @_guarded
    def __init__(self, folder: Path, read_only: bool = False) -> None:
        """read_only: for looking only (`kbbatch status`), which must work on a full disk."""
        self.path = folder / JOURNAL_NAME
        self.read_only = read_only
        self.immutable = False
        if read_only:
            self.connection = self._read_only_connection()
            self._present = self._columns()
            return
        folder.mkdir(parents=True, exist_ok=True)
        refusal = _unwritable(self.path)
        if refusal:  # before SQLite leaves files of this user's beside it: see _unwritable
            raise JournalError(f"{self.path}: job journal cannot be written ({refusal})")
        try:  # made as the clips are: the umask's mode
            os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            pass
        except OSError as error:
            raise JournalError(f"{self.path}: job journal cannot be made "
                               f"({error.strerror or error})") from error
        self.connection = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        self.connection.execute("PRAGMA journal_mode=WAL")
        self.connection.execute("PRAGMA synchronous=FULL")
        self.connection.execute("CREATE TABLE IF NOT EXISTS jobs ("
                                + ", ".join(f"{n} {t}" for n, t in COLUMNS) + ")")
        for name, kind in COLUMNS:  # journals written by earlier versions
            if name not in self._columns():
                self.connection.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")
        self._present = self._columns()
        # which output folder this is, wherever it is moved (RunReport.journal_id); without
        # it (a full disk) reports are known by the folder they name alone
        with contextlib.suppress(sqlite3.OperationalError):
            self.connection.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY,"
                                    " value TEXT)")
            self.connection.execute("INSERT OR IGNORE INTO meta VALUES ('id', ?)",
                                    (uuid.uuid4().hex,))
        # looked up per photo (Journal.owners, Journal.job_of): a scan each in a large journal;
        # only a speed-up, so a full disk that cannot take it is no reason to stop
        with contextlib.suppress(sqlite3.OperationalError):
            self.connection.execute("CREATE INDEX IF NOT EXISTS jobs_output ON jobs (output)")
            self.connection.execute("CREATE INDEX IF NOT EXISTS jobs_content ON jobs (content)")

    def _read_only_connection(self) -> sqlite3.Connection:
        uri = self.path.absolute().as_uri()
        if os.path.lexists(self.path) and not os.access(self.path, os.R_OK):
            facts = self.path.stat()  # SQLite said "unable to open database file"
            raise JournalError(f"{self.path}: job journal cannot be read: it belongs to "
                                  f"{user_name(facts.st_uid)}, mode "
                                  f"{stat.S_IMODE(facts.st_mode):o}, and this is "
                                  f"{user_name(os.getuid())}")
        if (not any(os.path.lexists(f) for f in _side_files(self.path))
                and _unwritable(self.path)):
            # Another user's journal, not written now: the file is the whole journal, looked
            # at as immutable, so that SQLite makes no side files (another user's `kbbatch
            # status` left them, owned by that user, and the journal's own owner could write
            # it no more). The journal's owner and group look through its log, as before: an
            # immutable look is not safe from a run that starts meanwhile.
            self.immutable = True
            return sqlite3.connect(f"{uri}?mode=ro&immutable=1", uri=True, timeout=30,
                                   isolation_level=None)
        connection = sqlite3.connect(f"{uri}?mode=ro", uri=True, timeout=30,
                                     isolation_level=None)
        try:
            connection.execute("SELECT COUNT(*) FROM jobs").fetchone()
            return connection
        except sqlite3.OperationalError:
            wal = self.path.with_name(self.path.name + "-wal")
            if os.path.exists(wal) and os.path.getsize(wal) > 0:
                raise
            connection.close()
        # No write-ahead log to read, so the file is the whole journal: opened as immutable,
        # SQLite makes no shared-memory file (-shm) for it, which a full disk refused.
        return sqlite3.connect(f"{uri}?mode=ro&immutable=1", uri=True, timeout=30,
                               isolation_level=None)

    def identity(self) -> str | None:
        """The id made with the journal (None for one of an earlier version only looked at)."""
        try:
            row = self.connection.execute("SELECT value FROM meta WHERE key = 'id'").fetchone()
        except sqlite3.OperationalError:
            return None
        return row[0] if row else None

    def _columns(self) -> set[str]:
        return {row[1] for row in self.connection.execute("PRAGMA table_info(jobs)")}

    def close(self) -> None:
        self.connection.close()

    def _select(self, where: str = "", args: tuple = ()) -> list[Job]:
        # a journal of an earlier version, only looked at (`kbbatch status`), lacks columns
        names = ", ".join(n if n in self._present else "NULL" for n, _ in COLUMNS)
        rows = self.connection.execute(f"SELECT {names} FROM jobs {where} ORDER BY source", args)
        return [replace(job, source=_restored(job.source), output=_restored(job.output))
                for job in (Job(*row) for row in rows)]

    @_guarded
    def get(self, source: Path) -> Job | None:
        jobs = self._select("WHERE source = ?", (_stored(source),))
        return jobs[0] if jobs else None

    @_guarded
    def jobs(self, state: str | None = None) -> list[Job]:
        return self._select("WHERE state = ?", (state,)) if state else self._select()

    @_guarded
    def start(self, source: Path, fingerprint: str, settings: str, output: str,
              content: str, taken: str | None = None) -> None:
        previous = self.get(source)
        attempts = previous.attempts if previous and previous.fingerprint == fingerprint else 0
        kept: tuple[str | None, str | None] = (None, None)  # the clip this attempt replaces
        if previous and previous.output == output and previous.content == content:
            kept = ((previous.settings, previous.clip) if previous.state == "done"
                    else (previous.kept_settings, previous.kept_clip))
        self.connection.execute(
            "INSERT OR REPLACE INTO jobs (source, fingerprint, settings, state, output, error,"
            " attempts, seconds, updated, content, clip, folder, taken, kept_settings,"
            " kept_clip) VALUES (?, ?, ?, 'running', ?, NULL, ?, NULL, ?, ?, NULL, ?, ?, ?, ?)",
            (_stored(source), fingerprint, settings, _stored(output), attempts + 1, time.time(),
             content, folder_id(Path(source).parent), taken, *kept),
        )

    @_guarded
    def restore_kept(self, source: Path, settings: tuple[str, ...], output: Path,
                     content: str) -> bool:
        """An unfinished attempt's record (failed, or stopped) back to the done clip it was
        to replace, where that clip is still at its name, of its size, and of one of these
        settings: a run with another preset that failed at every photo wrote over the records
        of the clips still there, and the next run with their settings made them all again.
        Whether it was restored."""
        job = self.get(source)
        if (job is None or job.state == "done" or job.kept_settings not in settings
                or job.output != output.name or job.content != content):
            return False
        try:
            size = output.stat().st_size
        except OSError:
            return False
        if clip_size(job.kept_clip) != size:
            return False
        from kbbatch.encode import read_clip_mark

        if read_clip_mark(output) != (content, job.kept_settings):  # a file of that size
            return False
        self.connection.execute(
            "UPDATE jobs SET state = 'done', settings = kept_settings, clip = kept_clip,"
            " error = NULL, kept_settings = NULL, kept_clip = NULL, updated = ?"
            " WHERE source = ?", (time.time(), _stored(source)))
        return True

    @_guarded
    def finish(self, source: Path, state: str, seconds: float, error: str | None = None,
               clip: str | None = None, content: str | None = None) -> None:
        """content: the sha256 of the bytes the clip was made from, when known (they are the
        job's unless the photo was replaced between its start and its read)."""
        self.connection.execute(
            "UPDATE jobs SET state = ?, seconds = ?, error = ?, clip = ?, updated = ?,"
            " content = COALESCE(?, content) WHERE source = ?",
            (state, seconds, _message(error), clip, time.time(), content, _stored(source)))
        if state == "done":  # the clip kept is replaced
            self.connection.execute("UPDATE jobs SET kept_settings = NULL, kept_clip = NULL"
                                     " WHERE source = ?", (_stored(source),))

    @_guarded
    def moved(self, source: Path, destination: Path) -> None:
        """The photo now lies at destination (done/ or failed/); its clip stays its own."""
        with self.connection:
            self.connection.execute("DELETE FROM jobs WHERE source = ?",
                                    (_stored(destination),))
            self.connection.execute("UPDATE jobs SET source = ? WHERE source = ?",
                                    (_stored(destination), _stored(source)))

    @_guarded
    def place(self, source: Path, content: str, taken: str | None) -> None:
        """Where a photo found up to date is now (its folder's folder_id) and when it was
        taken, for a record of its bytes that lacks them or holds another place: records of
        an earlier version, adopted clips and folders moved since were never set aside as
        another card's (Job.of_another_folder), and day 1's clips were replaced."""
        self.connection.execute(
            "UPDATE jobs SET folder = ?, taken = COALESCE(?, taken) WHERE source = ?"
            " AND content = ? AND (folder IS NOT ? OR taken IS NULL)",
            (folder_id(source.parent), taken, _stored(source), content,
             folder_id(source.parent)))

    @_guarded
    def set_aside(self, source: Path) -> None:
        """The record of a photo of another directory at this path (Job.of_another_folder)
        goes aside (aside_name), so that this photo is no edit of it."""
        job = self.get(source)
        if job is not None and job.folder is not None and job.content is not None:
            self.moved(source, source.with_name(aside_name(source.name, job.folder,
                                                           job.content)))

    @_guarded
    def job_of(self, source: Path, content: str) -> Job | None:
        """This photo's job, with its records under other spellings of its folder (through a
        link, a bind mount, a journal of a version that kept paths as typed) settled: the
        latest one kept under this path, the rest dropped. Without it a folder run by two
        spellings made every clip again at each switch. Only records of the same bytes count:
        a link since pointed at another card holds other photos of the same names, whose
        clips are not this photo's. A record of the same bytes and name whose photo is no
        longer where it was is this photo's too (its folder moved or renamed): left under the
        old path, an edit after the move made a second clip beside the stale one."""
        own = self.get(source)
        for job in self._select("WHERE content = ? AND source != ?",
                                (content, _stored(source))):
            other = Path(job.source)
            if own is None and other.name == aside_name(
                    source.name, folder_id(source.parent) or "", content):
                self.moved(other, source)  # its directory is back (here, or moved)
                own = self.get(source)
                continue
            if other.name != source.name:
                continue
            if not in_folder(other, source.parent):
                if own is None and not os.path.lexists(other):
                    self.moved(other, source)
                    own = self.get(source)
                continue
            if own is None or job.updated > own.updated:
                self.moved(other, source)
                own = self.get(source)
            else:
                self.forget(other)
        return own

    @_guarded
    def photo_gone(self, source: Path, folder: Path) -> None:
        """An unfinished job whose photo was deleted: nothing is left to make. A clip of an
        earlier make still at its name stays the photo's (done, with settings unknown, so the
        photo, put back, is made again under that name rather than a second one beside it);
        without one the job is forgotten."""
        job = self.get(source)
        if job is None:
            return
        output = folder / job.output if job.output else None
        if output is None or not output.is_file():
            self.forget(source)
            return
        self.connection.execute(
            "UPDATE jobs SET state = 'done', settings = '', error = NULL, clip = ?, updated = ?"
            " WHERE source = ?", (source_fingerprint(output), time.time(), _stored(source)))

    @_guarded
    def done_photo_removed(self, source: Path) -> bool:
        """A photo whose clip was made is deleted from its folder: its record (and its clip)
        moves aside under GONE_MARK, so that a different photo saved later under the same name
        is a photo of its own, with a clip of its own name, not an edit of the deleted one
        that replaces its clip. (The same bytes put back are still found up to date, by
        content.) Whether anything was moved aside."""
        job = self.get(source)
        if job is None or job.state != "done" or source.name.endswith(GONE_MARK) \
                or _ASIDE.search(source.name):
            return False
        self.moved(source, source.with_name(f"{source.name}{GONE_MARK}"))
        return True

    @_guarded
    def forget(self, source: Path) -> None:
        """The photo is gone (deleted by its owner before its clip was made)."""
        self.connection.execute("DELETE FROM jobs WHERE source = ?", (_stored(source),))

    @_guarded
    def owners(self, output: str) -> list[Job]:
        """Jobs whose clip has this file name."""
        return self._select("WHERE output = ?", (_stored(output),))

    @_guarded
    def counts(self) -> dict[str, int]:
        rows = self.connection.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state")
        return {state: 0 for state in STATES} | dict(rows.fetchall())

    @_guarded
    def adopt_marked_clip(self, source: Path, fingerprint: str, settings: tuple[str, ...],
                          content: str, folder: Path, preferred: str) -> str | None:
        """Record as done a clip of this photo's bytes and one of these settings, at a name
        clip_name gives it (preferred, or a content name beside another's clip or a file of
        the user's), that the journal knows nothing of (the journal deleted, the folder
        copied without it): kbbatch's by the mark in the file (encode.clip_mark); its name,
        or None. It was taken for a file of the user's, and every clip was made again beside
        itself under a content name. A file without the mark, or another photo's or
        settings', is left as it was."""
        from kbbatch.encode import is_whole_clip, read_clip_mark

        if self.job_of(source, content) is not None:
            return None
        for name in self._names(source, content, preferred):
            output = folder / name
            if not os.path.lexists(output):
                return None  # clip_name gives no name past the first free one
            if self.owners(name):
                continue
            mark = read_clip_mark(output)
            if mark is None or mark[0] != content or mark[1] not in settings:
                continue
            try:
                clip = source_fingerprint(output)
            except OSError:  # deleted meanwhile
                return None
            if not is_whole_clip(output):  # a copy that stopped keeps the mark at its start
                continue
            self.connection.execute(
                "INSERT OR REPLACE INTO jobs (source, fingerprint, settings, state, output,"
                " error, attempts, seconds, updated, content, clip)"
                " VALUES (?, ?, ?, 'done', ?, NULL, ?, 0, ?, ?, ?)",
                (_stored(source), fingerprint, mark[1], _stored(name), ADOPTED_ATTEMPTS,
                 time.time(), content, clip))
            return name
        return None

    def name_to_make(self, source: Path, content: str, preferred: str, folder: Path,
                     with_depth_images: bool, name: str) -> str:
        """The name clip_name gave, for a clip about to be made; but a clip adopted by its
        mark is never made over: its record is dropped and the new clip named as beside a
        file of the user's. An edit saved in place may keep the mark, and the size the clip
        had when written, by which a journal tells its clip from such an edit, is unknown."""
        job = self.get(source)
        if job is None or job.state != "done" or job.attempts != ADOPTED_ATTEMPTS:
            return name
        self.forget(source)
        return self.clip_name(source, content, preferred, folder, with_depth_images)

    def is_up_to_date(self, source: Path, fingerprint: str, settings: tuple[str, ...],
                      output: Path, content: str) -> bool:
        """Done with this photo's bytes and one of these settings' digests, and the clip is
        the file then written (of its size: a clip touched, or copied without its time, is
        still up to date; a truncated or replaced one is not).

        The bytes are told by their sha256 (by size and time for a job of a version that kept
        no sha256): a folder copied without its times, or a photo dropped in the daemon's
        inbox again once its clip was made (the job is then another path's, in done/), has
        nothing new to make; a photo edited with its time kept (exiftool -P) has."""
        try:
            size = output.stat().st_size
        except OSError:
            return False
        own = self.get(source)
        jobs = ([own] if own is not None else []) + self._select("WHERE content = ?", (content,))
        return any(
            job.state == "done" and job.output == output.name and job.settings in settings
            and clip_size(job.clip) == size
            and (job.content == content if job.content is not None
                 else job is own and job.fingerprint == fingerprint)
            for job in jobs)

    def clip_name(self, source: Path, content: str, preferred: str, folder: Path,
                  with_depth_images: bool = False) -> str:
        """The clip's file name: the one this photo's clip already has, else
        `preferred` unless a clip of another photo has (or is about to have) it, or a file
        kbbatch did not write has it or, with_depth_images, the name of a depth image written
        beside it (`--save-depth`); then the photo's stem and the start of its sha256. One
        rule for the batch and the daemon, so no clip of one photo ever replaces a clip of
        another, nor a file of the user's, and an edited photo replaces its own."""
        from kbbatch.images import depth_image_names

        def free(name: str) -> bool:
            companions = depth_image_names(name) if with_depth_images else ()
            return self._is_free(name, source, content, folder, companions)

        # The name this photo's clip was given before, while it is still its own: kept when
        # a same-stem photo comes or goes beside it (a.png beside a.jpg) and through an edit
        # of a photo named by its content, so an editing project's reference stays right and
        # no stale copy is left beside a new name.
        # Its depth images' names taken by the user's files since do not move it: a second
        # copy under a new name would be left beside the old one; those images are not
        # written instead (pipeline.save_depth_images says so).
        job = self.get(source)
        if job is not None and job.output \
                and Path(job.output).suffix == Path(preferred).suffix \
                and self._is_free(job.output, source, content, folder, ()):
            return job.output
        # A content name is checked too: kept through an edit, it may hold a clip of other
        # bytes than its digest says (the edited photo's), which the original, imported
        # again, must not replace.
        return next(name for name in self._names(source, content, preferred) if free(name))

    @staticmethod
    def _names(source: Path, content: str, preferred: str) -> Iterator[str]:
        """The names clip_name tries, in turn: preferred, then the photo's stem with the start
        of its sha256 (and a number, from the second)."""
        from kbbatch.images import fitted_name

        yield preferred
        number = 1
        while True:
            tail = f".{content[:CONTENT_NAME_HEX]}" + (f".{number}" if number > 1 else "")
            yield fitted_name(Path(source).stem, tail + Path(preferred).suffix)
            number += 1

    def _is_free(self, name: str, source: Path, content: str, folder: Path,
                 companions: tuple[str, ...]) -> bool:
        from kbbatch.images import is_users_file

        if any(is_users_file(folder / file)
               for file in companions):
            return False  # the user's file (beside this photo's own clip too)
        owners = sorted(self.owners(name), key=lambda job: job.updated)
        latest = owners[-1] if owners else None
        if latest is not None and (latest.source == str(source) or latest.content == content
                                   or latest.source == Path(source).name):
            # this photo's own clip (re-rendered, the folder moved, or a journal of an earlier
            # version, which keyed jobs by file name), unless another file was saved over it
            # an unfinished attempt knows no clip of its own: the one it was to replace
            return not _saved_over(folder / name, latest.clip or latest.kept_clip)
        if any(os.path.lexists(folder / file) for file in (name, *companions)):
            return False  # another photo's clip or maps, or a file kbbatch did not write
        return latest is None or latest.state != "running"


def clip_size(clip: str | None) -> int | None:
    """The size a clip had when written, from its fingerprint (source_fingerprint)."""
    return int(clip.split(":", 1)[0]) if clip else None


def _saved_over(path: Path, clip: str | None) -> bool:
    """A file other than the clip kbbatch wrote at its name (of another size, and not that
    clip cut short): the user's, e.g. the clip trimmed in an editor and saved in place."""
    from kbbatch.encode import is_cut_short_clip

    written = clip_size(clip)
    try:
        size = path.stat().st_size
    except OSError:
        return False
    return written is not None and size != written and not is_cut_short_clip(path, written)


class FolderBusyError(RuntimeError):
    pass


LOCK_WAIT_S = 1.0
"""How long a run waits for a folder's lock before it says another kbbatch holds it: `kbbatch
status` takes the lock for an instant to tell a killed run from a live one."""


def locked_within(descriptor: int, wait_s: float) -> bool:
    """An exclusive flock on the open file, taken within wait_s; False if another holds it."""
    import fcntl

    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


class FolderLock:
    """An exclusive lock on a folder (flock on the folder itself, so it needs no file there and
    works on a read-only inbox); released when the process ends, even by kill -9."""

    def __init__(self, folder: Path, what: str, wait_s: float = LOCK_WAIT_S) -> None:
        self.descriptor = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        if not locked_within(self.descriptor, wait_s):
            os.close(self.descriptor)
            raise FolderBusyError(f"{folder}: another kbbatch is already {what} this "
                                  "folder; stop it first")

    def release(self) -> None:
        os.close(self.descriptor)
