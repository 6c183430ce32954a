"""A folder of photos to a folder of clips: the batch runner (journal, lock, report, executor).

Each clip is made by kbbatch.pipeline.make_clip, here (LocalExecutor) or through an executor
such as kbbatch.ray_executor.RayExecutor.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from kbbatch.camera import working_size
from kbbatch.depth import DepthError
from kbbatch.images import (
    LONE_MAP_REASON,
    NAME_END_REASON,
    OLD_PLAN_SHEET_REASON,
    PHOTO_KINDS,
    UNREAD_FORMAT_REASON,
    FolderScan,
    ImageReadError,
    atomic_output,
    broken_link_reason,
    is_image_file,
    read_photo,
    scan_folder,
    upright_size,
)
from kbbatch.interrupts import interrupted
from kbbatch.manifest import (
    CropAspectError,
    Manifest,
    ManifestEntry,
    ManifestError,
    loose_name,
)
from kbbatch.models import providers_used
from kbbatch.outputs import (
    OutputFolderError,
    check_writable,
    folder_identity,
    moved_to,
    name_job,
    output_names,
    remove_partial_clips,
    replaced_clip_note,
    unreplaceable,
)
from kbbatch.pipeline import (
    CLIP_SUFFIX,
    ClipExecutor,
    ClipJob,
    ClipOptions,
    ClipResult,
    CropTooSmallError,
    LocalExecutor,
    apply_entry,
    check_depth_is_not_the_photo,
    check_photo_size,
    clip_fingerprints,
    joined_notes,
    plan_photo,
    progress_bar,
    remove_stale_scratch,
    working_depth,
)
from kbbatch.presets import Preset

CORES_PER_JOB = 4
"""A clip already renders its frames on every core; a second photo in parallel pays only when
there are cores to spare (issue 14: on 2 cores, 2 jobs gained 5 % over 1 on 12 photos)."""

MEMORY_PER_JOB_GIB = 3
"""A worker holds a few GB with the models loaded (issue 14 saw 2.4 GB idle)."""


def default_jobs() -> int:
    """Photos processed in parallel by default, sized from the cores and the memory."""
    cores = os.cpu_count() or 1
    try:
        memory_gib = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30
    except (ValueError, OSError):
        memory_gib = MEMORY_PER_JOB_GIB
    return max(1, min(cores // CORES_PER_JOB, int(memory_gib // MEMORY_PER_JOB_GIB)))




@dataclass
class RunReport:
    folder: str
    output_folder: str
    preset: str
    results: list[ClipResult]
    notes: list[str] = field(default_factory=list)  # what was passed over, and why
    stopped_by: str | None = None  # what ended the run early: a signal, a full disk
    device: str = "cpu"  # the --device setting; each clip says where it was rendered
    onnx_providers: dict[str, str] = field(default_factory=dict)
    """Each ONNX model this run used, and the onnxruntime provider its session ran on."""
    started_at: str = ""  # UTC, ISO 8601
    finished_at: str | None = None
    """None in the report written as the run starts: left so, the run was killed (or runs)."""
    not_started: list[str] = field(default_factory=list)
    """Photos a stop (a signal, a full disk) left before they were begun: a stopped run's
    report listed only the clips it made, and looked complete."""
    unwritten: str | None = None
    """Why the report itself could not be written, if so (the run is then incomplete)."""
    made_before: list[dict] = field(default_factory=list)
    """While the run is unfinished: what earlier reports said of the clips it has not reached
    (a run killed outright left a report without them, and the next run reported each clip
    it skipped as 0 frames, with no plan)."""
    journal_id: str | None = None
    """The output folder's journal's id: the report is known as the folder's after the folder
    was moved or renamed (it names the folder it was written in)."""

    @property
    def failed(self) -> list[ClipResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def no_space(self) -> list[ClipResult]:
        """Clips their full disk could not take: queued for the next run."""
        return [r for r in self.results if r.status == "no_space"]

    @property
    def interrupted(self) -> list[ClipResult]:
        """Clips whose encoder a stop signal ended: queued for the next run."""
        return [r for r in self.results if r.status == "interrupted"]

    def to_json(self) -> str:
        return json.dumps(
            {"folder": self.folder, "output_folder": self.output_folder, "preset": self.preset,
             "started_at": self.started_at, "finished_at": self.finished_at,
             "stopped_by": self.stopped_by, "not_started": self.not_started,
             "notes": self.notes, "device": self.device,
             "onnx_providers": self.onnx_providers, "journal_id": self.journal_id,
             "clips": [asdict(r) for r in self.results]}
            | ({"made_before": self.made_before} if self.made_before else {}), indent=2,
        )

    def write(self, output_folder: Path) -> str | None:
        """Written atomically into output_folder (report_path); why not, if it could not be.
        A file of another's found under the report's name (at the start or later) is said in
        the notes the report carries."""
        path = report_path(output_folder)
        if path is None:
            return (f"{output_folder / REPORT_NAME} and {output_folder / OTHER_REPORT_NAME}: "
                    "files of another's (not this folder's run reports, or another user's in "
                    "a sticky folder); kept, so no report was written")
        note = foreign_report_note(output_folder, path)
        if path.name != REPORT_NAME and note not in self.notes:
            self.notes.append(note)
        try:
            # not made again: a folder removed mid-run is the user's doing (see FOLDER_GONE)
            with atomic_output(path, ".json", make_folder=False) as temp_path:
                temp_path.write_text(self.to_json(), encoding="utf-8")
            _written_here[str(path)] = _stamp(path)
        except OSError as error:
            return f"{path}: report could not be written ({error.strerror or error})"
        if path.name == REPORT_NAME and self.finished_at is not None:
            other = output_folder / OTHER_REPORT_NAME  # this run's report is here now
            if is_run_report(other, output_folder):
                with contextlib.suppress(OSError):
                    other.unlink()
        return None


REPORT_NAME = "kbbatch-report.json"

OTHER_REPORT_NAME = "kbbatch-run-report.json"
"""The run report's name where a file of another's has REPORT_NAME (a file kbbatch did not
write is never replaced: a user's notes there were overwritten by the report)."""

REPORT_READ_MAX_BYTES = 1 << 30
"""A file under a report's name larger than this is taken for another's without reading it."""

_written_here: dict[str, tuple[int, int, int] | None] = {}
"""The reports this process wrote, by path: their stamp then (known its own without reading)."""


def _stamp(path: Path) -> tuple[int, int, int] | None:
    try:
        stat = path.lstat()
    except OSError:
        return None
    return stat.st_ino, stat.st_size, stat.st_mtime_ns


def foreign_report_note(output_folder: Path, written: Path | None) -> str:
    first = output_folder / REPORT_NAME
    why = unreplaceable(first) or (f"{first}: not this folder's run report (a file of yours, "
                                   "or a report copied from another folder); kept")
    return why + (f", this run's report is {written}" if written else "")


REPORT_KEYS = frozenset({"folder", "output_folder", "preset", "started_at", "clips"})
"""What every run report holds (the reports of earlier versions too)."""


def is_run_report(path: Path, output_folder: Path) -> bool:
    """Whether path is a run report of this output folder: a file of the user's that begins
    like one, or a report copied in from another folder, is not (both were overwritten). A
    folder moved or renamed is still the same: its journal, moved with it, has the id the
    report names."""
    stamp = _stamp(path)
    if stamp is None or os.path.islink(path) or not path.is_file():
        return False
    if _written_here.get(str(path)) == stamp:
        return True
    try:
        if stamp[1] > REPORT_READ_MAX_BYTES:
            return False
        report = json.loads(path.read_text(encoding="utf-8"))
        written_for = Path(report["output_folder"])
        if not (report.keys() >= REPORT_KEYS and written_for.is_absolute()):
            return False
        if written_for == output_folder or written_for.resolve() == output_folder.resolve():
            return True
        return report.get("journal_id") is not None and \
            report["journal_id"] == _journal_identity(output_folder)
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RuntimeError):
        return False


