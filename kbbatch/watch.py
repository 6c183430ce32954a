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
import json
import logging
import os
import queue
import shutil
import signal
import tempfile
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from kbbatch import models
from kbbatch.batch import (
    ClipOptions,
    ClipResult,
    check_writable,
    clip_fingerprint,
    make_clip,
    output_names,
    remove_partial_clips,
    remove_stale_scratch,
)
from kbbatch.fingerprint import file_sha256
from kbbatch.images import atomic_output, is_image_file, scan_folder, unreadable_reason
from kbbatch.journal import (
    FolderLock,
    Journal,
    JournalError,
    source_fingerprint,
)
from kbbatch.manifest import Manifest, ManifestEntry
from kbbatch.presets import Preset

log = logging.getLogger("kbbatch.watch")

DONE_FOLDER = "done"
FAILED_FOLDER = "failed"
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


def is_candidate(path: Path) -> bool:
    """A photo to consider: an image, not hidden, not a temporary download."""
    name = path.name.lower()
    return is_image_file(path) and not name.endswith(TEMPORARY_SUFFIXES)


REWRITE_GRACE_S = 10.0
"""A photo that fails while it was modified this recently (at least 5 settle times) is not filed
away yet: a writer that paused longer than the settle time may still finish it."""

WORKER_DEATHS_TO_FAIL = 2
"""A photo whose worker process dies this often (while it runs alone) fails; others are retried."""

JOURNAL_RETRY_S = 10.0
"""How long the daemon pauses when its journal cannot be written (a full disk) before retrying."""


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
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
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
    while candidate.exists():
        candidate = folder / f"{stem}.{counter}{suffix}"
        counter += 1
    return candidate


