"""The output folder, as every runner shares it: clip names (and a clip's start in the
journal), writability, partial clips."""

from __future__ import annotations

import logging
import os
import stat
import tempfile
from collections import Counter
from pathlib import Path

from kbbatch.images import fitted_name
from kbbatch.manifest import ManifestEntry
from kbbatch.pipeline import CLIP_SUFFIX, ClipJob, ClipResult, depth_images_missing

log = logging.getLogger(__name__)


def output_names(sources: list[Path]) -> dict[Path, str]:
    """Clip file names, distinct (ignoring case): the photo's stem, or its full name where two
    photos share a stem or a stem is another photo's full name (x.jpg.png beside x.jpg and
    x.png), and a number after names that differ only in case."""
    chosen = {s: s.stem for s in sources}
    while True:
        counts = Counter(name.lower() for name in chosen.values())
        clashing = [s for s in sources if counts[chosen[s].lower()] > 1 and chosen[s] != s.name]
        if not clashing:
            break
        for source in clashing:
            chosen[source] = source.name
    taken = {name.lower() for name in chosen.values() if counts[name.lower()] == 1}
    names = {}
    for source in sorted(sources):
        name = base = chosen[source]
        number = 1
        while counts[base.lower()] > 1 and name.lower() in taken:
            number += 1
            name = f"{base}.{number}"
        taken.add(name.lower())
        names[source] = fitted_name(name, CLIP_SUFFIX)  # a 251-byte stem's `x.jpg.mp4` too
    return names


class OutputFolderError(OSError):
    pass


def folder_identity(folder: Path) -> tuple[int, int] | None:
    """(device, inode) of a folder, None where there is none: a folder removed or renamed
    while a runner uses it is not the folder it started with, even when made again."""
    try:
        stat = os.stat(folder)
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


def moved_to(folder_fd: int) -> Path | None:
    """Where a folder held open as folder_fd is now, so that a run whose output folder was
    moved can still leave its report beside its clips; None where it was removed, or where
    the system cannot say (Linux's /proc tells)."""
    try:
        path = Path(os.readlink(f"/proc/self/fd/{folder_fd}"))
        return path if os.path.samestat(os.stat(path), os.fstat(folder_fd)) else None
    except OSError:
        return None


def unreplaceable(path: Path) -> str | None:
    """Why this user cannot replace the file at path, if so: in a sticky folder only the
    file's owner (or the folder's, or root) may, which a run found out after the render, as
    a raw PermissionError, the good clip's record then marked failed."""
    try:
        folder, file = path.parent.stat(), path.lstat()
    except OSError:
        return None
    if not folder.st_mode & stat.S_ISVTX or os.geteuid() in (0, file.st_uid, folder.st_uid):
        return None
    from kbbatch.journal import user_name

    return (f"{path}: belongs to {user_name(file.st_uid)} in a sticky folder (mode "
            f"{stat.S_IMODE(folder.st_mode):o}): only its owner can replace it; kept")


def check_writable(folder: Path) -> None:
    """Fail early, with the reason, when clips could never be written to a folder."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".kbbatch-write-test-"):
            pass
    except OSError as error:
        raise OutputFolderError(f"{folder}: output folder is not writable "
                                f"({error.strerror or error})") from error


def remove_partial_clips(folder: Path, older_than_s: float = 0.0) -> list[Path]:
    """Temporary files (`.NAME.XXXX.part.mp4`: a clip, or a photo's copy to done/ on another
    disk) left by a killed run; call with the folder locked, so that no live run's file is
    taken, or with older_than_s, an age no live run's file reaches (a folder no lock keeps:
    the review's previews)."""
    import time

    from kbbatch.images import TEMP_NAME

    removed = []
    now = time.time()
    for partial in folder.glob(".*.part.*"):
        if TEMP_NAME.match(partial.name) and not partial.is_dir():
            try:
                if older_than_s and now - partial.stat().st_mtime <= older_than_s:
                    continue
                partial.unlink(missing_ok=True)
            except OSError as error:  # another user's, in a sticky folder: a traceback before
                log.warning("%s: a partial clip left by an interrupted run; kept, since it "
                            "cannot be removed (%s)", partial, error.strerror or error)
                continue
            removed.append(partial)
    return removed