def _journal_identity(output_folder: Path) -> str | None:
    from kbbatch.journal import JOURNAL_NAME, Journal

    if not (output_folder / JOURNAL_NAME).is_file():
        return None
    try:
        journal = Journal(output_folder, read_only=True)
    except (sqlite3.Error, OSError):
        return None
    try:
        return journal.identity()
    finally:
        journal.close()


def report_path(output_folder: Path) -> Path | None:
    """Where the folder's run report goes: REPORT_NAME unless a file of another's is there,
    then OTHER_REPORT_NAME unless one is there too; None then."""
    for name in (REPORT_NAME, OTHER_REPORT_NAME):
        path = output_folder / name
        if ((not os.path.lexists(path) or is_run_report(path, output_folder))
                and unreplaceable(path) is None):  # another user's, in a sticky folder
            return path
    return None


CARRIED_FIELDS = ("preset", "depth_backend", "plan", "risk", "frames", "device")
"""What the report says of a clip skipped as up to date, from the report of the run that made
it: each re-run dropped the crops, depth backend and preset of every clip it skipped."""


def _last_report(output_folder: Path) -> dict:
    """The folder's last run report as it is on disk, under either name (the newer; {} where
    there is none it can read): a user's file removed, a report under the other name was
    never read again."""
    own = [path for path in (output_folder / REPORT_NAME, output_folder / OTHER_REPORT_NAME)
           if is_run_report(path, output_folder)]
    path = max(own, key=lambda path: path.stat().st_mtime_ns, default=None)
    try:
        report = json.loads(path.read_text(encoding="utf-8")) if path else {}
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) else {}


def _clips_of_last_report(output_folder: Path) -> dict[tuple[str, str], dict]:
    """The clips the folder's last report describes as made (or carried), by clip name and
    the sha256 of the photo's bytes, and by clip name and source (reports of versions that
    kept no sha256): keyed by source alone, a photo folder renamed or moved lost every
    skipped clip's crops, preset and depth backend from the reports, for good."""
    report = _last_report(output_folder)
    clips = report.get("made_before"), report.get("clips")  # the run's own last
    try:
        described = [clip for listed in clips for clip in listed or ()
                     if isinstance(clip, dict) and clip.get("status") in ("done", "skipped")
                     and clip.get("plan")]
        return ({(Path(clip.get("output") or "").name, str(clip["source"])): clip
                 for clip in described}
                | {(Path(clip.get("output") or "").name, str(clip["content"])): clip
                   for clip in described if clip.get("content")})
    except (KeyError, TypeError):
        return {}


def _as_made_before(result: ClipResult, made_before: dict[tuple[str, str], dict]
                    ) -> ClipResult:
    """A skipped clip with what the report of the run that made it said of it."""
    name = Path(result.output or "").name
    before = made_before.get((name, str(result.content))) or made_before.get(
        (name, result.source))
    if result.status != "skipped" or before is None:
        return result
    return replace(result, **{name: before.get(name) for name in CARRIED_FIELDS
                              if before.get(name) is not None})


def _renamed_to(manifest: Manifest, key: str, photos: list[Path],
                hashes: dict[Path, str | None]) -> str:
    """The photo whose bytes the entry under key was planned for (`photo_sha256`): the photo
    renamed since, its crops kept under the old name. hashes: each photo's sha256, as far as
    worked out (each photo is read once however many entries are looked for)."""
    photo = _photo_planned_for(manifest, key, photos, hashes)
    if photo is None:
        return ""
    return (f"; {photo.name!r} has the bytes it was planned for (renamed?): "
            + ("it has an entry of its own, so remove this one"
               if photo.name in manifest.entries else "give the entry its name"))


def _renamed_exclusions(manifest: Manifest | None, names: list[str], photos: list[Path],
                        hashes: dict[Path, str | None]) -> dict[Path, str]:
    """Photos without an entry of their own that have the bytes an excluded entry, whose photo
    is gone, was planned for (`photo_sha256`): the rejected photo renamed; each with that
    entry's name."""
    renamed = {}
    for name in names:
        photo = _photo_planned_for(manifest, name, photos, hashes)
        if photo is not None and photo.name not in manifest.entries:
            renamed[photo] = name
    return renamed


def _photo_planned_for(manifest: Manifest, key: str, photos: list[Path],
                       hashes: dict[Path, str | None]) -> Path | None:
    """The photo with the bytes the entry under key was planned for (`photo_sha256`)."""
    planned_for = manifest.entries[key].data.get("photo_sha256")
    return next((photo for photo in photos if planned_for
                 and _sha256_of(photo, hashes) == planned_for), None)