def folder_is_writable(folder: Path) -> bool:
    """Whether files can be created and moved in a folder (a read-only mount says no, even to
    root, where the permission bits would say yes)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".kbbatch-write-test-"):
            return True
    except OSError:
        return False


@dataclass(frozen=True)
class InFlight:
    path: Path
    fingerprint: str  # size and time when taken: a change since means it was still written
    output: str
    preferred: str
    renamed: bool


@dataclass(frozen=True)
class Suspect:
    """A failed photo modified recently: filed away only if it stays unchanged until `until`."""

    result: ClipResult
    fingerprint: str
    until: float


class Daemon:
    def __init__(self, settings: WatchSettings) -> None:
        # absolute: the journal keys jobs by the photo's path
        settings = replace(settings, inbox=settings.inbox.absolute(),
                           outbox=settings.outbox.absolute())
        self.settings = settings
        self.stopping = threading.Event()
        self.events: queue.Queue[tuple[Path, bool]] = queue.Queue()
        self.pending: dict[Path, tuple[int, int, float, bool]] = {}
        self.in_flight: dict[Future, InFlight] = {}
        self.suspects: dict[Path, Suspect] = {}
        self.journal: Journal | None = None
        self.keep_sources = settings.keep_sources
        self.failure_reports = settings.inbox / FAILED_FOLDER
        self.mentioned: set[Path] = set()  # subfolders and broken links already logged
        self.worker_deaths: dict[Path, int] = {}  # photos in flight when a worker died
        self.pool: ProcessPoolExecutor | None = None

    # --- lifecycle -------------------------------------------------------------------------
    def request_stop(self, *_: object) -> None:
        if not self.stopping.is_set():
            log.info("stopping: no new work; finishing %d clip(s) in progress",
                     len(self.in_flight))
        self.stopping.set()

    def run(self) -> int:
        s = self.settings
        check_writable(s.outbox)
        s.inbox.mkdir(parents=True, exist_ok=True)
        locks = [FolderLock(s.inbox, "watching"), FolderLock(s.outbox, "writing clips into")]
        try:
            return self.serve()
        finally:
            for lock in locks:
                lock.release()

    def serve(self) -> int:
        s = self.settings
        if not folder_is_writable(s.inbox):
            log.warning("%s is read-only: photos stay where they are (as with --keep-sources) "
                        "and failure reports go to %s", s.inbox, s.outbox / FAILED_FOLDER)
            self.keep_sources = True
            self.failure_reports = s.outbox / FAILED_FOLDER
        self.journal = Journal(s.outbox)
        self.recover()
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        observer = self.start_observer()
        for path in sorted(s.inbox.iterdir()):
            self.events.put((path, False))
        threads = max(1, (os.cpu_count() or 1) // s.jobs)
        options = replace(s.options, threads=threads)
        log.info("watching %s -> %s (preset %s, %d job(s), %s, frames on %s)", s.inbox,
                 s.outbox, s.preset.name, s.jobs, "polling" if s.poll else "inotify",
                 options.device)
        self.pool = self.new_pool()
        try:
            while not self.stopping.is_set() or self.in_flight:
                try:
                    self.collect_events()
                    self.submit_ready(options)
                    self.finish_completed()
                    self.file_suspects()
                except JournalError as error:
                    log.error("%s; pausing %.0f s, then retrying (nothing is lost)", error,
                              JOURNAL_RETRY_S)
                    self.stopping.wait(JOURNAL_RETRY_S)
                time.sleep(LOOP_INTERVAL_S)
        finally:
            self.pool.shutdown(wait=True)
        # watchdog's inotify thread, stopped while it waits for an event, logs a spurious
        # "queue_events() called when the thread is inactive" error; nothing is wrong then.
        logging.getLogger("watchdog.observers.inotify").setLevel(logging.CRITICAL)
        observer.stop()
        observer.join()
        self.journal.close()
        log.info("stopped")
        return 0

    def start_observer(self):
        from watchdog.events import FileSystemEventHandler
        from watchdog.observers import Observer
        from watchdog.observers.polling import PollingObserver

        events = self.events

        class Handler(FileSystemEventHandler):
            def on_created(self, event):
                events.put((Path(event.src_path), False))

            def on_modified(self, event):
                if not event.is_directory:
                    events.put((Path(event.src_path), False))

            def on_moved(self, event):
                events.put((Path(event.dest_path), True))

        observer = PollingObserver(timeout=0.5) if self.settings.poll else Observer()
        observer.schedule(Handler(), str(self.settings.inbox), recursive=False)
        observer.start()
        return observer

    # --- recovery --------------------------------------------------------------------------
    def recover(self) -> None:
        """After a crash: drop partial clips, and settle jobs whose clip was already renamed."""
        s = self.settings
        for partial in remove_partial_clips(s.outbox):
            log.info("removed partial file %s from an interrupted run", partial.name)
        for scratch in remove_stale_scratch():
            log.info("removed %s, left by a killed worker", scratch)
        for job in self.journal.jobs("running"):
            source = Path(job.source)
            output = s.outbox / job.output if job.output else None
            if output is not None and output.is_file() and source.is_file():
                # The clip was complete (renamed) before the crash; only the photo's move is left.
                self.journal.finish(source, "done", job.seconds or 0.0, None,
                                    source_fingerprint(output))
                self.move_source(source, DONE_FOLDER)
                log.info("recovered %s: clip was complete", job.name)
            else:
                log.info("resuming %s: interrupted before its clip was complete", job.name)

    # --- the loop --------------------------------------------------------------------------
    def collect_events(self) -> None:
        now = time.monotonic()
        while True:
            try:
                path, renamed = self.events.get_nowait()
            except queue.Empty:
                break
            if path.parent != self.settings.inbox or not self.usable(path):
                continue
            try:
                stat = path.stat()
            except FileNotFoundError:
                self.pending.pop(path, None)
                continue
            previous = self.pending.get(path)
            changed = previous is None or previous[:2] != (stat.st_size, stat.st_mtime_ns)
            since = now if changed else previous[2]
            self.pending[path] = (stat.st_size, stat.st_mtime_ns, since,
                                  renamed or (previous[3] if previous else False))

    def usable(self, path: Path) -> bool:
        """A photo to take; a subfolder or a broken link is said once in the log."""
        if path.name in (DONE_FOLDER, FAILED_FOLDER) or path.name.startswith("."):
            return False
        if path.is_dir() or (is_candidate(path) and path.is_symlink() and not path.exists()):
            if path not in self.mentioned:
                self.mentioned.add(path)
                what = ("subfolders are not watched; move its photos into the inbox"
                        if path.is_dir() else "broken symbolic link, its target is missing")
                log.warning("%s: %s", path, what)
            return False
        return is_candidate(path)

    def is_ready(self, path: Path) -> bool:
        size, mtime_ns, since, renamed = self.pending[path]
        try:
            stat = path.stat()
        except FileNotFoundError:
            return False
        if (stat.st_size, stat.st_mtime_ns) != (size, mtime_ns):
            self.pending[path] = (stat.st_size, stat.st_mtime_ns, time.monotonic(), False)
            return False
        return renamed or time.monotonic() - since >= self.settings.settle_s

    def new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=self.settings.jobs, initializer=_worker_init,
                                   initargs=(self.settings.jobs,))

    def submit_ready(self, options: ClipOptions) -> None:
        s = self.settings
        busy = {job.path for job in self.in_flight.values()} | set(self.suspects)
        for path in sorted(self.pending, key=lambda p: (p not in self.worker_deaths, p)):
            if len(self.in_flight) >= s.jobs or self.stopping.is_set():
                return
            if any(job.path in self.worker_deaths for job in self.in_flight.values()):
                return  # a photo whose worker died runs alone, so a second death is its own
            if path in self.worker_deaths and self.in_flight:
                return
            if path in busy or not self.is_ready(path):
                continue
            renamed = self.pending[path][3]
            entry = s.manifest.entry(path.name) if s.manifest else None
            try:
                fingerprint = source_fingerprint(path)
                content = file_sha256(path)
                settings = clip_fingerprint(path, content, s.preset, options, entry)
            except OSError as error:
                del self.pending[path]
                result = ClipResult(str(path), None, "failed", 0.0,
                                    error=f"{error.filename or path}: {unreadable_reason(error)}")
                self.file_failure(path, result)
                continue
            preferred = self.preferred_name(path)
            name = self.journal.clip_name(path, content, preferred, s.outbox)
            output = s.outbox / name
            if self.journal.is_up_to_date(path, fingerprint, settings, output):
                del self.pending[path]
                log.info("%s: clip already complete, moving the photo", path.name)
                self.move_source(path, DONE_FOLDER)
                continue
            self.journal.start(path, fingerprint, settings, name, content)
            del self.pending[path]
            if name != preferred:
                log.warning("%s: %s already holds a clip of another photo; this one is named "
                            "by its content: %s", path.name, preferred, name)
            log.info("start %s", path.name)
            try:
                future = self.pool.submit(_render, path, output, s.preset, options, entry)
            except BrokenProcessPool:  # broke since the last look: its jobs come back below
                self.journal.finish(path, "queued", 0.0, "worker pool broken; retrying")
                self.events.put((path, True))
                return
            self.in_flight[future] = InFlight(path, fingerprint, name, preferred, renamed)

    def preferred_name(self, source: Path) -> str:
        """The batch's rule: the stem, or the full name while another photo in the inbox
        shares the stem."""
        siblings = [p for p in scan_folder(self.settings.inbox).photos
                    if p.stem.lower() == source.stem.lower() and p != source]
        return output_names([source, *siblings])[source]

    def finish_completed(self) -> None:
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
            if self.changed_since_taken(job):
                self.journal.finish(job.path, "queued", result.seconds,
                                    "changed while being processed")
                del self.in_flight[future]
                log.warning("%s changed while it was processed (still being written?): "
                            "taken again once it settles", job.path.name)
                self.events.put((job.path, False))
                continue
            self.worker_deaths.pop(job.path, None)
            clip = None
            if result.status == "done":
                with contextlib.suppress(OSError):
                    clip = source_fingerprint(self.settings.outbox / job.output)
            self.journal.finish(job.path, result.status, result.seconds, result.error, clip)
            del self.in_flight[future]
            if result.status == "done":
                self.move_source(job.path, DONE_FOLDER)
                log.info("done %s in %.1f s -> %s", job.path.name, result.seconds,
                         result.output)
            elif not job.renamed and self.recently_written(job.path):
                grace = max(REWRITE_GRACE_S, 5 * self.settings.settle_s)
                self.suspects[job.path] = Suspect(result, job.fingerprint,
                                                  time.monotonic() + grace)
                log.info("%s failed but was written %.0f s ago or less; filed as failed only "
                         "if it stays unchanged that long", job.path.name, grace)
            else:
                self.file_failure(job.path, result)

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
            self.events.put((job.path, True))

    def changed_since_taken(self, job: InFlight) -> bool:
        try:
            return source_fingerprint(job.path) != job.fingerprint
        except FileNotFoundError:
            return False

    def recently_written(self, path: Path) -> bool:
        try:
            age_s = time.time() - path.stat().st_mtime
        except FileNotFoundError:
            return False
        return age_s < max(REWRITE_GRACE_S, 5 * self.settings.settle_s)

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
                self.events.put((path, False))
            elif time.monotonic() >= suspect.until:
                del self.suspects[path]
                self.file_failure(path, suspect.result)

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
        destination = unique_destination(self.settings.inbox / folder, path.name)
        try:
            shutil.move(str(path), destination)
        except OSError as error:
            log.error("%s: cannot be moved to %s/ (%s); it stays in the inbox", path, folder,
                      error.strerror or error)
            return None
        self.journal.moved(path, destination)
        return destination

    def write_failure_report(self, photo: Path, result: ClipResult) -> None:
        folder = photo.parent if photo.parent.name == FAILED_FOLDER else self.failure_reports
        report = unique_destination(folder, photo.name + ".error.json")
        data = {"photo": str(photo), "error": result.error, "detail": result.detail,
                "result": asdict(result)}
        try:
            with atomic_output(report, ".json") as temp_path:
                temp_path.write_text(json.dumps(data, indent=2), encoding="utf-8")
        except OSError as error:
            log.error("%s: failure report cannot be written (%s)", report,
                      error.strerror or error)


def watch(settings: WatchSettings) -> int:
    return Daemon(settings).run()


def status_lines(outbox: Path) -> list[str]:
    """The journal's counts and failures, for `kbbatch status`."""
    journal = Journal(outbox)
    try:
        counts = journal.counts()
        lines = [", ".join(f"{state} {count}" for state, count in counts.items())]
        lines += [f"FAILED {job.source}: {job.error}" for job in journal.jobs("failed")]
        lines += [f"QUEUED {job.source} ({job.error})" for job in journal.jobs("queued")]
        lines += [f"RUNNING {job.source} (attempt {job.attempts})"
                  for job in journal.jobs("running")]
        return lines
    finally:
        journal.close()
