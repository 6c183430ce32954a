"""`kbbatch review`: a local page to review and edit every photo's plan, then save the manifest.

The session plans the folder's photos in one background thread (cached on disk per photo,
preset and manifest entry), renders short low-resolution preview clips on demand through the
same `make_clip` as a batch (cached per plan), and writes the manifest atomically after
validating it. It serves only the folder's own photos, the page's files and the previews it
rendered. Every request needs the session's token (the address it prints carries it once,
then a cookie does; a POST also in a header), and must name a local host: the loopback
address is open to every user of the machine.
"""

from __future__ import annotations

import contextlib
import hashlib
import ipaddress
import json
import logging
import os
import secrets
import shlex
import socket
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
from flask import Flask, Response, jsonify, redirect, request, send_file
from werkzeug.exceptions import HTTPException
from werkzeug.serving import make_server
from werkzeug.wsgi import ClosingIterator

from kbbatch.camera import SceneGeometry, working_size
from kbbatch.depth import DepthError
from kbbatch.depth import cache as depth_cache
from kbbatch.depth.file import load_map
from kbbatch.fingerprint import clip_inputs, file_sha256
from kbbatch.images import (
    ImageReadError,
    atomic_output,
    list_images,
    read_image,
    read_photo,
)
from kbbatch.manifest import (
    ManifestEntry,
    ManifestError,
    load_manifest,
    manifest_from_data,
    parse_manifest_text,
    plan_to_entry,
    write_manifest,
)
from kbbatch.outputs import OutputFolderError, check_writable, remove_partial_clips
from kbbatch.pipeline import (
    ClipOptions,
    CropTooSmallError,
    apply_entry,
    check_cloud_size,
    check_photo_size,
    cloud_scale,
    make_clip,
    plan_photo,
    resize_to,
    working_depth,
)
from kbbatch.presets import Preset, PresetError, builtin_names, load_preset, with_overrides
from kbbatch.review import depth_picture

STATIC_FOLDER = Path(__file__).parent / "static"
TOKEN_HEADER = "X-KBBatch-Token"
TOKEN_PARAMETER = "token"
"""The query parameter of the address a session prints, which sets its cookie."""


def token_cookie(port: str) -> str:  # port: as the WSGI environment gives it
    """The session's cookie, named for its port: a browser sends a host's cookies to every
    port, and two sessions side by side must not take each other's."""
    return f"kbbatch-review-{port}"


LOCAL_HOSTS = ("127.0.0.1", "localhost", "[::1]")

PREVIEW_LONG_SIDE_PX = 480
"""Long side of a preview clip: enough to judge a move, a few seconds to render."""
PREVIEW_MAX_DURATION_S = 2.0
PREVIEW_FPS = 15.0
PREVIEW_THREADS = 2
JPEG_QUALITY = 88
PICTURES_KEPT = 64
"""Encoded photos and depth maps kept in memory (most recently used)."""
REVIEW_CACHE_VERSION = 1
"""Bump when a change to planning or rendering changes cached plans or previews."""
STOP_WAIT_S = 60.0
"""A stop waits this long at most for the requests being answered (a preview rendering, a
depth map worked out): stopped under them, the process aborted ("terminate called without an
active exception") and left a preview's partial file behind."""
PARTIAL_PREVIEW_AGE_S = 3600.0
"""A preview's temporary file this old is left by a review killed while rendering it (a
preview takes seconds), and removed when a review starts; a younger one may be another
review's, rendering now into the same cache."""

log = logging.getLogger(__name__)