def _sha256_of(photo: Path, hashes: dict[Path, str | None]) -> str | None:
    """The photo's sha256 (None where it cannot be read), worked out once into hashes."""
    from kbbatch.fingerprint import file_sha256

    if photo not in hashes:
        try:
            hashes[photo] = file_sha256(photo)
        except OSError:
            hashes[photo] = None
    return hashes[photo]


def _nearly_named(key: str, photos: list[Path]) -> str:
    """The photo a manifest key names but for case, spaces around it or a folder before it:
    the entry's crops were silently not used, and the photo was planned instead."""
    wanted = loose_name(key)
    near = sorted(photo.name for photo in photos if loose_name(photo.name) == wanted)
    if not near:
        return ""
    return f"; {near[0]!r} is there: a key must be its photo's exact file name"


def last_run_lines(output_folder: Path) -> list[str]:
    """What the folder's run report says of the last batch run, when it did not finish or was
    stopped (for `kbbatch status`: counted from the journal alone, a run stopped before half
    its photos looked complete)."""
    report = _last_report(output_folder)
    if "started_at" not in report:
        return []  # none, or an earlier version's
    started = report["started_at"]
    if report.get("finished_at") is None:
        return [f"LAST RUN started {started} and did not finish (killed, or still running): "
                "run again to finish"]
    left = report.get("not_started") or []
    if not (report.get("stopped_by") or left):
        return []
    left, waiting = _still_to_do(output_folder, left, report.get("finished_at"))
    if not (left or waiting):  # all made since (another run, the daemon): nothing to finish
        return []
    how = (f"stopped by {report['stopped_by']}" if report.get("stopped_by")
           else "ended at its first failure (--fail-fast)")
    return [f"LAST RUN started {started}, {how} at {report['finished_at']}; {len(left)} "
            "photo(s) not started: run again to finish"]


def failed_before_a_job(output_folder: Path) -> list[tuple[str, str]]:
    """The last run's failures found before a job began, each (source, error): a broken link,
    a pipe, a manifest's missing photo, whose job is none or an earlier run's failure. `kbbatch
    status`, counting from the journal alone, said "failed 0" of a run that exited 1 for them.
    A photo there again since is left out: it fails no more."""
    from kbbatch.journal import Journal, JournalError

    report = _last_report(output_folder)
    clips = report.get("clips")
    failed = [(str(clip["source"]), str(clip.get("error") or ""))
              for clip in (clips if isinstance(clips, list) else ())
              if isinstance(clip, dict) and clip.get("status") == "failed"
              and clip.get("source")
              and not os.path.isfile(str(clip["source"]))]  # a photo there now: not failing
    if not failed:
        return []
    try:
        journal = Journal(output_folder, read_only=True)
    except JournalError:
        return []
    try:  # a failed job of an earlier run: this is the newer reason (a corrupt photo's link)
        jobs = {source: journal.get(Path(source)) for source, _ in failed}
        return [(source, error) for source, error in failed
                if jobs[source] is None or jobs[source].state == "failed"]
    except JournalError:
        return []
    finally:
        journal.close()


def _still_to_do(output_folder: Path, sources: list[str], finished_at: str | None
                 ) -> tuple[list[str], int]:
    """The photos among sources that no run has made since finished_at, and how many jobs
    wait in the journal (queued, or running when killed): a daemon that later made a stopped
    run's photos in the same folder left `status` telling the user to run again."""
    from kbbatch.journal import DONE_FOLDER, Journal, JournalError

    try:
        since = datetime.datetime.fromisoformat(str(finished_at)).timestamp()
        journal = Journal(output_folder, read_only=True)
    except (ValueError, JournalError):
        return sources, 1
    try:
        made = [Path(job.source) for job in journal.jobs("done") if job.updated >= since]
        waiting = len(journal.jobs("queued")) + len(journal.jobs("running"))
    except JournalError:
        return sources, 1
    finally:
        journal.close()
    # the daemon's job follows its photo into the inbox's done folder
    done = {str(path.parent.parent / path.name if path.parent.name == DONE_FOLDER else path)
            for path in made}
    return [source for source in sources if source not in done], waiting


def utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


HIDDEN_REASON = "hidden (the name starts with a dot); not taken: rename to render"


class EmptyFolderError(ValueError):
    """Nothing to do: no photo in the folder (and no manifest entry naming one)."""


def empty_folder_error(folder: Path, scan: FolderScan) -> EmptyFolderError:
    """Said alike by the batch and `plan`: what the folder holds that is no photo to take."""
    where = f"; subfolders are not searched: {_some(scan.subfolders)}" if scan.subfolders else ""
    if scan.unread_formats:
        where += f"; {_some(scan.unread_formats)}: {UNREAD_FORMAT_REASON}"
    if scan.name_ends:
        where += f"; {_some(scan.name_ends)}: {NAME_END_REASON}"
    if scan.hidden:
        where += f"; {_some(scan.hidden)}: {HIDDEN_REASON}"
    if scan.lone_maps:
        where += f"; {_some(scan.lone_maps)}: {LONE_MAP_REASON}"
    kinds = ", ".join(PHOTO_KINDS)
    return EmptyFolderError(f"{folder}: no photos here ({kinds}){where}; nothing was written")


INTERRUPT_CAUGHT = "interrupt caught"
"""Key of a run's stop requests: set once the run has caught a Ctrl-C and cleans up."""


