"""On-disk cache of final depth maps (and ISNet's map, once the depth stage or the planner
worked it out), so re-runs and the daemon never recompute them.

The key is the digest of the depth stage's inputs (kbbatch.fingerprint: photo and depth-file
bytes, the networks present, the options, the depth code) and the working size. Files are
written atomically, so a reader sees a whole entry or none; a damaged entry is recomputed. The
folder is bounded: past the bound the least recently used entries are removed.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from kbbatch.depth import DepthResult, SceneContext
from kbbatch.images import atomic_output
from kbbatch.settings import env_number

log = logging.getLogger(__name__)

CACHE_ENV = "KBBATCH_CACHE"
CACHE_MAX_ENV = "KBBATCH_CACHE_MAX_MB"
CACHE_MAX_MB_DEFAULT = 2048
"""The folder's bound in MB unless $KBBATCH_CACHE_MAX_MB says otherwise. An entry is float32
disparity at the working size (long side 1024 px) and ISNet's map at 16-bit levels where
ISNet ran: 4.5 MB for a 4579x3271 photo, at most 6.3 MB, so the default holds about
450 photos."""

ENTRY_PATTERN = re.compile(r"[0-9a-f]{32}\.npz")
"""A finished entry's file name (temporary files of a write in progress never match)."""


def cache_dir() -> Path:
    override = os.environ.get(CACHE_ENV)
    if override:
        return Path(override).expanduser()  # a cache shared on purpose keeps its modes
    import platformdirs

    folder = Path(platformdirs.user_cache_dir("kbbatch")) / "depth"
    _made_private(folder)
    return folder


@functools.cache
def _made_private(folder: Path) -> None:
    """The user's own cache, made (or made again) readable by this user alone, as the
    freedesktop thumbnail spec asks of what is derived from a user's pictures: its depth
    maps, and the review's plans and preview clips, of a photo in a private folder were
    readable by every user of the machine (a home is 755 by default). Once per process."""
    with contextlib.suppress(OSError):  # no writable home: said where the cache is written
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        status = folder.stat()
        if status.st_uid == os.geteuid() and status.st_mode & 0o077:
            folder.chmod(0o700)


SALIENCY_LEVELS = 65535
"""ISNet's map is kept as 16-bit levels (half the size of float32): the planner frames photos
on it, and without it a cache hit ran ISNet again (1.7 s) for every photo a vertical or
square preset frames. Its threshold, one half, lies halfway between two levels: a pixel is
salient or not alike in the map and its levels, so a hit plans as a miss does."""


PLANNER_SALIENCY = "saliency_by_planner"
"""Marks a map kept for the planner after the entry was written, not the depth stage's own:
where ISNet is not run for framing, the planner uses only the depth stage's, so that a photo
planned at a vertical preset first plans at `slideshow` as if it had not been."""


def _saliency_levels(saliency: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(saliency), 0.0, 1.0) * SALIENCY_LEVELS).astype(
        np.uint16)


def _saliency_from_levels(levels: np.ndarray) -> np.ndarray:
    return levels.astype(np.float32) / np.float32(SALIENCY_LEVELS)


def load(key: str, image: np.ndarray | None = None) -> DepthResult | None:
    """The entry, with ISNet's map as its segmentation when it was stored and image (the
    working photo it belongs to) is given."""
    path = cache_dir() / f"{key}.npz"
    try:
        with np.load(path, allow_pickle=False) as data:
            context = None
            if image is not None and "saliency" in data.files:
                levels = data["saliency"]
                if levels.dtype == np.uint16 and levels.shape == image.shape[:2]:
                    context = SceneContext.known(image, _saliency_from_levels(levels),
                                                 by_planner=PLANNER_SALIENCY in data.files)
            disparity = data["disparity"]
            if not _is_disparity(disparity):  # a valid file of bad values (edited by hand)
                return None
            result = DepthResult(disparity, str(data["backend"]), str(data["source"]),
                                 context)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None  # absent, or damaged (say truncated by a copy): computed again
    with contextlib.suppress(OSError):  # evicted meanwhile, or a read-only cache
        os.utime(path)  # used now: the last to be evicted
    return result


