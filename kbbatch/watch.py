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
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from kbbatch import models
from kbbatch.batch import (
    ClipOptions,
    ClipResult,
    check_writable,
    clip_settings,
    make_clip,
    remove_stale_scratch,
)
from kbbatch.images import is_image_file
from kbbatch.journal import Journal, source_fingerprint
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


def _worker_init(jobs: int = 1) -> None:
    """Workers leave signals to the daemon and die with it (no orphan finishing a clip)."""
    models.share_cores(jobs)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # Not on Linux: a killed daemon's worker may finish its clip; recovery copes with that.
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _render(source: Path, output: Path, preset: Preset, options: ClipOptions,
            entry: ManifestEntry | None) -> ClipResult:
    return make_clip(source, output, preset, options, show_progress=False, entry=entry)


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


class Daemon:
    def __init__(self, settings: WatchSettings) -> None:
        self.settings = settings
        self.stopping = threading.Event()
        self.events: queue.Queue[tuple[Path, bool]] = queue.Queue()
        self.pending: dict[Path, tuple[int, int, float, bool]] = {}
        self.in_flight: dict[Future, tuple[Path, str]] = {}
        self.journal: Journal | None = None

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
        self.journal = Journal(s.outbox)
        self.recover()
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        observer = self.start_observer()
        for path in sorted(s.inbox.iterdir()):
            self.events.put((path, False))
        threads = max(1, (os.cpu_count() or 1) // s.jobs)
        options = replace(s.options, threads=threads)
        log.info("watching %s -> %s (preset %s, %d job(s), %s)", s.inbox, s.outbox,
                 s.preset.name, s.jobs, "polling" if s.poll else "inotify")
        with ProcessPoolExecutor(max_workers=s.jobs, initializer=_worker_init,
                                 initargs=(s.jobs,)) as pool:
            while not self.stopping.is_set():
                self.collect_events()
                self.submit_ready(pool, options)
                self.finish_completed()
                time.sleep(LOOP_INTERVAL_S)
            while self.in_flight:
                self.finish_completed()
                time.sleep(LOOP_INTERVAL_S)
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
                if not event.is_directory:
                    events.put((Path(event.src_path), False))

            def on_modified(self, event):
                if not event.is_directory:
                    events.put((Path(event.src_path), False))

            def on_moved(self, event):
                if not event.is_directory:
                    events.put((Path(event.dest_path), True))

        observer = PollingObserver(timeout=0.5) if self.settings.poll else Observer()
        observer.schedule(Handler(), str(self.settings.inbox), recursive=False)
        observer.start()
        return observer

    # --- recovery --------------------------------------------------------------------------
    def recover(self) -> None:
        """After a crash: drop partial clips, and settle jobs whose clip was already renamed."""
        s = self.settings
        for partial in s.outbox.glob(".*.part*"):
            log.info("removing partial file %s from an interrupted run", partial.name)
            partial.unlink(missing_ok=True)
        for scratch in remove_stale_scratch():
            log.info("removed %s, left by a killed worker", scratch)
        for job in self.journal.jobs("running"):
            source = s.inbox / job.source
            output = s.outbox / job.output if job.output else None
            if output is not None and output.is_file() and source.is_file():
                # The clip was complete (renamed) before the crash; only the photo's move is left.
                self.journal.finish(job.source, "done", job.seconds or 0.0)
                self.move_source(source, DONE_FOLDER)
                log.info("recovered %s: clip was complete", job.source)
            else:
                log.info("resuming %s: interrupted before its clip was complete", job.source)

    # --- the loop --------------------------------------------------------------------------
    def collect_events(self) -> None:
        now = time.monotonic()
        while True:
            try:
                path, renamed = self.events.get_nowait()
            except queue.Empty:
                break
            if path.parent != self.settings.inbox or not is_candidate(path):
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

    def submit_ready(self, pool: ProcessPoolExecutor, options: ClipOptions) -> None:
        s = self.settings
        busy = {path for path, _ in self.in_flight.values()}
        for path in sorted(self.pending):
            if len(self.in_flight) >= s.jobs or self.stopping.is_set():
                return
            if path in busy or not self.is_ready(path):
                continue
            del self.pending[path]
            entry = s.manifest.entry(path.name) if s.manifest else None
            fingerprint = source_fingerprint(path)
            settings = clip_settings(s.preset, options, entry)
            output = self.output_for(path)
            if self.journal.is_up_to_date(path.name, fingerprint, settings, output):
                log.info("%s: clip already complete, moving the photo", path.name)
                self.move_source(path, DONE_FOLDER)
                continue
            self.journal.start(path.name, fingerprint, settings, output.name)
            log.info("start %s", path.name)
            future = pool.submit(_render, path, output, s.preset, options, entry)
            self.in_flight[future] = (path, output.name)

    def output_for(self, source: Path) -> Path:
        """The photo's stem, unless another photo's clip already has that name."""
        taken = self.journal.outputs_taken()
        name = source.stem + ".mp4"
        if taken.get(name, source.name) != source.name:
            name = source.name + ".mp4"
        return self.settings.outbox / name

    def finish_completed(self) -> None:
        for future in [f for f in self.in_flight if f.done()]:
            path, _ = self.in_flight.pop(future)
            try:
                result = future.result()
            except Exception as error:  # the worker itself died
                result = ClipResult(str(path), None, "failed", 0.0,
                                    error=f"{path}: worker failed: {error}")
            if result.status == "done":
                self.journal.finish(path.name, "done", result.seconds)
                self.move_source(path, DONE_FOLDER)
                log.info("done %s in %.1f s -> %s", path.name, result.seconds, result.output)
            else:
                self.journal.finish(path.name, "failed", result.seconds, result.error)
                moved = self.move_source(path, FAILED_FOLDER)
                self.write_failure_report(moved or path, result)
                log.warning("failed %s: %s", path.name, result.error)

    def move_source(self, path: Path, folder: str) -> Path | None:
        if self.settings.keep_sources and folder == DONE_FOLDER:
            return None
        if not path.exists():
            return None
        destination = unique_destination(self.settings.inbox / folder, path.name)
        shutil.move(str(path), destination)
        return destination

    def write_failure_report(self, photo: Path, result: ClipResult) -> None:
        report = photo.with_name(photo.name + ".error.json")
        data = {"photo": photo.name, "error": result.error, "detail": result.detail,
                "result": asdict(result)}
        report.write_text(json.dumps(data, indent=2), encoding="utf-8")


def watch(settings: WatchSettings) -> int:
    return Daemon(settings).run()


def status_lines(outbox: Path) -> list[str]:
    """The journal's counts and failures, for `kbbatch status`."""
    journal = Journal(outbox)
    try:
        counts = journal.counts()
        lines = [", ".join(f"{state} {count}" for state, count in counts.items())]
        lines += [f"FAILED {job.source}: {job.error}" for job in journal.jobs("failed")]
        lines += [f"RUNNING {job.source} (attempt {job.attempts})"
                  for job in journal.jobs("running")]
        return lines
    finally:
        journal.close()