@contextlib.contextmanager
def stop_signals(stop: dict) -> Iterator[None]:
    """SIGTERM asks the batch to stop after the clip in progress, as it asks the daemon; so
    does a hang-up (SIGHUP: the SSH session dropped), which killed the batch at once, with
    no report. Ctrl-C stops it at once (KeyboardInterrupt); pressed again once the run has
    caught it (stop[INTERRUPT_CAUGHT]) and cleans up, it is not raised again: pressing it
    three times left the report unfinished and the process killed by the signal."""
    import signal
    import threading

    from kbbatch.interrupts import deferred

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    # a terminal's descriptors now: once it hangs up, isatty() no longer says so
    terminal = [descriptor for descriptor in (1, 2) if os.isatty(descriptor)]

    def request(number: int, _frame: object) -> None:
        stop.setdefault("by", signal.Signals(number).name)  # the first reason is the one
        if number == signal.SIGHUP:
            _away_from(terminal)

    def interrupt(_number: int, _frame: object) -> None:
        # raised until the run has caught one: an interrupt lost on its way (a library that
        # swallowed it) must not make the next ones vain
        if not stop.get(INTERRUPT_CAUGHT) and not deferred():
            raise KeyboardInterrupt
        stop.setdefault("by", "SIGINT")  # in the clean-up: said, and the report finished

    handlers = {signal.SIGTERM: request}
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # `nohup kbbatch ...`: ignored
        handlers[signal.SIGHUP] = request
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        handlers[signal.SIGINT] = interrupt
    previous = {number: signal.signal(number, handler) for number, handler in handlers.items()}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _away_from(terminal: list[int]) -> None:
    """After a hang-up, writing to the terminal fails (EIO) and would fail the clip in
    progress: what is printed there goes nowhere instead; the run report is still written."""
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for descriptor in terminal:
            os.dup2(null, descriptor)
    finally:
        os.close(null)


SUBFOLDERS_NAMED = 5
"""An empty folder's error names this many of the subfolders (or unread photos) it did not
search."""

CONTACT_SHEET_NAME = "contact-sheet.png"
"""`kbbatch plan`'s sheet of all previews, in the previews folder (a PNG: every preview is a
.jpg, so no photo's preview takes its name)."""


def _some(paths: list[Path]) -> str:
    """The first SUBFOLDERS_NAMED names, and how many more."""
    more = len(paths) - SUBFOLDERS_NAMED
    return (", ".join(path.name for path in paths[:SUBFOLDERS_NAMED])
            + (f" and {more} more" if more > 0 else ""))


PREVIEWS_SUFFIX = "-previews"
"""`kbbatch plan`'s previews folder: `<manifest>-previews/`, beside the manifest."""


def _holds_photos(folder: Path) -> bool:
    """Whether a subfolder (not searched) has photos of its own to advise running kbbatch on:
    the advice was given for the folder of earlier clips, of depth maps, of `plan`'s previews
    and for a link back to the folder itself. One that cannot be read is said as if it had."""
    if folder.name.endswith(PREVIEWS_SUFFIX) and (
            (folder / CONTACT_SHEET_NAME).exists()
            or folder.with_name(folder.name.removesuffix(PREVIEWS_SUFFIX) + ".json").exists()):
        return False
    try:
        if folder.resolve() in (folder.parent.resolve(), *folder.parent.resolve().parents):
            return False
        with os.scandir(folder) as entries:
            return any(is_image_file(Path(entry.path)) for entry in entries)
    except OSError:
        return True


