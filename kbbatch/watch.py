"""The watch-folder daemon: photos dropped into an inbox become clips in an outbox.

A photo is taken only once complete (it arrived by rename, or its size and modification time
stayed put for the settle time). Each clip is written under a temporary name and renamed; the
photo then moves to INBOX/done (or INBOX/failed with a report saying why). The journal in the
outbox records every job, so a restart after kill -9 finishes interrupted work without a
duplicate clip, a lost photo or a partial file.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import glob
import json
import logging
import os
import queue
import shutil
import signal
import stat
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from kbbatch import models
from kbbatch.depth.file import find_depth_file
from kbbatch.fingerprint import file_sha256
from kbbatch.images import (
    NAME_END_REASON,
    OLD_PLAN_SHEET_REASON,
    UNREAD_FORMAT_REASON,
    atomic_output,
    broken_link_reason,
    entry_kind,
    fitted_name,
    free_bytes,
    is_image_file,
    map_stem,
    scan_folder,
    unreadable_reason,
)
from kbbatch.journal import (
    DONE_FOLDER,
    GONE_MARK,
    FolderBusyError,
    FolderLock,
    Journal,
    JournalError,
    clip_size,
    folder_key,
    in_folder,
    source_fingerprint,
)
from kbbatch.manifest import (
    Manifest,
    ManifestEntry,
    ManifestError,
    file_version,
    load_manifest,
)
from kbbatch.outputs import (
    OutputFolderError,
    check_writable,
    folder_identity,
    name_job,
    output_names,
    remove_partial_clips,
    replaced_clip_note,
    unreplaceable,
)
from kbbatch.pipeline import (
    ClipOptions,
    ClipResult,
    clip_fingerprints,
    make_clip,
    remove_stale_scratch,
)
from kbbatch.presets import Preset
from kbbatch.ray_executor import RayClipPool, RayExecutor

log = logging.getLogger("kbbatch.watch")

FAILED_FOLDER = "failed"
INBOX_NOTE = ".kbbatch-inbox.json"
"""In the output folder: the inbox of the daemon that writes there (or last did), for `kbbatch
status` to count the photos waiting in it."""
TEMPORARY_SUFFIXES = (".tmp", ".part", ".crdownload", ".download", ".partial", "~")
LOOP_INTERVAL_S = 0.2
PR_SET_PDEATHSIG = 1


@dataclass(frozen=True)
class WatchSettings:
    inbox: Path
    outbox: Path
    preset: Preset
    options: ClipOptions
    manifest: Manifest | None = None
    jobs: int = 1
    poll: bool = False
    settle_s: float = 2.0
    keep_sources: bool = False
    executor: RayExecutor | None = None  # None: --jobs processes on this machine
    inbox_as_given: Path | None = None  # before links were followed (Daemon.run)


def is_candidate(path: Path) -> bool:
    """A photo to consider: an image, not hidden, not a temporary download."""
    name = path.name.lower()
    return is_image_file(path) and not name.endswith(TEMPORARY_SUFFIXES)


UNUSABLE_ENTRIES: dict[str, Callable[[Path], str]] = {
    "subfolder": lambda path: "subfolders are not watched; move its photos into the inbox",
    "broken_link": broken_link_reason,  # a missing target, or links in a loop
    "not_file": lambda path: "not a regular file (a named pipe, socket or device); not read",
    "unread_format": lambda path: UNREAD_FORMAT_REASON,
    "name_end": lambda path: NAME_END_REASON,
    "plan_sheet": lambda path: OLD_PLAN_SHEET_REASON,
}
"""What the log says, once, of an inbox entry that is no photo to take (images.entry_kind)."""

REWRITE_GRACE_SETTLES = 5.0
"""A photo that fails while it was modified within this many settle times (10 s at the default
settle) is not filed away yet: a writer that paused longer than the settle time may still finish
it. No floor: an inbox whose photos arrive whole (`--settle 0.5`) files a bad one in 2.5 s."""

WORKER_DEATHS_TO_FAIL = 2
"""A photo whose worker process dies this often (while it runs alone) fails; others are retried."""

ENCODER_STOPS_TO_FAIL = 3
"""A photo whose encoder a signal stops this often in one run of the daemon fails: a request to
stop ends the daemon too, so the same photo stopped again and again is hitting a limit (ffmpeg
takes SIGXCPU, a CPU-time limit's signal, as it takes SIGTERM)."""

SPACE_TO_RESUME_BYTES = 1 << 20
"""After a clip found the output's disk full, photos are taken again once this much more room is
free than then (a retry with less would fail the same way)."""

SPACE_RETRY_S = 60.0
"""After a full disk the daemon cannot measure (a Ray node's temporary folder), photos are taken
again this long after."""

MENTIONED_RECHECK_S = 2.0
"""How often the inbox's entries said to be no photo (a broken link) are looked at again."""

MAX_NOTE_BYTES = 1 << 20
"""A file larger than this is not read as one of the daemon's own (a failure report, the inbox
note): someone else's file under such a name."""


def read_note(path: Path) -> object:
    """The JSON of one of the daemon's own small files (a failure report, the inbox note).
    Only a regular file of at most MAX_NOTE_BYTES, not a link, is read: a named pipe under
    the name hung `kbbatch status`, and a link to /dev/zero filled the memory."""
    facts = path.lstat()
    if not stat.S_ISREG(facts.st_mode) or facts.st_size > MAX_NOTE_BYTES:
        raise ValueError(f"{path}: not one of kbbatch's notes")
    return json.loads(path.read_text(encoding="utf-8"))


JOURNAL_RETRY_S = 10.0
"""How long the daemon pauses when its journal cannot be written (a full disk) before retrying."""

RUN_FAULT_RETRY_S = 5.0
"""After a photo failed for a fault of the run's (run_fault), how often the daemon looks whether
it is mended before it takes photos again."""

EVENT_LAG_S = 1.5
"""How long a made clip whose photo is gone from the inbox waits for the observer's word of a
rename or deletion (a polling observer looks every 0.5 s): a rename seen after the finish gave
the photo a second clip under its new name."""


class PhotoLogFilter(logging.Filter):
    """Prefixes a worker's log lines (`depth from popup`) with the photo it is working on."""

    photo: str | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        if self.photo and self.photo not in record.getMessage():
            record.msg, record.args = f"{self.photo}: {record.getMessage()}", None
        return True


PHOTO_LOG = PhotoLogFilter()


def _worker_init(jobs: int = 1) -> None:
    """Workers leave signals to the daemon and die with it (no orphan finishing a clip)."""
    models.share_cores(jobs)
    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(number, signal.SIG_IGN)
    for handler in logging.getLogger().handlers:
        handler.addFilter(PHOTO_LOG)
    # Not on Linux: a killed daemon's worker may finish its clip; recovery copes with that.
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _render(source: Path, output: Path, preset: Preset, options: ClipOptions,
            entry: ManifestEntry | None) -> ClipResult:
    PHOTO_LOG.photo = source.name
    try:
        return make_clip(source, output, preset, options, show_progress=False, entry=entry)
    finally:
        PHOTO_LOG.photo = None


def unique_destination(folder: Path, name: str) -> Path:
    """A path in folder for name that overwrites nothing."""
    folder.mkdir(parents=True, exist_ok=True)
    candidate = folder / name
    stem, suffix = Path(name).stem, Path(name).suffix
    counter = 1
    while os.path.lexists(candidate):  # a broken link there is a file not to replace too
        candidate = folder / fitted_name(stem, f".{counter}{suffix}")
        counter += 1
    return candidate


def move_photo(path: Path, destination: Path) -> None:
    """Move a photo; a relative symbolic link is made again to point from its new folder at
    the same file (moved as it was, `../photos/x.jpg` led nowhere from done/)."""
    target = os.readlink(path) if path.is_symlink() else None
    if target is None or os.path.isabs(target):
        try:
            os.rename(path, destination)
        except OSError as error:
            # Copied only across file systems: another user's photo in a sticky inbox was
            # copied into done/ and could not be removed, a copy more at every start.
            if error.errno != errno.EXDEV:
                raise
            # under a temporary name until complete: a full disk, or a kill, left a truncated
            # copy under the photo's own name
            with atomic_output(destination, destination.suffix, make_folder=False) as temp:
                shutil.copy2(path, temp)
            try:
                path.unlink()
            except OSError:
                destination.unlink()  # one photo, in the inbox, as the error says
                raise
        return
    # The target as written, after the way back from the new folder: tidied as text,
    # `dirlink/../x.jpg` would mean another file.
    os.symlink(os.path.join(os.path.relpath(path.parent, destination.parent), target),
               destination)
    try:
        path.unlink()
    except OSError:
        destination.unlink()  # one link, in the inbox, as the error says
        raise


def folder_is_writable(folder: Path) -> bool:
    """Whether files can be created and moved in a folder (a read-only mount says no, even to
    root, where the permission bits would say yes)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".kbbatch-write-test-"):
            return True
    except OSError:
        return False


def run_fault(outbox: Path) -> str | None:
    """Why no photo can be made now for a reason of the run's, not the photo's: the output
    folder can no longer be written (made read-only while the daemon ran), or a model file was
    damaged or replaced by another. Each photo then failed, and a whole inbox went to failed/,
    for its owner to move back one by one."""
    if not folder_is_writable(outbox):
        return f"{outbox}: files can no longer be made in the output folder (made read-only?)"
    try:
        models.check_cache()
    except models.ModelError as error:
        return str(error)
    return None


@dataclass(frozen=True)
class InFlight:
    path: Path
    fingerprint: str  # size and time when taken: a change since means it was still written
    output: str
    renamed: bool
    replaces: bool = False  # its clip replaces one made from the photo's earlier bytes
    content: str = ""  # sha256 of its bytes when taken


@dataclass(frozen=True)
class Suspect:
    """A failed photo modified recently: filed away only if it stays unchanged until `until`."""

    result: ClipResult
    fingerprint: str
    until: float


@dataclass(frozen=True)
class Arrival:
    """A photo seen in the inbox and not taken yet: it is complete once it arrived by rename, or
    once its size and time stayed put for the settle time."""

    size_bytes: int
    mtime_ns: int
    since: float  # time.monotonic() when the size or time was last seen to change
    renamed: bool  # arrived by rename (complete at once)


class InboxTracker:
    """Which photos in the inbox are complete: file events in, settled photos out."""

    def __init__(self, inbox: Path, settle_s: float, ignore: tuple[str, ...] = ()) -> None:
        self.inbox = inbox
        self.settle_s = settle_s
        self.ignore = (DONE_FOLDER, FAILED_FOLDER, *ignore)  # the daemon's own folders
        self.events: queue.Queue[tuple[Path, bool]] = queue.Queue()  # filled by the observer
        self.arrivals: dict[Path, Arrival] = {}
        self.mentioned: set[Path] = set()  # subfolders and broken links already logged
        self.mentioned_checked_at = 0.0  # time.monotonic() of the last recheck_mentioned
        self.held: set[Path] = set()  # photos the manifest excludes or names as depth maps
        self.removals: queue.Queue[Path] = queue.Queue()  # filled by the observer
        self.removed: set[Path] = set()  # taken photos deleted since (their clips in flight)
        self.maps: dict[Path, float] = {}  # depth maps in the inbox: their last event's time
        self.renames: queue.Queue[tuple[Path, Path]] = queue.Queue()  # filled by the observer
        self.renamed_to: dict[Path, Path] = {}  # photos renamed in the inbox: old -> new path

    def notice(self, path: Path, renamed: bool = False) -> None:
        """A file event (from any thread), or a photo handed back to be taken again."""
        self.events.put((path, renamed))

    def notice_removal(self, path: Path) -> None:
        """A file was deleted from the inbox (from the observer's thread)."""
        self.removals.put(path)

    def notice_rename(self, source: Path, destination: Path) -> None:
        """A file was renamed (from the observer's thread): a photo renamed while its clip was
        made got a second clip under its new name."""
        self.renames.put((source, destination))

    def forget(self, path: Path) -> None:
        """The photo was taken (or filed away): no longer waiting."""
        del self.arrivals[path]
        self.removed.discard(path)

    def forget_if_waiting(self, path: Path) -> None:
        if path in self.arrivals:
            self.forget(path)

    def recheck_mentioned(self) -> None:
        """Entries said once to be no photo: a link whose target appeared since is taken (no
        event in the inbox tells of it: it waited for a restart), and one removed is forgotten
        (a link made again under its name was not said again)."""
        if time.monotonic() < self.mentioned_checked_at + MENTIONED_RECHECK_S:
            return
        self.mentioned_checked_at = time.monotonic()
        for path in list(self.mentioned):
            if not os.path.lexists(path):
                self.mentioned.discard(path)
            elif path.is_symlink() and path.is_file():
                self.mentioned.discard(path)
                self.notice(path)

    def collect_events(self) -> None:
        self.recheck_mentioned()
        while True:
            try:
                self.removed.add(self.removals.get_nowait())
            except queue.Empty:
                break
        while True:
            try:
                source, destination = self.renames.get_nowait()
            except queue.Empty:
                break
            if source.parent == self.inbox and destination.parent == self.inbox:
                for old, new in list(self.renamed_to.items()):  # renamed again
                    if new == source:
                        self.renamed_to[old] = destination
                self.renamed_to[source] = destination
        now = time.monotonic()
        while True:
            try:
                path, renamed = self.events.get_nowait()
            except queue.Empty:
                break
            if path.parent == self.inbox and map_stem(path.name):
                self.maps[path] = now
                continue
            if path.parent != self.inbox or not self.usable(path):
                continue
            try:
                stat = path.stat()
            except FileNotFoundError:
                self.arrivals.pop(path, None)
                continue
            previous = self.arrivals.get(path)
            changed = previous is None or (previous.size_bytes, previous.mtime_ns) != (
                stat.st_size, stat.st_mtime_ns)
            since = now if changed else previous.since
            self.arrivals[path] = Arrival(stat.st_size, stat.st_mtime_ns, since,
                                          renamed or (previous.renamed if previous else False))

    def usable(self, path: Path) -> bool:
        """A photo to take; a subfolder, broken link or pipe is said once in the log."""
        if path.name in self.ignore or path.name.startswith("."):
            return False
        kind = entry_kind(path)
        if kind in UNUSABLE_ENTRIES:
            if path not in self.mentioned:
                self.mentioned.add(path)
                log.warning("%s: %s", path, UNUSABLE_ENTRIES[kind](path))
            return False
        return is_candidate(path)

    def is_ready(self, path: Path) -> bool:
        arrival = self.arrivals[path]
        try:
            stat = path.stat()
        except FileNotFoundError:
            return False
        if (stat.st_size, stat.st_mtime_ns) != (arrival.size_bytes, arrival.mtime_ns):
            self.arrivals[path] = Arrival(stat.st_size, stat.st_mtime_ns, time.monotonic(), False)
            return False
        settled = arrival.renamed or time.monotonic() - arrival.since >= self.settle_s
        return settled and not self.map_being_written(path)  # looked up once it counts

    def settled_lone_maps(self) -> list[Path]:
        """Depth maps in the inbox, unchanged for the settle time, with no photo of their
        stem waiting; each given once (a photo that comes later finds its map as ever)."""
        now = time.monotonic()
        waiting = {photo.stem for photo in self.arrivals}
        lone = []
        for path, since in list(self.maps.items()):
            if now - since < self.settle_s:
                continue
            del self.maps[path]
            if path.exists() and map_stem(path.name) not in waiting:
                lone.append(path)
        return lone

    def map_being_written(self, path: Path) -> bool:
        """Whether the photo's depth map beside it changed within the settle time: a photo
        that settled while its map was still being copied failed ("not a readable image"),
        and was filed with half its map."""
        depth_map = find_depth_file(path)
        if depth_map is None:
            return False
        try:
            changed_s_ago = time.time() - depth_map.stat().st_mtime
        except OSError:
            return False
        return abs(changed_s_ago) < self.settle_s  # a time in the future is no arrival


class ManifestFollower:
    """The daemon's manifest, read again when its file changes: an exclude or a crop saved
    from `kbbatch review` while the daemon ran was ignored until a restart. A change that does
    not load is logged once and the manifest as it was stays in force."""

    def __init__(self, manifest: Manifest | None) -> None:
        self.current = manifest
        self.stamp = manifest.version_read if manifest else None

    def get(self) -> Manifest | None:
        if self.current is None:
            return None
        stamp = file_version(self.current.path)
        if stamp == self.stamp:
            return self.current
        self.stamp = stamp
        if stamp is None:
            log.error("%s: gone or unreadable; still following it as it was", self.current.path)
            return self.current
        try:
            self.current = load_manifest(self.current.path)
        except ManifestError as error:
            log.error("%s; still following the manifest as it was", error)
            return self.current
        log.info("%s: changed; read again", self.current.path)
        return self.current


class JobRunner:
    """The clips of settled photos: submission to the pool, results, worker deaths, the photos'
    moves to done/ or failed/ and the failure reports; the journal records every step."""

    def __init__(self, settings: WatchSettings, journal: Journal, keep_sources: bool,
                 failure_reports: Path, requeue: Callable[[Path, bool], None]) -> None:
        self.settings = settings
        self.journal = journal
        self.keep_sources = keep_sources
        self.failure_reports = failure_reports
        self.requeue = requeue  # hands a photo back to the inbox tracker (path, renamed)
        self.in_flight: dict[Future, InFlight] = {}
        self.suspects: dict[Path, Suspect] = {}
        self.worker_deaths: dict[Path, int] = {}  # photos in flight when a worker died
        self.encoder_stops: dict[Path, int] = {}  # photos whose encoder a signal stopped
        self.space_wanted: tuple[Path, int, float | None] | None = None  # after a full disk
        self.fault: tuple[str, float] | None = None  # run_fault's reason, when to look again
        self.gone_since: dict[Future, float] = {}  # made clips awaiting word of their photo
        self.pool: ProcessPoolExecutor | RayClipPool | None = None
        self.manifest = ManifestFollower(settings.manifest)
        # the inbox as given too: a link to it pointed elsewhere leaves the folder watched
        # unused, as a removed one would
        self.identities = {folder: folder_identity(folder)
                           for folder in (settings.inbox, settings.inbox_as_given,
                                          settings.outbox) if folder is not None}

    def folders_gone(self) -> str | None:
        """The inbox or the output folder removed, renamed or made again since the start: the
        daemon watched a folder nobody used (silently), or filed every photo as failed when
        its clip found no output folder."""
        for folder, identity in self.identities.items():
            if folder_identity(folder) != identity:
                which = ("output folder" if folder == self.settings.outbox else "inbox")
                return f"{folder}: the {which} was removed, renamed or made again"
        return None

    def recover(self) -> None:
        """After a crash: drop partial clips, and settle jobs whose clip was already renamed."""
        s = self.settings
        for partial in remove_partial_clips(s.outbox):
            log.info("removed partial file %s from an interrupted run", partial.name)
        for folder in (s.inbox / DONE_FOLDER, s.inbox / FAILED_FOLDER):
            if folder.is_dir():  # a photo's copy to another disk, interrupted
                for partial in remove_partial_clips(folder):
                    log.info("removed partial copy %s/%s from an interrupted run", folder.name,
                             partial.name)
        for scratch in remove_stale_scratch():
            log.info("removed %s, left by a killed worker", scratch)
        for job in self.journal.jobs("running"):
            source = Path(job.source)
            output = s.outbox / job.output if job.output else None
            if in_folder(source, s.inbox) and not os.path.lexists(source):
                # deleted while no daemon ran: nothing to resume (a batch's photo elsewhere
                # may only be on a card out of the reader: left alone)
                self.journal.photo_gone(source, s.outbox)
                log.info("dropped %s: the photo was removed before its clip was complete",
                         job.name)
            elif (output is not None and output.is_file() and source.is_file()
                  and output.stat().st_mtime >= job.updated):
                # The clip was complete (renamed) before the crash; only the photo's move is
                # left. (A clip older than the job is an earlier make's: the photo was edited,
                # and its new clip was not finished.)
                self.journal.finish(source, "done", job.seconds or 0.0, None,
                                    source_fingerprint(output))
                self.move_source(source, DONE_FOLDER)
                log.info("recovered %s: clip was complete", job.name)
            else:
                log.info("resuming %s: interrupted before its clip was complete", job.name)
        for job in self.journal.jobs("done"):
            source = Path(job.source)
            if in_folder(source, s.inbox) and not os.path.lexists(source):
                self.journal.done_photo_removed(source)  # deleted while no daemon ran

    def new_pool(self) -> ProcessPoolExecutor | RayClipPool:
        """--jobs worker processes here, or --jobs clips in flight on Ray."""
        if self.settings.executor is not None:
            return RayClipPool(self.settings.executor).start()
        return ProcessPoolExecutor(max_workers=self.settings.jobs, initializer=_worker_init,
                                   initargs=(self.settings.jobs,))

    def submit_ready(self, inbox: InboxTracker, options: ClipOptions,
                     stopping: threading.Event) -> None:
        """Start the settled photos, --jobs at a time; a photo whose worker died runs alone."""
        s = self.settings
        before, manifest = self.manifest.current, self.manifest.get()
        if manifest is not before:  # photos it excluded, or maps it named, may be wanted now
            for path in sorted(inbox.held):  # still held: not said again
                if path.exists():
                    self.requeue(path, False)
                else:
                    inbox.held.discard(path)
        if not self.has_space() or self.fault_remains():
            return
        busy = {job.path for job in self.in_flight.values()} | set(self.suspects)
        # renamed while its clip is made: that clip becomes its own once finished
        busy |= {inbox.renamed_to[job.path] for job in self.in_flight.values()
                 if job.path in inbox.renamed_to}
        for path in sorted(inbox.arrivals, key=lambda p: (p not in self.worker_deaths, p)):
            if len(self.in_flight) >= s.jobs or stopping.is_set():
                return
            if any(job.path in self.worker_deaths for job in self.in_flight.values()):
                return  # a photo whose worker died runs alone, so a second death is its own
            if path in self.worker_deaths and self.in_flight:
                return
            if path in busy or not inbox.is_ready(path):
                continue
            renamed = inbox.arrivals[path].renamed
            entry = manifest.entry(path.name, path.parent) if manifest else None
            map_of = manifest.depth_map_of(path) if manifest else None
            if (entry is not None and entry.excluded) or map_of:  # as the batch: not rendered
                inbox.forget(path)
                if path not in inbox.held:
                    inbox.held.add(path)
                    log.info("%s: %s; left in the inbox", path.name,
                             f"the depth map of {map_of} in the manifest" if map_of
                             else "excluded by the manifest")
                continue
            inbox.held.discard(path)
            if manifest and entry is None:
                near = manifest.near_key(path.name)
                if near is not None:  # the batch says so; the daemon rendered it silently
                    log.warning("%s: the manifest's entry %r is not its exact file name, so "
                                "it does not apply (an exclude or crops there are not used)",
                                path.name, near)
            try:
                fingerprint = source_fingerprint(path)
                content = file_sha256(path)
                settings = clip_fingerprints(path, content, s.preset, options, entry)
            except OSError as error:
                inbox.forget(path)
                result = ClipResult(str(path), None, "failed", 0.0,
                                    error=f"{error.filename or path}: {unreadable_reason(error)}")
                self.file_failure(path, result)
                continue
            preferred = self.preferred_name(path)
            job = name_job(self.journal, path, s.outbox, preferred, entry, fingerprint, content,
                           settings, options.save_depth)
            inbox.forget(path)
            if isinstance(job, ClipResult):
                if job.status == "skipped":
                    if job.note:
                        log.info("%s", job.note)
                    log.info("%s: clip already complete%s", path.name,
                             "" if self.keep_sources else ", moving the photo")
                    self.move_source(path, DONE_FOLDER)
                else:  # its clip's name is another user's file in a sticky outbox
                    self.file_failure(path, job)
                continue
            if job.name_note is not None:
                log.warning("%s", job.name_note)
            log.info("start %s", path.name)
            try:
                future = self.pool.submit(_render, path, job.output, s.preset, options, entry)
            except BrokenProcessPool:  # broke since the last look: its jobs come back below
                self.journal.finish(path, "queued", 0.0, "worker pool broken; retrying")
                self.requeue(path, True)
                if not self.in_flight:  # an idle worker died: no job's result will say so,
                    # and the photo was offered to the broken pool again and again
                    log.warning("a worker process died while idle (out of memory, or "
                                "killed); pool rebuilt")
                    self.recover_from_worker_death()
                return
            self.in_flight[future] = InFlight(path, fingerprint, job.output.name, renamed,
                                              job.replaces_other_bytes, content)

    def preferred_name(self, source: Path) -> str:
        """The batch's rule (outputs.output_names) over the photos in the inbox now."""
        others = [p for p in scan_folder(self.settings.inbox).photos if p != source]
        return output_names([source, *others])[source]

    def finish_completed(self, removed: set[Path] | None = None,
                         renamed: dict[Path, Path] | None = None,
                         forget: Callable[[Path], None] | None = None) -> None:
        """Record the clips that are finished. removed: photos deleted from the inbox since
        they were taken (a file now at such a path is another photo); deletions of photos no
        longer in flight (the moves to done/ among them) are dropped from it. renamed: photos
        renamed in the inbox (old path -> new), whose clip is the renamed photo's, taken no
        more (forget)."""
        removed = set() if removed is None else removed
        renamed = {} if renamed is None else renamed
        if any(f.done() and isinstance(f.exception(), BrokenProcessPool)
               for f in self.in_flight):
            self.recover_from_worker_death()
        for future in [f for f in self.in_flight if f.done()]:
            job = self.in_flight[future]
            try:
                result = future.result()
            except Exception as error:  # the call itself failed (not the photo's pipeline)
                result = ClipResult(str(job.path), None, "failed", 0.0,
                                    error=f"{job.path}: worker failed: {error}")
            if self.awaiting_word(future, job, result, removed, renamed):
                continue
            # Deleted and another photo put under its name while the clip was made: the clip is
            # the deleted photo's, and the new one is a photo of its own, not an edit of it.
            replaced = (result.status == "done" and job.path in removed
                        and job.path.exists())
            if self.changed_since_taken(job, result) and not replaced:
                self.journal.finish(job.path, "queued", result.seconds,
                                    "changed while being processed")
                del self.in_flight[future]
                log.warning("%s changed while it was processed (still being written?): "
                            "taken again once it settles", job.path.name)
                self.requeue(job.path, False)
                continue
            self.worker_deaths.pop(job.path, None)
            gone = self.folders_gone()
            if result.status != "done" and gone:  # the folder's fault, not the photo's
                del self.in_flight[future]
                log.warning("%s: not made (%s); left where it is", job.path.name, gone)
                continue
            if result.status in ("failed", "interrupted", "no_space") and not job.path.exists():
                # deleted from the inbox while it was processed: the user's choice, no failure
                self.journal.forget(job.path)
                del self.in_flight[future]
                log.info("%s was removed from the inbox while it was processed; skipped",
                         job.path.name)
                continue
            fault = run_fault(self.settings.outbox) if result.status == "failed" else None
            if fault:  # the run's fault, not the photo's: it stays queued until mended
                self.journal.finish(job.path, "queued", result.seconds, result.error)
                del self.in_flight[future]
                self.hold_for(fault, job.path)
                self.requeue(job.path, job.renamed)
                continue
            if result.status == "no_space":  # not the photo's fault: it waits for room
                self.journal.finish(job.path, "queued", result.seconds, result.error)
                del self.in_flight[future]
                self.wait_for_space(result)
                self.requeue(job.path, job.renamed)
                continue
            if result.status == "interrupted":  # ffmpeg stopped from outside: not the photo's
                stops = self.encoder_stops.get(job.path, 0) + 1
                self.encoder_stops[job.path] = stops
                if stops < ENCODER_STOPS_TO_FAIL:
                    self.journal.finish(job.path, "queued", result.seconds, result.error)
                    del self.in_flight[future]
                    log.warning("%s: %s", job.path.name, result.error)
                    self.requeue(job.path, job.renamed)
                    continue
                del self.encoder_stops[job.path]
                result.status = "failed"  # filed below: a limit, not a stop, ends its encoder
                result.error = (f"{result.error} ({stops} times in a row: a limit such as a "
                                "CPU-time limit stops it, not a request to stop); set aside")
            self.encoder_stops.pop(job.path, None)
            clip = None
            if result.status == "done":
                with contextlib.suppress(OSError):
                    clip = source_fingerprint(self.settings.outbox / job.output)
            # journaled under the bytes it was made from: read after the photo was replaced,
            # they are the new photo's, and a cross-path look-up by content must not take
            # the clip for the deleted one's
            self.journal.finish(job.path, result.status, result.seconds, result.error, clip,
                                result.content)
            del self.in_flight[future]
            now_at = self.renamed_photo(job, result, renamed)
            if now_at is not None:  # the same photo under its new name: the clip is its
                self.journal.moved(job.path, now_at)
                if forget is not None:
                    forget(now_at)
                log.info("%s was renamed %s while its clip was made: the clip is the renamed "
                         "photo's",
                         job.path.name, now_at.name)
                job = replace(job, path=now_at)
            if result.status == "done" and (replaced or not job.path.exists()):
                # Deleted while its frames rendered: its clip no longer belongs to the inbox
                # path, or a different photo dropped there later would take the clip's name
                # as its own re-render and replace it.
                self.journal.done_photo_removed(job.path)
            if replaced:
                log.info("done %s in %.1f s -> %s; %s was replaced by another photo while "
                         "its clip was made: that one gets a clip of its own", job.path.name,
                         result.seconds, result.output, job.path.name)
                self.requeue(job.path, False)
            elif result.status == "done":
                if self.move_source(job.path, DONE_FOLDER) is None:
                    self.remove_reports_of(job.path)
                log.info("done %s in %.1f s -> %s", job.path.name, result.seconds,
                         result.output)
                if result.note:
                    log.warning("%s", result.note)
                if job.replaces:
                    log.warning("%s", replaced_clip_note(job.path, job.output))
            elif not job.renamed and self.recently_written(job.path):
                grace = self.rewrite_grace_s()
                self.suspects[job.path] = Suspect(result, job.fingerprint,
                                                  time.monotonic() + grace)
                log.info("%s failed but was written %.0f s ago or less; filed as failed only "
                         "if it stays unchanged that long", job.path.name, grace)
            else:
                self.file_failure(job.path, result)
        in_flight = {job.path for job in self.in_flight.values()}
        for path in set(renamed) - in_flight:
            del renamed[path]
        for path in removed - in_flight:
            if not os.path.lexists(path) and self.journal.done_photo_removed(path):
                log.info("%s was removed from the inbox; its clip %s stays, and a photo saved "
                         "later under its name gets a clip of its own", path.name,
                         self.journal.get(path.with_name(f"{path.name}{GONE_MARK}")).output)
        removed.intersection_update(in_flight)

    def awaiting_word(self, future: Future, job: InFlight, result: ClipResult,
                      removed: set[Path], renamed: dict[Path, Path]) -> bool:
        """A clip made of a photo gone from its path, with no rename or deletion seen yet,
        waits up to EVENT_LAG_S for the observer to say which it was."""
        if (result.status != "done" or job.path in removed or job.path in renamed
                or os.path.lexists(job.path)):
            self.gone_since.pop(future, None)
            return False
        since = self.gone_since.setdefault(future, time.monotonic())
        if time.monotonic() - since < EVENT_LAG_S:
            return True
        del self.gone_since[future]
        return False

    def renamed_photo(self, job: InFlight, result: ClipResult, renamed: dict[Path, Path]
                      ) -> Path | None:
        """Where a photo renamed in the inbox while its clip was made now is: the same bytes
        at its new name, the old one gone."""
        now_at = renamed.get(job.path)
        if (result.status != "done" or now_at is None or os.path.lexists(job.path)
                or not now_at.is_file()):
            return None
        try:
            return now_at if file_sha256(now_at) == (result.content or job.content) else None
        except OSError:
            return None

    def wait_for_space(self, result: ClipResult) -> None:
        """No photo is taken until the disk that was full (the output's, or the temporary
        folder's) has SPACE_TO_RESUME_BYTES more room than when the clip found it full: each
        would fail the same way. A folder this process cannot see (a Ray node's) is tried again
        after SPACE_RETRY_S."""
        folder = Path(result.full_folder or self.settings.outbox)
        free = free_bytes(folder)
        if free is not None and result.free_bytes_when_full is not None:
            free = min(free, result.free_bytes_when_full)  # room made since then counts
        if self.space_wanted is None:
            log.warning("%s; no photo is taken until %d MB more are free there", result.error,
                        SPACE_TO_RESUME_BYTES >> 20)
        retry_at = time.monotonic() + SPACE_RETRY_S if free is None else None
        self.space_wanted = (folder, (free or 0) + SPACE_TO_RESUME_BYTES, retry_at)

    def has_space(self) -> bool:
        if self.space_wanted is None:
            return True
        folder, wanted, retry_at = self.space_wanted
        free = free_bytes(folder)
        if retry_at is not None and time.monotonic() < retry_at:
            return False
        if retry_at is None and (free is None or free < wanted):
            return False
        self.space_wanted = None
        log.info("%s has room again (%s MB free): taking photos again", folder,
                 "?" if free is None else free >> 20)
        return True

    def hold_for(self, fault: str, path: Path) -> None:
        if self.fault is None:
            log.warning("%s: not made: %s; it stays in the inbox, and no photo is taken until "
                        "that is mended", path.name, fault)
        else:
            log.info("%s: not made (%s); it stays in the inbox", path.name, fault)
        self.fault = (fault, time.monotonic() + RUN_FAULT_RETRY_S)

    def fault_remains(self) -> bool:
        """Photos wait while a run fault lasts; looked at every RUN_FAULT_RETRY_S."""
        if self.fault is None:
            return False
        reason, look_at = self.fault
        if time.monotonic() < look_at:
            return True
        if run_fault(self.settings.outbox):
            self.fault = (reason, time.monotonic() + RUN_FAULT_RETRY_S)
            return True
        self.fault = None
        log.info("no longer so (%s): taking photos again", reason)
        return False

    def recover_from_worker_death(self) -> None:
        """A worker process died (out of memory, killed): the pool is broken and every photo in
        flight lost its result. Rebuild the pool and take them again; a photo that was alone in
        flight when its worker died twice is the cause, and fails saying so."""
        jobs = list(self.in_flight.values())
        self.in_flight.clear()
        # Workers ignore SIGTERM (signals are the daemon's), so the broken pool's own clean-up
        # would wait for the survivors' clips, whose results are lost anyway: end them now.
        for process in list((getattr(self.pool, "_processes", None) or {}).values()):
            with contextlib.suppress(OSError):
                process.kill()
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.pool = self.new_pool()
        for partial in remove_partial_clips(self.settings.outbox):  # none of them is alive now
            log.info("removed partial file %s of the dead worker", partial.name)
        remove_stale_scratch()
        for job in jobs:
            alone = len(jobs) == 1
            deaths = self.worker_deaths.get(job.path, 0) + 1 if alone else max(
                self.worker_deaths.get(job.path, 0), 1)
            self.worker_deaths[job.path] = deaths
            if deaths >= WORKER_DEATHS_TO_FAIL:
                del self.worker_deaths[job.path]
                error = (f"{job.path}: its worker process died {deaths} times while rendering "
                         "it (out of memory, or killed); the photo is set aside")
                self.journal.finish(job.path, "failed", 0.0, error)
                self.file_failure(job.path, ClipResult(str(job.path), None, "failed", 0.0,
                                                       error=error))
                continue
            self.journal.finish(job.path, "queued", 0.0, "worker process died; retrying")
            log.warning("%s: the worker process rendering it died (out of memory, or killed); "
                        "pool rebuilt, taking it again%s", job.path.name,
                        "" if alone else " alone")
            self.requeue(job.path, True)

    def changed_since_taken(self, job: InFlight, result: ClipResult) -> bool:
        """Its size or time changed, or its bytes: the clip was made from others than it was
        taken with, or it holds others now (saved over with its size and time kept, as
        exiftool -P does: it went to done/ with the clip of the photo it replaced)."""
        if result.content and job.content and result.content != job.content:
            return True
        try:
            if source_fingerprint(job.path) != job.fingerprint:
                return True
            return (result.status == "done" and bool(job.content)
                    and file_sha256(job.path) != job.content)
        except FileNotFoundError:
            return False
        except OSError:  # unreadable now: taken again, to fail by name if it stays so
            return True

    def recently_written(self, path: Path) -> bool:
        try:
            age_s = time.time() - path.stat().st_mtime
        except FileNotFoundError:
            return False
        return age_s < self.rewrite_grace_s()

    def rewrite_grace_s(self) -> float:
        return REWRITE_GRACE_SETTLES * self.settings.settle_s

    def file_suspects(self) -> None:
        """Failed photos on probation: changed means re-queued, unchanged in time means failed."""
        for path, suspect in list(self.suspects.items()):
            try:
                changed = source_fingerprint(path) != suspect.fingerprint
            except FileNotFoundError:
                del self.suspects[path]
                continue
            if changed:
                del self.suspects[path]
                self.journal.finish(path, "queued", 0.0, "changed after it failed")
                log.info("%s changed after it failed: taken again once it settles", path.name)
                self.requeue(path, False)
            elif time.monotonic() >= suspect.until:
                del self.suspects[path]
                self.file_failure(path, suspect.result)

    def file_late_maps(self, maps: list[Path]) -> None:
        """A depth map that came after its photo's clip was made (the photo in done/): left
        in the inbox, it was taken for the map of the next photo dropped under that name,
        another photo (or that photo failed: "the photo's aspect is ..."). It goes to done/
        beside its photo, said; dropped in again with the photo, it makes its clip."""
        if self.keep_sources:  # the photo stays in the inbox: the map is its own
            self.retake_photos_of(maps)
            return
        flying = {job.path.stem for job in self.in_flight.values()}
        done = self.settings.inbox / DONE_FOLDER
        for depth_map in maps:
            stem = map_stem(depth_map.name)
            if stem in flying or any(p.stem == stem for p in self.settings.inbox.iterdir()
                                     if is_candidate(p)):
                continue  # its photo is here: the photo's clip takes it
            made = [photo for photo in (done.iterdir() if done.is_dir() else ())
                    if photo.stem == stem and is_candidate(photo)
                    and (job := self.journal.get(photo)) is not None and job.state == "done"]
            if not made:
                continue  # its photo may still come
            photo = max(made, key=lambda path: path.stat().st_mtime_ns)
            try:
                destination = unique_destination(done, depth_map.name)
                move_photo(depth_map, destination)
            except OSError as error:
                log.error("%s: came after the clip of its photo %s was made, and cannot be "
                          "moved to %s/ (%s)", depth_map.name, photo.name, DONE_FOLDER,
                          error.strerror or error)
                continue
            log.warning("%s: came after the clip of %s was made (without it); moved to %s/ "
                        "beside the photo: drop both in again to make the clip with it",
                        depth_map.name, photo.name, DONE_FOLDER)

    def retake_photos_of(self, maps: list[Path]) -> None:
        """A depth map saved or edited beside a photo that stays in the inbox: the photo is
        looked at again, and its clip made again with the map (only a restart did). One in
        flight is taken again once its clip is made."""
        for depth_map in maps:
            stem = map_stem(depth_map.name)
            for photo in sorted(self.settings.inbox.iterdir()):
                if photo.stem == stem and is_candidate(photo):
                    log.info("%s: its depth map %s was saved; looked at again", photo.name,
                             depth_map.name)
                    self.requeue(photo, False)

    def file_failure(self, path: Path, result: ClipResult) -> None:
        moved = self.move_source(path, FAILED_FOLDER)
        self.write_failure_report(moved or path, result)
        log.warning("failed %s: %s", path.name, result.error)

    def move_source(self, path: Path, folder: str) -> Path | None:
        """Move a photo to done/ or failed/ (the journal follows it); None where it stays."""
        if self.keep_sources and folder == DONE_FOLDER:
            return None
        if self.keep_sources or not path.exists():
            return None
        depth_map = find_depth_file(path)
        if depth_map is not None and any(  # b.jpg and b.png share b.depth.png: it stays
                other.stem == path.stem and other != path
                for other in scan_folder(self.settings.inbox).photos):
            depth_map = None
        try:  # done/ made a file after the start: said, and the daemon goes on
            destination = unique_destination(self.settings.inbox / folder, path.name)
            move_photo(path, destination)
        except OSError as error:
            log.error("%s: cannot be moved to %s/ (%s); it stays in the inbox", path, folder,
                      error.strerror or error)
            return None
        self.journal.moved(path, destination)
        if depth_map is not None:  # left behind, it was taken for the map of the next photo
            # dropped under this name (a different one)
            map_destination = destination.with_name(
                destination.stem + depth_map.name[len(path.stem):])
            try:
                if os.path.lexists(map_destination):
                    raise FileExistsError(errno.EEXIST, "a file of its name is there")
                move_photo(depth_map, map_destination)
            except OSError as error:
                log.error("%s: cannot be moved to %s/ beside its photo (%s)", depth_map,
                          folder, error.strerror or error)
        return destination

    def reports_of_kept_photo(self, photo: Path) -> list[Path]:
        """The failure reports of a photo that stays where it is (--keep-sources, a read-only
        inbox): each new failure added one beside the last, and one made later kept saying it
        failed."""
        if photo.parent.name == FAILED_FOLDER or not self.failure_reports.is_dir():
            return []
        reports = []
        for report in self.failure_reports.glob("*.error.json"):
            try:
                if read_note(report).get("photo") == str(photo):
                    reports.append(report)
            except (OSError, ValueError, AttributeError):
                continue  # not one of ours
        return reports

    def remove_reports_of(self, photo: Path) -> None:
        for report in self.reports_of_kept_photo(photo):
            try:
                report.unlink()
            except OSError as error:
                log.error("%s: an earlier failure report of %s, cannot be removed (%s)",
                          report, photo.name, error.strerror or error)
            else:
                log.info("%s: removed %s, the report of its earlier failure", photo.name,
                         report.name)

    def write_failure_report(self, photo: Path, result: ClipResult) -> None:
        self.remove_reports_of(photo)
        folder = photo.parent if photo.parent.name == FAILED_FOLDER else self.failure_reports
        name = fitted_name(photo.name, ".error.json")
        report = folder / name
        data = {"photo": str(photo), "error": result.error, "detail": result.detail,
                "result": asdict(result)}
        try:
            report = unique_destination(folder, name)
            with atomic_output(report, ".json") as temp_path:
                temp_path.write_text(json.dumps(data, indent=2), encoding="utf-8")
        except OSError as error:
            log.error("%s: failure report cannot be written (%s)", report,
                      error.strerror or error)


class Daemon:
    """The wiring: locks, signals, the observer feeding the inbox tracker, and the loop that
    hands settled photos to the job runner."""

    def __init__(self, settings: WatchSettings) -> None:
        settings = replace(settings, inbox=settings.inbox.absolute(),
                           outbox=settings.outbox.absolute())
        self.settings = settings
        self.stopping = threading.Event()
        self.inbox: InboxTracker | None = None
        self.jobs: JobRunner | None = None

    def request_stop(self, *_: object) -> None:
        if not self.stopping.is_set():
            log.info("stopping: no new work; finishing %d clip(s) in progress",
                     len(self.jobs.in_flight) if self.jobs else 0)
        self.stopping.set()

    def run(self) -> int:
        s = self.settings
        if os.path.lexists(s.inbox) and not s.inbox.is_dir():
            raise OutputFolderError(f"{s.inbox}: the inbox is not a folder")
        # A missing parent is a typo or a share not mounted yet: made with its parents, the
        # inbox was an empty folder on the local disk that the share then hid, for good.
        if not s.inbox.is_dir() and not s.inbox.parent.is_dir():
            raise OutputFolderError(f"{s.inbox}: no such inbox, nor its folder "
                                    f"{s.inbox.parent} (a share not mounted yet?)")
        made = [folder for folder in (s.outbox, *s.outbox.parents) if not folder.exists()]
        check_writable(s.outbox)
        # The output folder's lock first: a daemon refused for a busy one made the inbox it
        # named and left it behind.
        outbox_lock = FolderLock(s.outbox, "writing clips into")
        refused = True  # until it serves: refused, the output folders it made go (empty)
        try:
            if not s.inbox.is_dir():
                s.inbox.mkdir(exist_ok=True)
                log.info("made the inbox %s", s.inbox)
            # Checked as given (a dangling link is no inbox to make), then followed: the
            # journal keys jobs by the photo's folder resolved (journal.photo_key).
            resolved = folder_key(s.inbox)
            if resolved != s.inbox:
                s = self.settings = replace(s, inbox=resolved, inbox_as_given=s.inbox)
            outbox = folder_key(s.outbox)  # inside the inbox, it is no subfolder to warn of
            self.inbox = InboxTracker(s.inbox, s.settle_s, (outbox.name,)
                                      if outbox.parent == s.inbox else ())
            for name in (DONE_FOLDER, FAILED_FOLDER):  # else a traceback after the first clip
                where = s.inbox / name
                if (where.exists() or where.is_symlink()) and not where.is_dir():
                    raise OutputFolderError(f"{where}: not a folder; the daemon moves finished "
                                            f"photos into {name}/ in the inbox: move this file "
                                            "away")
            inbox_lock = FolderLock(s.inbox, "watching")
            refused = False
            try:
                return self.serve()
            finally:
                inbox_lock.release()
        finally:
            outbox_lock.release()
            for folder in made if refused else ():
                with contextlib.suppress(OSError):
                    folder.rmdir()

    def serve(self) -> int:
        s = self.settings
        keep_sources, failure_reports = s.keep_sources, s.inbox / FAILED_FOLDER
        if not folder_is_writable(s.inbox):
            log.warning("%s is read-only: photos stay where they are (as with --keep-sources) "
                        "and failure reports go to %s", s.inbox, s.outbox / FAILED_FOLDER)
            keep_sources, failure_reports = True, s.outbox / FAILED_FOLDER
        journal = Journal(s.outbox)
        note_inbox(s.outbox, s.inbox, s.manifest.path if s.manifest else None)
        jobs = self.jobs = JobRunner(s, journal, keep_sources, failure_reports,
                                     self.inbox.notice)
        jobs.recover()
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        # a hang-up (the SSH session it was started from dropped) stops it as SIGTERM does:
        # it killed the daemon at once, a partial clip left and nothing logged
        if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # `nohup`: ignored
            signal.signal(signal.SIGHUP, self.request_stop)
        observer = start_observer(s.inbox, s.poll, self.inbox.notice, self.inbox.notice_removal,
                                  self.inbox.notice_rename)
        for path in sorted(s.inbox.iterdir()):
            self.inbox.notice(path)
        threads = max(1, (os.cpu_count() or 1) // s.jobs)
        options = replace(s.options, threads=threads)
        log.info("watching %s -> %s (preset %s, %d job(s), %s, frames on %s)", s.inbox,
                 s.outbox, s.preset.name, s.jobs, "polling" if s.poll else "inotify",
                 options.device)
        jobs.pool = jobs.new_pool()
        exit_code = 0
        try:
            while not self.stopping.is_set() or jobs.in_flight:
                gone = jobs.folders_gone()
                if gone and not self.stopping.is_set():
                    log.error("%s while the daemon ran; stopping (photos not made stay in "
                              "the inbox): start it again on the folders as they are now", gone)
                    exit_code = 1
                    self.stopping.set()
                try:
                    self.inbox.collect_events()
                    jobs.file_late_maps(self.inbox.settled_lone_maps())
                    jobs.submit_ready(self.inbox, options, self.stopping)
                    jobs.finish_completed(self.inbox.removed, self.inbox.renamed_to,
                                          self.inbox.forget_if_waiting)
                    jobs.file_suspects()
                except JournalError as error:
                    log.error("%s; pausing %.0f s, then retrying (nothing is lost)", error,
                              JOURNAL_RETRY_S)
                    self.stopping.wait(JOURNAL_RETRY_S)
                time.sleep(LOOP_INTERVAL_S)
        finally:
            jobs.pool.shutdown(wait=True)
        # watchdog's inotify thread, stopped while it waits for an event, logs a spurious
        # "queue_events() called when the thread is inactive" error; nothing is wrong then.
        logging.getLogger("watchdog.observers.inotify").setLevel(logging.CRITICAL)
        observer.stop()
        observer.join()
        journal.close()
        log.info("stopped")
        return exit_code


def start_observer(inbox: Path, poll: bool, notice: Callable[[Path, bool], None],
                   notice_removal: Callable[[Path], None],
                   notice_rename: Callable[[Path, Path], None]):
    """watchdog's observer of the inbox (inotify, or polling for network shares), calling
    notice(path, renamed), notice_removal(path) and notice_rename(old, new) from its own
    thread."""
    from watchdog.events import FileSystemEventHandler
    from watchdog.observers import Observer
    from watchdog.observers.polling import PollingObserver

    class Handler(FileSystemEventHandler):
        def on_created(self, event):
            notice(Path(event.src_path), False)

        def on_modified(self, event):
            if not event.is_directory:
                notice(Path(event.src_path), False)

        def on_moved(self, event):
            if not event.is_directory:
                notice_removal(Path(event.src_path))  # renamed away: its name is free
                notice_rename(Path(event.src_path), Path(event.dest_path))
            notice(Path(event.dest_path), True)

        def on_deleted(self, event):
            if not event.is_directory:
                notice_removal(Path(event.src_path))

    observer = PollingObserver(timeout=0.5) if poll else Observer()
    observer.schedule(Handler(), str(inbox), recursive=False)
    observer.start()
    return observer


def watch(settings: WatchSettings) -> int:
    return Daemon(settings).run()


def _folder_in_use(outbox: Path) -> bool:
    """Whether a batch or daemon holds the output folder's lock now."""
    try:
        FolderLock(outbox, "writing clips into", wait_s=0.0).release()
    except FolderBusyError:
        return True
    return False


def note_inbox(outbox: Path, inbox: Path, manifest: Path | None) -> None:
    """Written at the daemon's start (see INBOX_NOTE), with the manifest it follows (whose
    excluded photos and depth maps wait for nothing); a failure to write it costs only that."""
    note = {"inbox": str(inbox)} | ({"manifest": str(manifest.absolute())} if manifest else {})
    path = outbox / INBOX_NOTE
    if unreplaceable(path):  # another user's daemon's, in a sticky folder: one of this user's
        path = outbox / f"{INBOX_NOTE.removesuffix('.json')}.{os.geteuid()}.json"
    try:
        with atomic_output(path, ".json", make_folder=False) as temp_path:
            temp_path.write_text(json.dumps(note), encoding="utf-8")
    except OSError as error:
        log.warning("%s: cannot be written (%s); `kbbatch status` will not count the photos "
                    "waiting in the inbox", path, error.strerror or error)


def latest_inbox_note(outbox: Path) -> Path:
    """The note of the daemon that started last here: the users' notes of a sticky folder
    (note_inbox) beside the first one, which read alone counted the first user's inbox for a
    colleague's daemon."""
    stem = INBOX_NOTE.removesuffix(".json")
    notes = [outbox / INBOX_NOTE, *outbox.glob(f"{glob.escape(stem)}.*.json")]

    def written_ns(note: Path) -> int:
        try:
            return note.lstat().st_mtime_ns
        except OSError:
            return -1

    return max(notes, key=written_ns)


MISSING_NAMED_MAX = 3
"""`kbbatch status` names at most this many clips deleted by hand, then counts the rest."""


def missing_clip_lines(outbox: Path, journal: Journal) -> list[str]:
    """Clips the journal counts done that are no longer in the folder (deleted by hand), or
    no longer of the size written (cut short, or a file saved over them): status read as if
    every clip were there and whole. Those of photos still where they were are made again
    by the next run of their folder."""
    missing, changed = [], []
    for job in journal.jobs("done"):
        # a daemon's (one of a version that wrote no note of its inbox) is not followed
        if (not job.output or not os.path.lexists(job.source)
                or Path(job.source).parent.name in (DONE_FOLDER, FAILED_FOLDER)):
            continue
        try:
            size = (outbox / job.output).stat().st_size
        except FileNotFoundError:
            missing.append(job.output)
            continue
        except OSError:
            continue
        if clip_size(job.clip) not in (None, size):
            changed.append(job.output)

    def line(word: str, names: list[str], what: str, then: str) -> list[str]:
        if not names:
            return []
        more = len(names) - MISSING_NAMED_MAX
        return [f"{word} {len(names)} clip(s) counted done {what}: "
                + ", ".join(sorted(names)[:MISSING_NAMED_MAX])
                + (f" and {more} more" if more > 0 else "") + f"; {then}"]

    return (line("MISSING", missing, f"are not in {outbox} (deleted?)",
                 "the next run of their photos' folder makes them again")
            + line("CHANGED", changed, "are not as written (cut short, or saved over?)",
                   "the next run of their photos' folder makes them again (beside a file "
                   "of yours, never over it)"))


def waiting_in_inbox(outbox: Path, journal: Journal) -> tuple[Path, list[Path]] | None:
    """The inbox of the daemon that writes into outbox, and its photos no job has been
    started for yet: they waited there while `kbbatch status` said "queued 0"."""
    try:
        noted = read_note(latest_inbox_note(outbox))
        inbox = Path(noted["inbox"])
        photos = scan_folder(inbox).photos if inbox.is_dir() else []
        manifest_path = noted.get("manifest")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # no daemon wrote here, or its note is not ours
    manifest = None
    if isinstance(manifest_path, str):
        with contextlib.suppress(ManifestError, OSError):
            manifest = load_manifest(Path(manifest_path))

    def passed_over(photo: Path) -> bool:
        """Excluded by the daemon's manifest, or named there as a depth map: never taken."""
        if manifest is None:
            return False
        entry = manifest.entry(photo.name, photo.parent)
        return (entry is not None and entry.excluded) or bool(manifest.depth_map_of(photo))

    return inbox, [photo for photo in photos
                   if journal.get(photo) is None and not passed_over(photo)]


def status_lines(outbox: Path, failed_before_jobs: Sequence[tuple[str, str]] = ()
                 ) -> list[str]:
    """The journal's counts and failures, for `kbbatch status`; failed_before_jobs: the last
    run's failures, each (source, error), found before a job began (batch.failed_before_a_job),
    said instead of an earlier failure of the same photo's job."""
    journal = Journal(outbox, read_only=True)
    try:
        counts = journal.counts()
        newer = {source: error for source, error in failed_before_jobs}
        failed = [job for job in journal.jobs("failed") if str(job.source) not in newer]
        counts["failed"] = len(failed) + len(newer)
        waiting = waiting_in_inbox(outbox, journal)
        if waiting and waiting[1]:
            counts["queued"] += len(waiting[1])
        lines = [", ".join(f"{state} {count}" for state, count in counts.items())]
        if waiting and waiting[1]:
            lines.append(f"WAITING {len(waiting[1])} photo(s) in the inbox {waiting[0]}, "
                         + ("taken as they settle" if _folder_in_use(outbox)
                            else "taken when the daemon runs again"))
        lines += [f"FAILED {job.source}: {(job.error or '').removeprefix(f'{job.source}: ')}"
                  for job in failed]  # errors most often begin with the path
        lines += [f"FAILED {source}: {error.removeprefix(f'{source}: ')} (in the last run, "
                  "before its job began)" for source, error in newer.items()]
        lines += [f"QUEUED {job.source} ({job.error})" for job in journal.jobs("queued")]
        if waiting is None:  # a batch's folder (a daemon's clips are taken away as made)
            lines += missing_clip_lines(outbox, journal)
        elif not waiting[0].is_dir():  # said as if no photo waited there
            lines.append(f"NOTE the daemon's inbox {waiting[0]} is not there (renamed or "
                         "removed?): give `kbbatch watch` its new name")
        running = journal.jobs("running")
        if running and not _folder_in_use(outbox):  # its run was killed (kill -9, power cut)
            lines += [f"INTERRUPTED {job.source} (no kbbatch is working in this folder; the "
                      "next run or start takes it again)" for job in running]
        else:
            lines += [f"RUNNING {job.source} (attempt {job.attempts})" for job in running]
        return lines
    finally:
        journal.close()