def _is_disparity(disparity: np.ndarray) -> bool:
    """What the depth stage stores and the camera needs: a 2-D map of finite values with a
    positive maximum. An entry with a few NaN pixels failed its photo on every run
    ("disparity has no positive finite maximum"), without naming the cache."""
    return (disparity.ndim == 2 and disparity.dtype.kind == "f" and disparity.size > 0
            and bool(np.isfinite(disparity).all()) and float(disparity.max()) > 0)


def store(key: str, result: DepthResult) -> None:
    path = cache_dir() / f"{key}.npz"
    arrays = {"disparity": result.disparity, "backend": result.backend, "source": result.source}
    saliency = result.segmentation.known_saliency() if result.segmentation else None
    if saliency is not None:
        arrays["saliency"] = _saliency_levels(saliency)
    if _write(path, arrays):
        _bound(path)


def add_saliency(key: str, saliency: np.ndarray) -> None:
    """Keep in the entry a map worked out after it was written (the depth stage found no object
    to run ISNet for, or read a depth map; the planner then framed the photo on ISNet's map),
    so the next run reads it instead of running ISNet again."""
    path = cache_dir() / f"{key}.npz"
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return  # evicted or damaged meanwhile: written whole by the next run
    arrays["saliency"] = _saliency_levels(saliency)
    arrays[PLANNER_SALIENCY] = np.array(True)
    if _write(path, arrays):
        _bound(path)  # the entry grew


def _bound(written: Path) -> None:
    """Evict down to the bound, keeping the entry just written."""
    try:
        max_bytes = cache_max_bytes()
    except CacheSettingError as error:  # the commands refuse it at start; a library caller
        _say_bad_setting(str(error))
        max_bytes = CACHE_MAX_MB_DEFAULT * 2**20
    evict(max_bytes, keep=written)


def _write(path: Path, arrays: dict) -> bool:
    """Write an entry atomically; False (said once) where the cache cannot be written."""
    try:
        with atomic_output(path, ".npz") as temp_path, temp_path.open("wb") as handle:
            np.savez(handle, **arrays)
    except OSError as error:  # a cache that cannot be written only costs time: said once
        _say_unwritable(str(cache_dir()), error.strerror or str(error))
        return False
    return True


@functools.cache
def _say_unwritable(folder: str, reason: str) -> None:
    log.warning("%s: depth cache cannot be written (%s); depth is computed again on every run "
                "(set %s to another folder)", folder, reason, CACHE_ENV)


class CacheSettingError(ValueError):
    """$KBBATCH_CACHE_MAX_MB is not a size: refused when a command starts (it was only logged,
    and the cache grew to the default bound the user meant to lower)."""


def cache_max_bytes() -> int:
    """The bound on the folder's size, from $KBBATCH_CACHE_MAX_MB or the default."""
    try:
        megabytes = env_number(CACHE_MAX_ENV, CACHE_MAX_MB_DEFAULT)
    except ValueError as error:
        raise CacheSettingError(
            f"{CACHE_MAX_ENV}={os.environ[CACHE_MAX_ENV]!r} is not a size in MB: give a number "
            f"such as {CACHE_MAX_MB_DEFAULT} (the default), or unset it") from error
    return int(megabytes * 2**20)


@functools.cache
def _say_bad_setting(message: str) -> None:
    log.warning("%s; the depth cache is kept to %d MB", message, CACHE_MAX_MB_DEFAULT)


def evict(max_bytes: int, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used entries until the folder holds at most max_bytes (the
    entry just written is kept even when it alone is larger). Several processes may evict at
    once: an entry already gone is simply skipped."""
    entries = []
    for path in cache_dir().iterdir() if cache_dir().is_dir() else ():
        if not ENTRY_PATTERN.fullmatch(path.name):
            continue
        try:
            stat = path.stat()
        except OSError:
            continue
        entries.append((stat.st_mtime_ns, path.name, stat.st_size, path))
    total = sum(size for _, _, size, _ in entries)
    removed = []
    for _, _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        if path == keep:
            continue
        try:
            path.unlink(missing_ok=True)  # another process may have evicted it already
        except OSError:
            continue
        total -= size
        removed.append(path)
    return removed