def run_folder(
    folder: Path,
    output_folder: Path,
    preset: Preset,
    options: ClipOptions,
    show_progress: bool = True,
    manifest: Manifest | None = None,
    force: bool = False,
    fail_fast: bool = False,
    executor: ClipExecutor | None = None,
) -> RunReport:
    """Every photo in a folder to a clip in output_folder; the run report is written there.

    Clips that are complete and up to date (same photo, same settings, the clip untouched) are
    skipped unless force; the journal in the output folder remembers what was made with what.
    The output folder is locked for the run; partial clips of a killed run are removed first.
    SIGTERM stops after the clips in progress, Ctrl-C at once; either way nothing partial stays
    and the journal says which photos are left. Naming, the journal, the lock and the report
    stay here; the executor only makes clips (here, or on a cluster).
    """
    from kbbatch.journal import FolderLock, Journal, JournalError, folder_key, photo_key

    executor = executor or LocalExecutor()
    started_at = utc_now()
    remove_stale_scratch()
    # Both as the file system finds them (journal.photo_key): `-o x/../out` through a link
    # x, or an output folder inside the photo folder reached through a link, is where the
    # kernel puts it.
    output_folder = folder_key(output_folder)
    scan = scan_folder(folder, ignore=(output_folder.name,)
                       if output_folder.parent == folder_key(folder) else ())
    maps = {photo: manifest.depth_map_of(photo) for photo in scan.photos} if manifest else {}
    scan = replace(scan, photos=[photo for photo in scan.photos if not maps.get(photo)])
    missing = (manifest.unmatched_images({photo.name for photo in scan.photos})
               if manifest is not None else [])
    # an excluded photo that is gone was rejected, then deleted: nothing to make, no failure
    gone_excluded = [name for name in missing if manifest.entries[name].excluded]
    missing = [name for name in missing if name not in gone_excluded]
    hashes: dict[Path, str | None] = {}
    # ... or renamed: its bytes are still excluded (a rejected photo renamed was made)
    renamed_excluded = _renamed_exclusions(manifest, gone_excluded, scan.photos, hashes)
    gone_excluded = [name for name in gone_excluded if name not in renamed_excluded.values()]
    if not scan.photos and not scan.broken_links and not scan.not_files and not missing:
        raise empty_folder_error(folder, scan)
    check_writable(output_folder)
    lock = FolderLock(output_folder, "writing clips into")
    results: list[ClipResult] = []
    notes = [f"{sub}: subfolder not searched (run kbbatch on it to render its photos)"
             for sub in scan.subfolders if _holds_photos(sub)]
    notes += [f"{path}: {UNREAD_FORMAT_REASON}" for path in scan.unread_formats]
    notes += [f"{path}: {NAME_END_REASON}" for path in scan.name_ends]
    notes += [f"{path}: {OLD_PLAN_SHEET_REASON}" for path in scan.plan_sheets]
    if scan.hidden:
        notes.append(f"{folder}: {_some(scan.hidden)}: {HIDDEN_REASON}")
    notes += [f"{path}: {LONE_MAP_REASON}" for path in scan.lone_maps
              if not (manifest and manifest.depth_map_of(path))]
    notes += [f"{path}: the depth map of {image} in {manifest.path}; not rendered as a photo"
              for path, image in maps.items() if image]
    # each under its key in the journal, as the clips are (status counts it once), said as given
    for link in scan.broken_links:
        results.append(ClipResult(str(photo_key(link)), None, "failed", 0.0,
                                  error=f"{link}: {broken_link_reason(link)}"))
    for path in scan.not_files:
        results.append(ClipResult(str(photo_key(path)), None, "failed", 0.0, error=f"{path}: "
                                  "is not a regular file (a named pipe, socket or device); "
                                  "not read"))
    notes += [f"{manifest.path}: image {name!r} is excluded and not in {folder}; nothing to do"
              for name in gone_excluded]
    notes += [f"{photo}: has the bytes of {name!r}, which {manifest.path} excludes (renamed?); "
              "not rendered" for photo, name in renamed_excluded.items()]
    for name in missing:
        results.append(ClipResult(str(folder_key(folder) / name), None, "failed", 0.0,
                                  error=f"{manifest.path}: image {name!r}: no photo of "
                                  f"that file name in {folder} (keys are plain file names)"
                                  f"{_nearly_named(name, scan.photos)}"
                                  f"{_renamed_to(manifest, name, scan.photos, hashes)}"))
    stop: dict = {}
    # from the journal's opening, and through the clean-up: a SIGTERM before the handlers
    # (1 in about 12 at 1 s) killed the run with no report; one right after a Ctrl-C (a
    # supervisor stopping the job) killed it half cleaned up
    with stop_signals(stop):
        try:
            remove_partial_clips(output_folder)
            journal = Journal(output_folder)
            settle_deleted_photos(journal, folder, output_folder)
        except JournalError as error:
            lock.release()
            raise OutputFolderError(str(error)) from error
        made_before = _clips_of_last_report(output_folder)
        journal_id = journal.identity()
        written_at = [0.0]

        def report_so_far(every_s: float = REPORT_EVERY_S) -> None:
            """The report of the run unfinished: a run killed outright (kill -9, a power cut)
            leaves it, dated and unfinished, with the clips made so far, not an earlier run's
            report that looks like this one's."""
            if time.monotonic() - written_at[0] < every_s:
                return
            RunReport(str(folder_key(folder)), str(output_folder), preset.name, list(results),
                      notes, device=options.device, started_at=started_at,
                      made_before=list(made_before.values()),
                      journal_id=journal_id).write(output_folder)
            written_at[0] = time.monotonic()

        report_so_far(every_s=0.0)
        names = output_names(scan.photos)
        bar = progress_bar(total=len(scan.photos), desc="photos", unit="photo",
                           disable=not show_progress)
        identity, photos_identity = folder_identity(output_folder), folder_identity(folder)

        def jobs() -> Iterator[ClipJob]:
            """The photos to make, each started in the journal as the executor takes it."""
            if fail_fast and any(result.status == "failed" for result in results):
                return  # a broken link, a pipe, a manifest's missing photo: failed already
            for photo in scan.photos:
                if folder_identity(output_folder) != identity:
                    stop["by"] = FOLDER_GONE
                elif folder_identity(folder) != photos_identity:
                    stop["by"] = PHOTOS_GONE
                if stop:
                    return
                entry = manifest.entry(photo.name, photo.parent) if manifest else None
                if (entry is not None and entry.excluded) or photo in renamed_excluded:
                    results.append(excluded_result(journal, photo_key(photo), output_folder))
                    bar.update()
                    continue
                job = start_job(journal, photo_key(photo), output_folder, names[photo], preset,
                                options, entry, force)
                if isinstance(job, ClipResult):  # skipped, or failed before it could start
                    results.append(_as_made_before(job, made_before))
                    bar.update()
                    report_so_far()
                    if job.status == "no_space":
                        stop["by"] = DISK_FULL
                    if (fail_fast and job.status == "failed") or job.status == "no_space":
                        return
                    continue
                yield job

        try:
            for job in journal.jobs("running"):  # a run that was killed or interrupted
                journal.finish(Path(job.source), "queued", 0.0, "interrupted")
            with contextlib.closing(executor.render(jobs(), preset, options, show_progress)
                                    ) as rendered:
                for job, result in rendered:
                    gone = result.status == "failed" and (
                        FOLDER_GONE if folder_identity(output_folder) != identity
                        else PHOTOS_GONE if folder_identity(folder) != photos_identity
                        else None)
                    if gone:
                        # not the photo's fault (its temporary clip, or the photo itself, was
                        # no longer there), nor removed by its owner: taken again
                        result.status = "interrupted"
                        result.error = f"{job.source}: interrupted by {gone}"
                    results.append(finish_job(journal, job, result))
                    bar.update()
                    report_so_far()
                    if results[-1].status == "no_space":  # the photos after would fail too
                        stop["by"] = DISK_FULL
                    if fail_fast and results[-1].status == "failed":
                        break
        except KeyboardInterrupt:
            stop["by"] = "SIGINT"
            stop[INTERRUPT_CAUGHT] = True
            raise
        except BaseException as error:  # a crash: the report must not read as --fail-fast
            stop.setdefault("by", f"an error ({type(error).__name__})")
            raise
        finally:
            # cleaning up now: a Ctrl-C here (just after the last clip) raised in the middle
            # of it, and left the report written at the start, without a clip
            stop[INTERRUPT_CAUGHT] = True
            bar.close()
            with contextlib.suppress(JournalError):
                for job in journal.jobs("running"):
                    why = f"interrupted by {stop.get('by', 'an error')}"
                    journal.finish(Path(job.source), "queued", 0.0, why)
                    results.append(ClipResult(job.source, None, "interrupted", 0.0, error=why))
            journal.close()
            # the folder as it is found again: 'photos/../out' named no folder a user would
            # look in (every photo of a run through has a result; --fail-fast and stops
            # leave some)
            seen = {result.source for result in results}
            not_started = [str(photo_key(photo)) for photo in scan.photos
                           if str(photo_key(photo)) not in seen]
            report = RunReport(str(folder_key(folder)), str(output_folder), preset.name,
                               results, notes, stop.get("by"), options.device, providers_used(),
                               started_at, utc_now(), not_started, journal_id=journal_id)
            if folder_identity(output_folder) != identity:  # not made again: the user's doing
                now = moved_to(lock.descriptor)  # the report goes with the clips made
                where = "where the folder went"
                if now is not None:
                    report.output_folder = str(now)
                    for result in report.results:
                        if result.output and Path(result.output).parent == output_folder:
                            result.output = str(now / Path(result.output).name)
                    report.notes.append(f"{output_folder} was moved to {now} during the run")
                    unwritten = report.write(now)
                    where = f"in {now}, " + (f"without this run's report: {unwritten}"
                                             if unwritten else "with this run's report")
                lock.release()
                raise OutputFolderError(f"{output_folder}: removed or renamed during the run; "
                                        f"stopped there (the clips made before are {where})")
            report.unwritten = report.write(output_folder)
            written = report_path(output_folder)
            if (report.unwritten and written is not None and written.exists()
                    and not (report.stopped_by or report.not_started)):
                # the one written at the start says the run never finished, and it did; a run
                # stopped (by a full disk, most often what failed this write) keeps it, which
                # says so: removed, `status` had no word of the photos not started
                with contextlib.suppress(OSError):
                    written.unlink()
            lock.release()
    return report