class RequestError(Exception):
    """A request the session refuses; becomes a JSON answer with this status."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass
class PhotoState:
    path: Path
    status: str = "pending"  # pending, ready or failed
    error: str | None = None
    width_px: int | None = None
    height_px: int | None = None
    auto: dict[str, Any] | None = None  # the automatic plan as a manifest entry (source px)
    planned_as: tuple[int, int, int] | None = None  # the file's _stat_signature when planned


def review_cache_dir() -> Path | None:
    """Where plans and previews are kept between runs; None when that cannot be written (then
    a session keeps them for its run: every plan, preview and save once failed with a
    PermissionError)."""
    folder = depth_cache.cache_dir() / "review"
    try:
        check_writable(folder)
    except OutputFolderError as error:
        log.warning("%s; plans and previews are kept for this run only", error)
        return None
    return folder


def _digest(settings: dict[str, Any]) -> str:
    text = json.dumps(settings | {"version": REVIEW_CACHE_VERSION}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


class ReviewSession:
    """The folder, the manifest being edited, the plans and previews, for one server run."""

    def __init__(self, folder: Path, manifest_path: Path, preset: Preset, options: ClipOptions,
                 render_options: tuple[str, ...]) -> None:
        """render_options: the command-line options (preset, overrides, planner, depth) the
        page was started with, which the render command it shows must repeat."""
        self.folder = Path(folder).resolve()
        self.manifest_path = Path(manifest_path).absolute()
        self.preset = preset
        self.options = options
        self.render_options = render_options
        kept = review_cache_dir()
        self._scratch = (tempfile.TemporaryDirectory(prefix="kbbatch-review-") if kept is None
                         else None)
        self.cache_dir = kept if self._scratch is None else Path(self._scratch.name)
        self.token = secrets.token_urlsafe(32)
        # Only files that really lie inside the folder: a symlink pointing out is not served,
        # and said (the batch renders it, with its automatic plan).
        listed = list_images(self.folder)
        self.photos = {p.name: PhotoState(p) for p in listed
                       if p.resolve().is_relative_to(self.folder)}
        self.links_out = [p for p in listed if p.name not in self.photos]
        self._manifest_signature = _stat_signature(self.manifest_path)
        if self.manifest_path.exists():  # a depth map the manifest names is no photo to plan
            maps = load_manifest(self.manifest_path)  # (render and plan pass it over too)
            self.photos = {name: state for name, state in self.photos.items()
                           if not maps.depth_map_of(state.path)}
        self.entries = self._manifest_on_disk()
        self._lock = threading.Lock()
        self._save_lock = threading.Lock()
        self._key_locks: dict[str, threading.Lock] = {}
        self._hashes: dict[tuple[str, int, int, int, int], str] = {}
        self._images: OrderedDict[tuple[str, str, str], bytes] = OrderedDict()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kbbatch-plan")
        self._stopping = False
        self._answering = 0  # requests being answered, which a stop waits for
        self._answered = threading.Condition()
        # a review killed while it rendered a preview left its partial file, for good
        remove_partial_clips(self.cache_dir / "previews", PARTIAL_PREVIEW_AGE_S)

    # -- the manifest ----------------------------------------------------------------------

    def _manifest_on_disk(self) -> dict[str, dict[str, Any]]:
        """Entries of the manifest file as it is now (ManifestError if it is invalid)."""
        if not self.manifest_path.exists():
            return {}
        manifest = load_manifest(self.manifest_path)
        entries = {name: entry.data for name, entry in manifest.entries.items()}
        # a key in the other Unicode form takes the photo's spelling, so the page shows and
        # saves the entry that renders
        for name in self.photos:
            entry = manifest.entry(name, self.folder)
            if entry is not None and entry.image != name:
                entries[name] = entries.pop(entry.image)
        return entries

    def render_command(self) -> str:
        command = ["kbbatch", str(self.folder), "--manifest", str(self.manifest_path)]
        return shlex.join([*command, *self.render_options])

    def save(self, changes: Any, bases: Any = None) -> dict[str, Any]:
        """Apply the page's changed entries (None removes one) to the manifest on disk.

        Entries for photos that are not in the folder are kept; nothing is written unless the
        whole manifest validates and every crop fits its photo and preset. bases: the entry
        each change started from (None: none); a photo whose entry on disk is no longer its
        base was changed meanwhile (by hand, or in another review), and the save is refused
        rather than written over that change.
        """
        if not isinstance(changes, dict):
            raise RequestError(400, "'entries' must be an object of photo name -> entry or null")
        if bases is not None and not isinstance(bases, dict):
            raise RequestError(400, "'bases' must be an object of photo name -> entry or null")
        # one read-modify-write of the file at a time, in this server and any other
        with self._save_lock, manifest_lock(self.manifest_path):
            return self._save(changes, bases or {})

    def _save(self, changes: dict[str, Any], bases: dict[str, Any]) -> dict[str, Any]:
        try:
            merged = self._manifest_on_disk()
        except ManifestError as error:
            raise RequestError(409, f"the manifest on disk is not valid, not overwritten: "
                                    f"{error}") from error
        changed = sorted(name for name in changes
                         if name in bases and merged.get(name) != bases[name])
        if changed:
            with self._lock:  # what the page shows after a reload
                self.entries = merged
            raise RequestError(409, f"{', '.join(changed)}: changed in {self.manifest_path} "
                                    "since this page read it (edited by hand or in another "
                                    "review); nothing saved: reload the page to see it, then "
                                    "edit again")
        for name, entry in changes.items():
            self._photo(name)
            if entry is None:
                merged.pop(name, None)
            else:
                merged[name] = entry
        document = {"version": 1, "images": merged}
        try:
            manifest = manifest_from_data(document, self.manifest_path)
            for name in changes:
                if changes[name] is not None:
                    self._settings(name, changes[name])
                    self._checked_plan(manifest.entries[name])
                    depth_file = manifest.entries[name].depth_file
                    if depth_file is not None:  # /etc/passwd was saved, then failed the render
                        load_map(depth_file)
        except (ManifestError, DepthError) as error:
            raise RequestError(400, str(error)) from error
        try:
            write_manifest(self.manifest_path, merged)
        except OSError as error:
            raise RequestError(500, f"{self.manifest_path}: cannot be written "
                                    f"({error.strerror or error})") from error
        with self._lock:
            self.entries = merged
        self._manifest_signature = _stat_signature(self.manifest_path)
        return {"manifest": str(self.manifest_path), "command": self.render_command(),
                "entries": len(merged)}

    def _checked_plan(self, entry: ManifestEntry) -> dict[str, Any] | None:
        """The entry's crops in source px, checked against the photo and its preset."""
        if not entry.has_crops:
            return None
        preset, _ = self._settings(entry.image, entry.data)
        width, height = self._size(entry.image)
        working_width, working_height = working_size(width, height)
        plan = entry.plan(width, height, working_width, preset.aspect, preset.easing)
        # ... and against the cloud its tightest crop needs, as the render checks it: a crop
        # 1e-9 wide was saved, then failed the render
        scene = SceneGeometry(working_width, working_height, 1.0)
        try:
            check_cloud_size(cloud_scale(preset, plan, scene, max(width, height)), plan, scene,
                             preset, width, Path(entry.image))
        except CropTooSmallError as error:
            raise ManifestError(str(error)) from error
        return plan_to_entry(plan, width, height, working_width)

    # -- photos and plans ------------------------------------------------------------------

    def _photo(self, name: Any) -> PhotoState:
        if not isinstance(name, str) or name not in self.photos:
            raise RequestError(404, f"no photo {name!r} in {self.folder}")
        state = self.photos[name]
        # looked at each time: a photo replaced by a link out of the folder after the start
        # was served (the check ran only at the start)
        if not state.path.resolve().is_relative_to(self.folder):
            raise RequestError(404, f"{name}: now a link to a file outside {self.folder}; "
                                    "not served")
        return state

    def _settings(self, name: str, data: dict[str, Any] | None) -> tuple[Preset, ClipOptions]:
        if not data:
            return self.preset, self.options
        entry = ManifestEntry(name, data, self.manifest_path)
        try:
            return apply_entry(entry, self.preset, self.options)
        except ManifestError as error:
            raise RequestError(400, str(error)) from error

    def _inputs(self, path: Path, options: ClipOptions) -> str:
        """The digest of everything a photo's plan and clip are made from (fingerprint's:
        the photo's and its depth map's bytes, the networks present, the code), so that a
        depth map edited while the page is open gives a new plan and preview."""
        try:
            return clip_inputs(path, self._file_hash(path), options.depth, None).digest
        except FileNotFoundError:
            raise  # removed while the page is open: the app says so (404)
        except OSError as error:
            raise RequestError(422, f"{error.filename or path}: cannot be read "
                                    f"({error.strerror or error})") from error

    def _file_hash(self, path: Path) -> str:
        stat = path.stat()
        # the change time too, which no copy can set: a photo swapped for one of the same
        # size with its time kept (`cp -p`, `touch -r`) was taken for the first
        key = (str(path), stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns)
        if key not in self._hashes:
            self._hashes[key] = file_sha256(path)
        return self._hashes[key]

    def _key_lock(self, key: str) -> threading.Lock:
        with self._lock:
            return self._key_locks.setdefault(key, threading.Lock())

    def _size(self, name: str) -> tuple[int, int]:
        """The photo's size now: through its plan, cached by the file's bytes, so a photo
        replaced while the page is open (a smaller one) is measured again, not trusted from
        the first look."""
        state = self.photos[name]
        try:
            self.auto_plan(name, None)
        except ImageReadError as error:
            raise RequestError(422, str(error)) from error
        return state.width_px, state.height_px

    def auto_plan(self, name: str, data: dict[str, Any] | None) -> dict[str, Any]:
        """The automatic plan for a photo under an entry's preset, planner and depth (cached)."""
        state = self._photo(name)
        preset, options = self._settings(name, data)
        key = _digest({"inputs": self._inputs(state.path, options),
                       "preset": preset.frame_settings(), "planner": options.planner})
        path = self.cache_dir / "plans" / f"{key}.json"
        with self._key_lock(key):
            try:
                result = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                try:
                    result = self._compute_plan(state.path, preset, options)
                except (DepthError, CropTooSmallError) as error:  # the photo's, not ours
                    raise RequestError(422, str(error)) from error
                # not kept on a full disk: computed again next time
                with contextlib.suppress(OSError), atomic_output(path, ".json") as temp_path:
                    temp_path.write_text(json.dumps(result), encoding="utf-8")
        state.width_px, state.height_px = result["width_px"], result["height_px"]
        return result["entry"]

    @staticmethod
    def _compute_plan(source: Path, preset: Preset, options: ClipOptions) -> dict[str, Any]:
        photo, content = read_photo(source)
        check_photo_size(photo.shape[1], photo.shape[0], preset, source)  # as plan and render
        working, depth_result, depth = working_depth(photo, source, options, content)
        plan = plan_photo(working, depth_result, depth, preset, options.planner)
        return {"entry": plan_to_entry(plan, photo.shape[1], photo.shape[0], working.shape[1]),
                "width_px": photo.shape[1], "height_px": photo.shape[0]}

    def start_planning(self) -> None:
        """Plan every photo in the background, in name order."""
        for name in self.photos:
            self._worker.submit(self._plan_in_background, name)

    def _plan_in_background(self, name: str) -> None:
        state = self.photos[name]
        state.planned_as = _stat_signature(state.path)
        if state.planned_as is None:  # removed since it was listed
            state.status = "failed"
            state.error = unreadable_words(FileNotFoundError(2, "gone", str(state.path)), name)
            return
        try:
            state.auto = self.auto_plan(name, self.entries.get(name))
            state.status, state.error = "ready", None
        except (ImageReadError, ManifestError) as error:
            state.status, state.error = "failed", str(error)
        except RequestError as error:
            state.status, state.error = "failed", error.message
        except Exception as error:  # one photo must never stop the others
            if self._stopping:  # Ctrl-C: the planner's own threads refused, nothing is wrong
                return
            log.exception("planning %s failed", name)
            state.status, state.error = "failed", f"{name}: {type(error).__name__}: {error}"

    def stop(self) -> None:
        self._stopping = True
        self._worker.shutdown(wait=False, cancel_futures=True)
        with self._answered:
            if self._answering:
                log.warning("stopping: waiting for %d request(s) being answered (a preview "
                            "rendering)", self._answering)
            self._answered.wait_for(lambda: not self._answering, STOP_WAIT_S)
        if self._scratch is not None:
            self._scratch.cleanup()

    def answering(self, app: Callable) -> Callable:
        """The WSGI application app, each request counted until its answer has been sent
        (the server closes the answer then), so that a stop waits for it."""
        def counted(environ: dict, start_response: Callable) -> Any:
            with self._answered:
                self._answering += 1
            try:
                return ClosingIterator(app(environ, start_response), self._answer_sent)
            except BaseException:
                self._answer_sent()
                raise

        return counted

    def _answer_sent(self) -> None:
        with self._answered:
            self._answering -= 1
            self._answered.notify_all()

    def _plan_again_if_changed(self, name: str) -> None:
        """A photo removed, damaged or replaced since it was planned is planned again (in the
        background): listed as ready, it was said to be, until its picture failed to load."""
        state = self.photos[name]
        with self._lock:  # two pages asking at once plan it once
            if (state.status == "pending" or self._stopping
                    or _stat_signature(state.path) == state.planned_as):
                return
            state.status, state.error = "pending", None
        with contextlib.suppress(RuntimeError):  # the worker is shut down: stopping
            self._worker.submit(self._plan_in_background, name)

    def photo_json(self, name: str) -> dict[str, Any]:
        self._plan_again_if_changed(name)
        state = self.photos[name]
        entry = self.entries.get(name)
        result: dict[str, Any] = {
            "name": name, "status": state.status, "error": state.error,
            "width_px": state.width_px, "height_px": state.height_px, "entry": entry,
            "auto": state.auto, "excluded": bool(entry and entry.get("exclude")),
            "source": "auto", "plan": state.auto,
        }
        try:
            preset, _ = self._settings(name, entry)
        except RequestError as error:
            return result | {"status": "failed", "error": error.message}
        result |= {"preset": preset.name, "aspect": preset.aspect,
                   "duration_s": preset.duration_s, "easing": preset.easing}
        if entry and "start" in entry and state.width_px is not None:
            try:
                result["plan"] = self._checked_plan(ManifestEntry(name, entry,
                                                                  self.manifest_path))
                result["source"] = "manifest"
            except ManifestError as error:
                result |= {"status": "failed", "error": str(error)}
            except RequestError as error:  # that photo's failure, not the list's: one
                # photo removed or damaged while the page was open emptied the whole page
                result |= {"status": "failed", "error": error.message}
            except OSError as error:
                result |= {"status": "failed", "error": unreadable_words(error, name)}
        return result

    def overview(self) -> dict[str, Any]:
        # The manifest as it is now: edited by hand (or by another review) since it was
        # read, the page showed the old entries, and saved them back over the edit.
        signature = _stat_signature(self.manifest_path)
        if signature != self._manifest_signature:  # read again only when it changed
            with contextlib.suppress(ManifestError, OSError):  # invalid: the save says so
                entries = self._manifest_on_disk()
                with self._lock:
                    self.entries = entries
                self._manifest_signature = signature
        photos = [self.photo_json(name) for name in self.photos]
        # as the render takes them: the command line's --duration and --fps over each
        presets = {name: with_overrides(load_preset(name), **dict(self.options.preset_overrides))
                   for name in builtin_names()}
        presets[self.preset.name] = self.preset
        return {
            "folder": str(self.folder), "manifest": str(self.manifest_path),
            "command": self.render_command(), "default_preset": self.preset.name,
            "presets": {name: {"aspect": p.aspect, "duration_s": p.duration_s,
                               "easing": p.easing, "width_px": p.width_px,
                               "height_px": p.height_px} for name, p in presets.items()},
            "progress": {"done": sum(p["status"] != "pending" for p in photos),
                         "total": len(photos)},
            "photos": photos,
        }

    # -- pictures and previews -------------------------------------------------------------

    def picture(self, name: str, kind: str) -> bytes:
        """The photo ('image', JPEG) or its depth map ('depth', PNG) at the working size."""
        state = self._photo(name)
        if kind == "image":
            key = (name, kind, self._file_hash(state.path))
        else:  # the depth's own inputs: a map saved in the entry, or put beside the photo,
            # showed the old depth until a restart (the plan had followed it)
            _, options = self._settings(name, self.entries.get(name))
            key = (name, kind, self._inputs(state.path, options))
        with self._lock:
            if key in self._images:
                self._images.move_to_end(key)
                return self._images[key]
        photo = read_image(state.path)
        if kind == "image":
            picture = resize_to(photo, *working_size(photo.shape[1], photo.shape[0]))
            ok, data = cv2.imencode(".jpg", picture[..., ::-1],
                                    [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        else:
            _, options = self._settings(name, self.entries.get(name))
            try:
                _, depth_result, _ = working_depth(photo, state.path, options)
            except DepthError as error:
                raise RequestError(422, str(error)) from error
            ok, data = cv2.imencode(".png", depth_picture(depth_result.disparity)[..., ::-1])
        if not ok:
            raise RequestError(500, f"{name}: the picture could not be encoded")
        with self._lock:
            self._images[key] = data.tobytes()
            while len(self._images) > PICTURES_KEPT:
                self._images.popitem(last=False)
        return data.tobytes()

    def preview_preset(self, preset: Preset) -> Preset:
        """The entry's preset made small and short: same aspect, a few seconds to render."""
        scale = PREVIEW_LONG_SIDE_PX / max(preset.width_px, preset.height_px)
        return with_overrides(
            preset, width_px=2 * round(preset.width_px * scale / 2),
            height_px=2 * round(preset.height_px * scale / 2),
            duration_s=min(preset.duration_s, PREVIEW_MAX_DURATION_S),
            fps=min(preset.fps, PREVIEW_FPS), codec="libx264", pix_fmt="yuv420p", crf=28,
            encoder_preset="veryfast",
        )

    def preview(self, name: str, data: Any) -> str:
        """Render (or find cached) the preview clip of a photo under an edited entry; its key."""
        state = self._photo(name)
        if not isinstance(data, dict):
            raise RequestError(400, "'entry' must be a manifest entry object")
        try:
            entry = manifest_from_data({"version": 1, "images": {name: data}},
                                       self.manifest_path).entries[name]
            preset, options = self._settings(name, data)
            self._checked_plan(entry)
            preset = self.preview_preset(preset)
        except (ManifestError, PresetError) as error:
            raise RequestError(400, str(error)) from error
        # The preview preset already carries the entry's preset and duration.
        clip_data = {k: v for k, v in data.items() if k not in ("preset", "duration_s")}
        key = _digest({"inputs": self._inputs(state.path, options),
                       "preset": preset.frame_settings(),
                       "options": asdict(replace(options, threads=1)), "entry": clip_data})
        path = self.preview_path(key)
        with self._key_lock(key):
            if not path.is_file():
                clip_entry = ManifestEntry(name, clip_data, self.manifest_path)
                try:  # clips never make their folder (make_clip): the previews' is ours
                    path.parent.mkdir(parents=True, exist_ok=True)
                except OSError as error:
                    raise RequestError(500, f"{path.parent}: previews cannot be written "
                                            f"({error.strerror or error})") from error
                result = make_clip(state.path, path, preset,
                                   replace(options, threads=PREVIEW_THREADS),
                                   show_progress=False, entry=clip_entry)
                if result.status != "done":
                    if result.detail:
                        log.error("preview of %s failed:\n%s", name, result.detail)
                    status = 507 if result.status == "no_space" else 422  # storage, not photo
                    raise RequestError(status, result.error or f"{name}: preview failed")
        return key

    def preview_path(self, key: str) -> Path:
        return self.cache_dir / "previews" / f"{key}.mp4"


def _stat_signature(path: Path) -> tuple[int, int, int] | None:
    """Inode, size and time of a file, None where there is none: a manifest replaced by a
    save or an editor's rename has another inode."""
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return stat.st_ino, stat.st_size, stat.st_mtime_ns


MANIFEST_LOCK_WAIT_S = 30.0
"""How long a save waits for another review's save of the same manifest."""


@contextlib.contextmanager
def manifest_lock(manifest: Path):
    """An exclusive lock on one manifest across processes: two reviews of one folder each
    read, changed and wrote the whole file, and one's save silently undid the other's. The
    lock is a file in the temporary folder named by the manifest's real path (the manifest
    itself is replaced by each save, and need not exist yet), so nothing is left beside it;
    opened for reading, another user's lock file locks too, and it is removed after each save
    (they were never removed: hundreds piled up in /tmp)."""
    from kbbatch.journal import locked_within

    key = hashlib.sha256(os.fsencode(os.path.realpath(manifest))).hexdigest()[:24]
    path = Path(tempfile.gettempdir()) / f"kbbatch-manifest-{key}.lock"
    deadline = time.monotonic() + MANIFEST_LOCK_WAIT_S
    while True:
        try:
            descriptor = _open_lock_file(path)
        except FileExistsError:  # made by another review between its two tries
            continue
        except OSError as error:  # this server's own lock still holds
            log.warning("%s: no lock against other reviews (%s)", path, error.strerror or error)
            yield
            return
        if not locked_within(descriptor, max(0.0, deadline - time.monotonic())):
            os.close(descriptor)
            raise RequestError(409, f"{manifest}: another review is saving it (it holds "
                               f"{path}); try again")
        try:
            if os.path.samestat(os.fstat(descriptor), os.stat(path)):
                break
        except OSError:
            pass
        os.close(descriptor)  # removed by the save before, as this one waited: take it anew
    try:
        yield
    finally:
        with contextlib.suppress(OSError):  # another user's, in a sticky /tmp: it stays
            path.unlink()
        os.close(descriptor)


def _open_lock_file(path: Path) -> int:
    """The lock file opened for reading, made if missing. Opened with O_CREAT, another
    user's file in a sticky /tmp is refused where fs.protected_regular is set (systemd's
    default), so it is made only when it is not there."""
    try:
        return os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return os.open(path, os.O_RDONLY | os.O_CREAT | os.O_EXCL, 0o644)


def unreadable_words(error: OSError, name: str) -> str:
    """What to say of a photo or map removed or made unreadable while the page is open."""
    if isinstance(error, FileNotFoundError):
        return f"{error.filename or name}: no longer there (removed while the page was open?)"
    return f"{error.filename or name}: cannot be read ({error.strerror or error})"


REQUEST_BODY_MAX_BYTES = 64 << 20
"""The largest request body read (a save of some 100,000 edited entries): a 200 MB body was
read whole into memory (the server grew to 670 MB)."""


def _json_body() -> dict[str, Any]:
    """The request's JSON object, read by the manifest's rules (no NaN, huge numbers, repeated
    keys or nesting deep enough to exhaust the stack: that one was a 500)."""
    raw = request.get_data()
    if len(raw) >= REQUEST_BODY_MAX_BYTES:  # a chunked body is cut there, not refused
        raise RequestError(413, f"the request body is {REQUEST_BODY_MAX_BYTES >> 20} MiB or "
                                "more; not read")
    try:
        data = parse_manifest_text(raw.decode("utf-8"))
    except (ValueError, json.JSONDecodeError) as error:
        raise RequestError(400, f"the request body must be a JSON object ({error})"
                           ) from error
    if not isinstance(data, dict):
        raise RequestError(400, "the request body must be a JSON object")
    return data


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _name_as_sent(name: str) -> str:
    """The photo name in /api/photos/<name>/..., from the request's own bytes: Flask decodes
    the path as UTF-8 and replaces what is not, so a name that is not UTF-8 (its bytes sent
    percent-encoded as they are) was never found. The server keeps the raw request path."""
    from urllib.parse import unquote_to_bytes

    raw_uri = request.environ.get("RAW_URI") or request.environ.get("REQUEST_URI") or ""
    raw = unquote_to_bytes(raw_uri.split("?", 1)[0]).split(b"/")
    return os.fsdecode(raw[3]) if len(raw) == 5 and raw[1:3] == [b"api", b"photos"] else name


def _host_name(host_header: str | None) -> str:
    """'127.0.0.1:8765' -> '127.0.0.1', '[::1]:8765' -> '[::1]'."""
    host = host_header or ""
    return host if host.endswith("]") or ":" not in host else host.rsplit(":", 1)[0]


def create_app(session: ReviewSession, allowed_hosts: tuple[str, ...] | None = LOCAL_HOSTS
               ) -> Flask:
    """The Flask application over one review session.

    Requests must name one of allowed_hosts (None: any, for a server exposed on purpose with
    --host), so that a web page elsewhere cannot reach it through DNS rebinding.
    """
    app = Flask(__name__, static_folder=str(STATIC_FOLDER), static_url_path="/static")
    app.json.sort_keys = False
    app.url_map.merge_slashes = False  # '//' is refused, not redirected
    app.config["MAX_CONTENT_LENGTH"] = REQUEST_BODY_MAX_BYTES  # larger: 413, unread
    app.wsgi_app = session.answering(app.wsgi_app)  # type: ignore[method-assign]

    def is_token(sent: str | None) -> bool:
        return bool(sent) and secrets.compare_digest(sent.encode(), session.token.encode())

    @app.before_request
    def guard() -> Response | None:
        if allowed_hosts and _host_name(request.host) not in allowed_hosts:
            raise RequestError(403, f"host {request.host!r} is not served (DNS rebinding?)")
        if request.method == "OPTIONS":
            return None
        if request.method not in ("GET", "HEAD"):  # a page elsewhere cannot set the header
            if not is_token(request.headers.get(TOKEN_HEADER)):
                raise RequestError(403, f"missing or wrong {TOKEN_HEADER} header")
            return None
        # Every user of the machine reaches the loopback address: without the token, another
        # user read the photos of a private folder and took the token from the page.
        cookie = token_cookie(request.environ.get("SERVER_PORT", ""))
        if request.path == "/" and is_token(request.args.get(TOKEN_PARAMETER)):
            response = redirect("/", 303)  # the token leaves the address bar and history
            # Lax: the address opened from another page (a chat, a web terminal) is a
            # cross-site visit, which a Strict cookie does not follow; a GET changes nothing
            response.set_cookie(cookie, session.token, httponly=True, samesite="Lax")
            return response
        if is_token(request.headers.get(TOKEN_HEADER)) or is_token(request.cookies.get(cookie)):
            return None
        raise RequestError(403, "this review session's key is missing: open the address "
                           f"`kbbatch review` printed (it ends in ?{TOKEN_PARAMETER}=...)")

    @app.errorhandler(RequestError)
    def refused(error: RequestError) -> tuple[Response, int]:
        return jsonify(error=error.message), error.status

    @app.errorhandler(HTTPException)
    def http_error(error: HTTPException) -> tuple[Response, int]:
        return jsonify(error=f"{error.name}: {error.description}"), error.code or 500

    @app.errorhandler(OSError)
    def unreadable(error: OSError) -> tuple[Response, int]:
        """A photo or map removed or made unreadable while the page is open: say which."""
        gone = isinstance(error, FileNotFoundError)
        return jsonify(error=unreadable_words(error, "a file") + ("; reload the page" if gone
                                                                  else "")), 404 if gone else 422

    @app.errorhandler(Exception)
    def unexpected(error: Exception) -> tuple[Response, int]:
        log.exception("request %s %s failed", request.method, request.path)
        return jsonify(error=f"internal error ({type(error).__name__}); see the server log"), 500

    @app.get("/")
    def index() -> Response:
        page = (STATIC_FOLDER / "index.html").read_text(encoding="utf-8")
        page = page.replace("__KBBATCH_TOKEN__", session.token)
        response = Response(page, mimetype="text/html")
        response.headers["Cache-Control"] = "no-store"
        return response

    @app.get("/api/photos")
    def photos() -> Response:
        return jsonify(session.overview())

    @app.get("/api/photos/<name>/image")
    def image(name: str) -> Response:
        return _picture(name, "image", "image/jpeg")

    @app.get("/api/photos/<name>/depth")
    def depth(name: str) -> Response:
        return _picture(name, "depth", "image/png")

    def _picture(name: str, kind: str, mimetype: str) -> Response:
        try:
            return Response(session.picture(_name_as_sent(name), kind), mimetype=mimetype)
        except ImageReadError as error:
            raise RequestError(422, str(error)) from error

    @app.post("/api/auto-plan")
    def auto_plan() -> Response:
        body = _json_body()
        data = body.get("entry") or None
        if data is not None and not isinstance(data, dict):
            raise RequestError(400, "'entry' must be a manifest entry object")
        try:
            plan = session.auto_plan(body.get("name"), data)
        except ImageReadError as error:
            raise RequestError(422, str(error)) from error
        return jsonify(plan=plan)

    @app.post("/api/preview")
    def preview() -> Response:
        body = _json_body()
        key = session.preview(body.get("name"), body.get("entry"))
        return jsonify(url=f"/api/previews/{key}.mp4")

    @app.get("/api/previews/<key>.mp4")
    def preview_file(key: str) -> Response:
        if len(key) != 32 or any(c not in "0123456789abcdef" for c in key):
            raise RequestError(404, "no such preview")
        path = session.preview_path(key)
        if not path.is_file():
            raise RequestError(404, "no such preview (render it with POST /api/preview)")
        return send_file(path, mimetype="video/mp4", conditional=True)

    @app.post("/api/save")
    def save() -> Response:
        body = _json_body()
        return jsonify(session.save(body.get("entries"), body.get("bases")))

    return app


class ReviewServer:
    """The threaded HTTP server of a session, on host:port (port 0: any free port)."""

    def __init__(self, session: ReviewSession, host: str = "127.0.0.1", port: int = 0) -> None:
        bare = host.strip("[]")
        in_url = f"[{bare}]" if ":" in bare else bare  # an IPv6 address is bracketed in a URL
        # A loopback address in any spelling (::1 turned the DNS-rebinding guard off) serves
        # only requests that name a local host; another address is exposed on purpose.
        hosts = (*LOCAL_HOSTS, in_url) if is_loopback(bare) else None
        try:  # werkzeug prints a bare "Name or service not known" and exits
            socket.getaddrinfo(bare, port)
        except socket.gaierror as error:
            raise OSError(f"{host} is no address of this machine ({error.strerror})") from error
        self.session = session
        # Bound here, so that a port in use is an OSError to act on: werkzeug prints its own
        # words and exits the process.
        family = socket.AF_INET6 if ":" in bare else socket.AF_INET
        with socket.create_server((bare, port), family=family) as listener:
            self.server = make_server(bare, listener.getsockname()[1],
                                      create_app(session, hosts), threaded=True,
                                      fd=listener.fileno())
        self.port = self.server.server_address[1]
        shown = {"0.0.0.0": "127.0.0.1", "::": "[::1]"}.get(bare, in_url)
        self.url = f"http://{shown}:{self.port}/?{TOKEN_PARAMETER}={session.token}"
        if hosts is None:
            log.warning("serving on %s:%d in plain HTTP: whoever sees the address with its "
                        "token, or the traffic, can read the photos and edit the manifest",
                        in_url, self.port)

    def serve(self, ready: Callable[[str], None] | None = None) -> None:
        self.session.start_planning()
        try:  # a stop in ready() stops the planning too
            if ready:
                ready(self.url)
            self.server.serve_forever()
        finally:
            self.session.stop()

    def shutdown(self) -> None:
        self.server.shutdown()
        self.server.server_close()