def replaced_clip_note(source: Path, name: str) -> str:
    """Said when a photo's bytes changed since its clip was made: the clip is replaced (one
    import folder for every card also brings another photo under a used name)."""
    return (f"{source.name} changed since {name} was made from it: that clip is replaced (a "
            "photo saved under the name of another is taken for an edit of it)")


def clip_name_note(source: Path, folder: Path, preferred: str, name: str, content: str,
                   settings: tuple[str, ...], adopted: bool = False) -> str | None:
    """Said when a clip is not named preferred: what holds that name. A clip of this photo
    with other settings, known by its mark once the journal was lost, is kept (it cannot be
    told from an edit of it saved in place): it was said to be another photo's; so was one of
    these settings adopted by its mark (the journal lost) and made again by --force. (An edit
    the journal tells from its clip keeps the mark of these settings: a file of the user's.)"""
    from kbbatch.encode import read_clip_mark

    if name == preferred:
        return None
    mark = read_clip_mark(folder / preferred)
    if mark is not None and mark[0] == content and (mark[1] not in settings or adopted):
        which = "these settings" if mark[1] in settings else "other settings"
        return (f"{source.name}: {preferred}, its clip of {which}, is kept (without the "
                "journal that knew it, it cannot be told from an edit of it saved in "
                f"place); this one is named by its content: {name}")
    return (f"{source.name}: {preferred} (or a depth map beside it) is another photo's or a "
            f"file kbbatch did not write; this one is named by its content: {name}")


ADOPTED_NOTE = ("{name}: made by kbbatch from this photo with these settings (its mark says "
                "so) but missing from the journal; kept, and recorded")


def name_job(journal, source: Path, output_folder: Path, preferred: str,
             entry: ManifestEntry | None, fingerprint: str, content: str,
             settings: tuple[str, ...], save_depth: bool, force: bool = False
             ) -> ClipJob | ClipResult:
    """The journal's part of starting a clip, one rule for the batch and the daemon: its name,
    whether it is up to date ("skipped"), whether this user may replace the file of that name
    ("failed", before any render), else the job, started. JournalError passes through (the
    batch fails the photo, the daemon pauses and retries)."""
    from kbbatch.images import capture_time, depth_image_names

    adopted = journal.adopt_marked_clip(source, fingerprint, settings, content,
                                        output_folder, preferred)
    previous = journal.job_of(source, content)
    taken = capture_time(source)
    if previous is not None and previous.of_another_folder(content, taken):
        journal.set_aside(source)  # its clip stays that photo's, under its name
        previous = journal.job_of(source, content)  # this directory's own, set aside
    name = journal.clip_name(source, content, preferred, output_folder, save_depth)
    output = output_folder / name
    journal.restore_kept(source, settings, output, content)  # a later attempt failed
    up_to_date = journal.is_up_to_date(source, fingerprint, settings, output, content)
    if not force and up_to_date and not (save_depth and depth_images_missing(output)):
        journal.place(source, content, taken)
        return ClipResult(str(source), str(output), "skipped", 0.0,
                          note=ADOPTED_NOTE.format(name=name) if adopted else None,
                          content=content)
    name = journal.name_to_make(source, content, preferred, output_folder, save_depth, name)
    output = output_folder / name
    # its depth images too: replaced with --save-depth, removed without it
    refusal = next(filter(None, map(unreplaceable, [output, *(
        output.with_name(name) for name in depth_image_names(output.name))])), None)
    if refusal:  # before the render, and the clip's record left as it is
        return ClipResult(str(source), None, "failed", 0.0, error=f"{source}: {refusal}")
    journal.start(source, fingerprint, settings[0], name, content, taken)
    replaces = previous is not None and previous.made_from_other_bytes(name, content, output)
    kept = previous is not None and previous.output == name  # its own name: nothing to note
    name_note = None if kept else clip_name_note(source, output_folder, preferred, name,
                                                  content, settings, adopted is not None)
    return ClipJob(source, output, entry, name_note, replaces_other_bytes=replaces,
                   content=content)