REPORT_EVERY_S = 10.0
"""The unfinished run's report is written again at most this often as clips finish (each write
is the whole report: after every clip, a run of thousands would write gigabytes)."""

FOLDER_GONE = "the output folder removed or renamed"
PHOTOS_GONE = "the photo folder removed or renamed"
"""A photo folder renamed mid-run read as every photo after removed by its owner: exit 0."""
DISK_FULL = "a full output disk"


def settle_deleted_photos(journal, folder: Path, output_folder: Path) -> None:
    """Jobs of this folder's photos that were deleted since. Unfinished, nothing is left to
    make of them, and kept queued they showed in `kbbatch status` for ever (Journal.photo_gone);
    done, their clips are kept from a different photo saved later under the same name
    (Journal.done_photo_removed). Another folder's jobs are left alone: its card may only be
    out of the reader."""
    from kbbatch.journal import folder_key, in_folder

    folder = folder_key(folder)
    done = journal.jobs("done")  # before the unfinished ones settle: photo_gone keeps some done
    for state in ("queued", "running"):
        for job in journal.jobs(state):
            source = Path(job.source)
            if in_folder(source, folder) and not os.path.lexists(source):
                journal.photo_gone(source, output_folder)
    for job in done:
        source = Path(job.source)
        if in_folder(source, folder) and not os.path.lexists(source):
            journal.done_photo_removed(source)


def excluded_result(journal, source: Path, output_folder: Path) -> ClipResult:
    """A photo the manifest excludes: not made, and a clip made of it earlier is left where it
    is (the user's to delete), but said, or the folder silently disagreed with the manifest."""
    result = ClipResult(str(source), None, "excluded", 0.0)
    job = journal.get(source)
    if job is not None and job.state == "done" and job.output \
            and (output_folder / job.output).is_file():
        result.note = (f"{source.name} is excluded by the manifest; its clip {job.output}, made "
                       "earlier, is kept (delete it if it should go)")
    return result


def start_job(journal, source: Path, output_folder: Path, preferred: str, preset: Preset,
              options: ClipOptions, entry: ManifestEntry | None, force: bool
              ) -> ClipJob | ClipResult:
    """Name one photo's clip and start it in the journal; a ClipResult where there is nothing
    to make (up to date) or it cannot start (unreadable photo, journal not writable)."""
    from kbbatch.fingerprint import file_sha256
    from kbbatch.images import unreadable_reason
    from kbbatch.journal import JournalError, source_fingerprint

    try:
        fingerprint = source_fingerprint(source)
        content = file_sha256(source)
        settings = clip_fingerprints(source, content, preset, options, entry)
    except OSError as error:
        if not os.path.lexists(source):
            return removed_result(source)
        return ClipResult(str(source), None, "failed", 0.0,
                          error=f"{error.filename or source}: {unreadable_reason(error)}")
    try:
        return name_job(journal, source, output_folder, preferred, entry, fingerprint,
                        content, settings, options.save_depth, force)
    except JournalError as error:
        # a full disk: not the photo's fault, and the photos after it would fail too
        return ClipResult(str(source), None, "no_space" if error.disk_full else "failed", 0.0,
                          error=f"{source}: {error}", full_folder=str(output_folder))


def removed_result(source: Path) -> ClipResult:
    """A photo deleted from its folder during the run: its owner's choice, not a failure (the
    report said FAILED and exited 1, while `kbbatch status` counted no failure)."""
    return ClipResult(str(source), None, "removed", 0.0,
                      note=f"{source}: removed from its folder during the run; not made")


def finish_job(journal, job: ClipJob, result: ClipResult) -> ClipResult:
    """Record a made clip in the journal; a journal that cannot be written fails the photo."""
    from kbbatch.journal import JournalError, source_fingerprint

    if result.status == "done" and job.content and result.content not in (None, job.content):
        # saved again between the job's start and the photo's read: the clip is of bytes the
        # journal would not know it by (and took for up to date once they came back)
        result.status = "failed"
        result.error = (f"{job.source}: changed while its clip was made (saved again during "
                        "the run?); run again to make it from the photo as it is then")
    if result.status == "failed" and not os.path.lexists(job.source):
        try:
            journal.photo_gone(job.source, job.output.parent)
        except JournalError as error:
            return ClipResult(str(job.source), None, "failed", 0.0,
                              error=f"{job.source}: {error}")
        return removed_result(job.source)
    replaced = (replaced_clip_note(job.source, job.output.name)
                if job.replaces_other_bytes and result.status == "done" else None)
    result.note = joined_notes(job.name_note, result.note, replaced)
    try:
        clip = source_fingerprint(job.output) if result.status == "done" else None
        # an interrupted clip is queued again, as one whose run was stopped, and so is one its
        # full disk could not take
        state = "queued" if result.status in ("interrupted", "no_space") else result.status
        journal.finish(job.source, state, result.seconds, result.error, clip, result.content)
    except (JournalError, OSError) as error:
        full = isinstance(error, JournalError) and error.disk_full
        return ClipResult(str(job.source), None, "no_space" if full else "failed", 0.0,
                          error=f"{job.source}: {error}",
                          full_folder=str(job.output.parent) if full else None)
    return result


@dataclass
class PlanResult:
    source: str
    status: str
    error: str | None = None
    entry: dict | None = None
    seconds: float = 0.0
    note: str | None = None  # e.g. its preview could not be written (the plan was)


PLANNED_FIELDS = ("units", "photo_size", "photo_sha256", "start", "end", "planner")
"""What `kbbatch plan` writes into an entry (with easing, which a user's setting overrides);
the rest of an existing entry (exclude, preset, duration, depth) is the user's and kept."""


def existing_manifest(manifest_path: Path) -> Manifest | None:
    """The manifest `plan -o` would write over, or None where there is none. Anything else
    there (a photo, a hand-written file kbbatch cannot read) is refused, not replaced: the
    default `-o manifest.json` replaced a photo or a user's edits without a word."""
    from kbbatch.manifest import is_read_only, load_manifest

    if not manifest_path.exists() and not manifest_path.is_symlink():
        return None
    if not manifest_path.exists():  # a link to a manifest not made yet: made through it,
        # as `review` does (it was refused as "not a regular file")
        target = Path(os.path.realpath(manifest_path))
        if target.parent.is_dir() and not os.path.lexists(target):
            return None
        raise OutputFolderError(f"{manifest_path}: a link to {target}, which cannot be made "
                                "(its folder is missing, or the link loops); give -o another "
                                "file")
    if not manifest_path.is_file():  # a pipe would block the read for good
        raise OutputFolderError(f"{manifest_path}: not a regular file; not replaced: give -o "
                                "another file")
    if is_read_only(manifest_path):
        raise OutputFolderError(f"{manifest_path}: read-only (its write permission is off); "
                                "not replaced: make it writable or give -o another file")
    try:
        return load_manifest(manifest_path)
    except ManifestError as error:
        raise OutputFolderError(f"{manifest_path}: exists and is not a manifest kbbatch can "
                                f"update ({error}); not replaced: give -o another file") from error


def _keeps_its_entry(entry: ManifestEntry | None, replan: bool) -> bool:
    """Whether `plan` leaves a photo's entry as it is: excluded, or crops of its own."""
    return entry is not None and (entry.excluded or (entry.has_crops and not replan))


def _merged_plans(manifest_path: Path, folder: Path, planned_entries: dict[str, dict],
                  replan: bool, renamed: dict[str, str], existing: Manifest | None
                  ) -> tuple[dict[str, dict], set[str]]:
    """The manifest as it is on disk now, with the new plans and the entries of renamed
    photos under their new names: read again at the end, as an edit saved while the photos
    were planned (from `kbbatch review`) was written over with the copy read at the start.
    Also the photos whose plans were not used: crops or an exclude saved meanwhile, which are
    the user's even under replan (existing: the manifest as read at the start)."""
    current = existing_manifest(manifest_path)
    entries = {name: entry.data for name, entry in current.entries.items()} if current else {}
    for new, old in renamed.items():
        if old in entries and new not in entries:
            entries[new] = entries.pop(old)
    unused = set()
    for name, planned in planned_entries.items():
        # its own key first: an entry saved meanwhile under a renamed photo's new name
        own = current.entry(name, folder) if current and name in renamed else None
        key = name if own is not None else renamed.get(name, name)
        entry = own or (current.entry(key, folder) if current else None)
        if own is not None:
            entries.pop(renamed[name], None)  # the old name's entry: this photo has its own
        before = existing.entry(key, folder) if existing else None
        edited = entry is not None and (before is None or entry.data != before.data)
        if _keeps_its_entry(entry, replan and not edited):
            unused.add(name)  # crops or an exclude saved meanwhile: the user's
            continue
        entries[name if name in renamed else entry.image if entry else name] = \
            _with_own_fields(planned, entry)
    return entries, unused


def renamed_photos(manifest: Manifest, photos: list[Path]) -> dict[str, str]:
    """{new name: old key} of photos renamed since they were planned: a key naming no photo
    whose `photo_sha256` is the bytes of a photo without an entry. `plan` kept such an entry
    silently, planned the photo afresh (its crops lost), and the render failed on it."""
    names = {photo.name for photo in photos}
    orphans = {manifest.entries[key].data.get("photo_sha256"): key
               for key in manifest.unmatched_images(names)}
    orphans.pop(None, None)
    renamed: dict[str, str] = {}
    hashes: dict[Path, str | None] = {}
    for photo in photos:
        if orphans and manifest.entry(photo.name, photo.parent) is None:
            old = orphans.pop(_sha256_of(photo, hashes), None)
            if old is not None:
                renamed[photo.name] = old
    return renamed


def _kept_crops_note(entry: ManifestEntry, source: Path) -> str | None:
    """What a kept entry's crops will do to its photo, if it was resized or cropped since they
    were made (a re-run of `plan` kept stale crops without a word)."""
    if entry.excluded:
        return None
    made_for = entry.data.get("photo_size")
    try:
        width, height = upright_size(source)
        if not made_for or entry.resized(width, height) == (1.0, 1.0):
            another = entry.planned_for_another(source)  # the same size, other content
            return f"{another}; kept as they were" if another else None
    except (ImageReadError, ManifestError) as error:
        return str(error)
    return (f"{source}: its crops in {entry.manifest} were made for the photo at "
            f"{made_for['width']}x{made_for['height']} px; it is {width}x{height} px now: the "
            "render scales them (--replan plans it again)")


def _kept_crops_unfit(entry: ManifestEntry, source: Path, preset: Preset,
                     options: ClipOptions) -> str | None:
    """Why a kept entry's crops cannot be rendered at the preset `plan` was given (planned
    for a 16:9 clip, kept by a plan for a vertical one), if they cannot: `plan` kept them and
    printed a render command that then failed on them."""
    if entry.excluded:
        return None
    try:
        photo_preset, _ = apply_entry(entry, preset, options)
        width, height = upright_size(source)
        entry.plan(width, height, working_size(width, height)[0], photo_preset.aspect,
                   photo_preset.easing)
    except CropAspectError as error:
        return (f"{entry.where(error.field)}: its crops are {error.crop_aspect:.3f} wide to "
                f"high, the preset's clips {error.output_aspect:.3f}; kept, and a render at "
                "this preset fails on them: plan it again (--replan), or render at the preset "
                "they were made for")
    except (ManifestError, ImageReadError):
        return None  # said by the note, or by the render, as for any photo
    return None


def _with_own_fields(planned: dict, entry: ManifestEntry | None) -> dict:
    """A photo's new plan with the fields of its entry that planning does not set (its
    preset, duration, depth file)."""
    own = {key: value for key, value in (entry.data if entry else {}).items()
           if key not in PLANNED_FIELDS}
    return planned | own


def plan_folder(folder: Path, manifest_path: Path, preset: Preset, options: ClipOptions,
                show_progress: bool = True, replan: bool = False) -> list[PlanResult]:
    """Plan every photo and write the plans as an editable manifest, with previews.

    Into an existing manifest: its entries stay; a photo whose entry already has crops (or is
    excluded) keeps it unless replan; a planned photo's entry keeps the user's own fields, and
    is planned with its preset, duration and depth file."""
    from kbbatch.manifest import plan_to_entry, write_manifest
    from kbbatch.review import contact_sheet, draw_plan

    if manifest_path.is_dir():
        raise OutputFolderError(f"{manifest_path}: is a folder; give the manifest's file name")
    scan = scan_folder(folder)
    if not scan.photos:  # as the batch: nothing written (it wrote an empty manifest, status 0)
        raise empty_folder_error(folder, scan)
    existing = existing_manifest(manifest_path)
    check_writable(manifest_path.parent)  # before the planning, not after it
    preview_dir = manifest_path.with_name(manifest_path.stem + PREVIEWS_SUFFIX)
    if preview_dir.resolve() == folder.resolve() or (  # a render took the sheet for a photo
            preview_dir.is_dir() and os.path.samefile(preview_dir, folder)):
        raise OutputFolderError(
            f"{preview_dir}: the previews of {manifest_path.name} go into this folder, and it "
            "is the photo folder (the contact sheet would be made into a clip); give the "
            "manifest another name")
    results: list[PlanResult] = []
    planned_entries: dict[str, dict] = {}
    drawn: dict[str, tuple] = {}  # each plan's preview (an image) and its file name
    sources = [source for source in scan.photos
               if not (existing and existing.depth_map_of(source))]  # a map it names: no photo
    names = output_names(sources)
    renamed = renamed_photos(existing, sources) if existing else {}
    results += [PlanResult(str(manifest_path), "note", note=(
        f"{manifest_path}: the entry of {old!r} is now {new!r}'s: no photo has the old name, "
        "and this one has the bytes it was planned for (renamed)")) for new, old in renamed.items()]
    for source in progress_bar(sources, desc="planning", unit="photo",
                               disable=not show_progress):
        started = time.perf_counter()
        entry = (existing.entry(renamed.get(source.name, source.name), source.parent)
                 if existing else None)
        if _keeps_its_entry(entry, replan):
            unfit = _kept_crops_unfit(entry, source, preset, options)
            results.append(PlanResult(str(source), "failed", error=unfit) if unfit else
                           PlanResult(str(source), "kept", entry=entry.data,
                                      note=_kept_crops_note(entry, source)))
            continue
        try:
            photo_preset, photo_options = apply_entry(entry, preset, options)
            check_depth_is_not_the_photo(entry, source)
            photo, content = read_photo(source)  # the bytes planned are those named
            check_photo_size(photo.shape[1], photo.shape[0], photo_preset, source)
            working, depth_result, depth = working_depth(photo, source, photo_options, content)
            plan = plan_photo(working, depth_result, depth, photo_preset, photo_options.planner)
            planned = plan_to_entry(plan, photo.shape[1], photo.shape[0], working.shape[1],
                                    content)
            planned_entries[source.name] = planned
            drawn[source.name] = (draw_plan(working, plan, f"{source.name} ({plan.planner})"),
                                  names[source].removesuffix(CLIP_SUFFIX) + ".jpg")
            results.append(PlanResult(str(source), "done",
                                      entry=_with_own_fields(planned, entry),
                                      seconds=time.perf_counter() - started))
        except (ImageReadError, DepthError, ManifestError, CropTooSmallError) as error:
            results.append(PlanResult(str(source), "failed", error=str(error)))
        except Exception as error:  # one photo must never stop the batch
            if interrupted(error):  # but a Ctrl-C does, whatever a library made of it
                raise KeyboardInterrupt from error
            message = f"{source}: {type(error).__name__}: {error}"
            results.append(PlanResult(str(source), "failed", error=message))
    merged, unused = _merged_plans(manifest_path, folder, planned_entries, replan, renamed,
                                   existing)
    write_manifest(manifest_path, merged)
    previews = []
    for index, result in enumerate(results):
        name = Path(result.source).name
        if result.status != "done" or name not in drawn:
            continue
        if name in unused:  # its preview would show crops the manifest does not hold
            results[index] = PlanResult(result.source, "kept", entry=merged.get(name),
                                        seconds=result.seconds, note=(
                f"{result.source}: its entry was saved while it was planned (kbbatch "
                "review); kept, and this plan dropped"))
            continue
        preview, preview_name = drawn[name]
        previews.append(preview)
        result.note = _written_or_why(preview_dir / preview_name, preview)
    if existing is not None:  # kept as they are, but a render of the manifest fails on them
        results += [PlanResult(str(manifest_path), "note", note=(
            f"{manifest_path}: image {name!r}: no photo of that file name in {folder}; its "
            f"entry is kept, and a render of the manifest fails on it"
            f"{_nearly_named(name, sources)}"))
            for name in existing.unmatched_images({source.name for source in sources})
            if not existing.entries[name].excluded and name not in renamed.values()]
    if previews:  # beside the previews: a sheet beside the photos became a clip of its own
        why = _written_or_why(preview_dir / CONTACT_SHEET_NAME, contact_sheet(previews))
        if why:
            results.append(PlanResult(str(preview_dir / CONTACT_SHEET_NAME), "note", note=why))
    return results


def _written_or_why(path: Path, picture) -> str | None:
    """A preview written, or why not: the plans are in the manifest either way, so a preview
    folder name taken by a file, or a disk full after the manifest, is a note, not a failed
    photo (every photo was reported failed, and '0 plans written', with all of them there).
    A file of the preview's name that kbbatch did not write (no mark) is the user's: kept."""
    from kbbatch.images import is_users_file, write_image

    if is_users_file(path):
        return (f"{path}: not written over, kbbatch did not write it (previews of kbbatch "
                "before December 2026 carry no mark either): move it away to have it written")
    try:
        write_image(path, picture, own=True)
    except OSError as error:
        where = Path(error.filename) if error.filename else path
        return f"{where}: preview not written ({error.strerror or error})"
    return None
