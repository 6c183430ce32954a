"""One photo in, one palindromic 3D Ken Burns clip out: the one-clip pipeline.

This is the only module that knows the order of the stages:
image -> depth -> plan -> extended point cloud -> frames -> encoder.
Every runner (the batch, the daemon, the Ray executor) makes its clips with make_clip; none of
them is imported here.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import shutil
import sys
import tempfile
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from tqdm import tqdm

from kbbatch import paper
from kbbatch.camera import (
    Plan,
    SceneGeometry,
    View,
    crop_at,
    depth_from_disparity,
    nearest_depth,
    output_view,
)
from kbbatch.camera import working_size as compute_working_size
from kbbatch.depth import DepthError, DepthOptions, DepthResult, SceneContext, estimate_disparity
from kbbatch.depth import cache as depth_cache
from kbbatch.device import DeviceError, frames_device
from kbbatch.encode import EncoderStoppedError, clip_mark, encode_frames, palindrome_order
from kbbatch.images import (
    ImageReadError,
    atomic_output,
    disk_full_message,
    free_bytes,
    is_disk_full,
    read_photo,
)
from kbbatch.inpaint import build_extended_cloud, colour_inpainter
from kbbatch.interrupts import interrupted
from kbbatch.manifest import ManifestEntry, ManifestError
from kbbatch.planners import PlanRequest, get_planner
from kbbatch.presets import Preset, PresetError, load_preset, with_overrides
from kbbatch.render import PointCloud, render_frame
from kbbatch.risk import Risk, relieved
from kbbatch.risk import assess as assess_risk

MAX_CLOUD_POINTS = 40_000_000
"""The largest point cloud a clip may need; a crop so tight that it would need more is refused
with the smallest width that fits (measured: a 32 M-point cloud peaks at 3.3 GB)."""

MAX_POINT_SPACING_PX = 1.8
"""Points may land at most this far apart in the output at the tightest crop; bilinear splats
then still meet, so the cloud is upsampled when the photo itself is too small."""

MAX_RENDER_SPACING_PX = 1.3
"""Points may land up to this far apart in a rendered frame. Up to here the splats still blend
neighbouring points and a large photo's tight crop stays crisp (rendered smaller and enlarged,
the giraffe's fur went soft); beyond, each pixel copies its nearest point, in blocks."""

MAX_SHRUNK_SCALE = 0.9
"""A frame rendered smaller is at most this scale: enlarged by a ratio just above 1, linear
interpolation drifts through every phase across the frame, in bands of sharp and half-pixel
blurred columns some 100 px apart that the picture moves through."""

MIN_RENDER_STEPS = 24
"""A frame is rendered smaller than the output (see render_view) only when its sides share a
divisor of at least this many: steps of the scale finer than about 4 %."""

FRAME_STORE_RAM_BYTES = 1 << 30
"""Rendered frames are kept in memory up to this size, else in a temporary file, so that the
return half of the palindrome is read back rather than rendered twice."""

PROGRESS_LOG_INTERVAL_S = 30.0
"""How often progress is written when stderr is a log or a pipe rather than a terminal."""

SCRATCH_PREFIX = "kbbatch-frames-"
"""Temporary frame stores are named with this and their process id."""

CLIP_SUFFIX = ".mp4"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClipOptions:
    planner: str = "auto"
    depth: DepthOptions = DepthOptions()
    threads: int = max(1, os.cpu_count() or 1)
    cache_depth: bool = True
    save_depth: bool = False
    device: str = "cpu"
    """Where frames are rendered: a --device value (auto, cpu or cuda), resolved by the
    process that renders, or kbbatch.device.TORCH_CPU."""
    preset_overrides: tuple[tuple[str, float], ...] = ()
    """The command line's --duration and --fps ((setting, value) pairs), already in the run's
    preset and put over a preset a manifest entry names too (they were dropped there)."""


@dataclass
class ClipResult:
    source: str
    output: str | None
    # "done", "failed", "interrupted" (its encoder was stopped: taken again) or "no_space" (its
    # disk is full: kept queued, not failed)
    status: str
    seconds: float
    error: str | None = None
    depth_backend: str | None = None
    plan: dict | None = None
    stage_seconds: dict[str, float] = field(default_factory=dict)
    frames: int = 0
    detail: str | None = None  # traceback of an unexpected failure
    note: str | None = None  # e.g. why the clip is named by content
    risk: dict | None = None  # risk measures and the parallax relief chosen (kbbatch.risk)
    device: str | None = None  # where the frames were rendered
    full_folder: str | None = None  # "no_space": the folder whose disk had no room
    free_bytes_when_full: int | None = None  # "no_space": the room that disk had then
    preset: str | None = None  # what it was made with: a manifest entry's own, or the run's
    content: str | None = None  # sha256 of the photo's bytes it was made from

    def found_disk_full(self, folder: Path, reason: str | None) -> None:
        """Its clip's disk (folder's) had no room: queued, not failed. The room left is kept
        as it was then: the daemon waits for more than that, and measured once the result was
        read (after a pause), it counted room a user had made meanwhile as the full disk's."""
        self.status, self.full_folder = "no_space", str(folder)
        self.free_bytes_when_full = free_bytes(folder)
        self.error = disk_full_message(folder, Path(self.source), reason,
                                       self.free_bytes_when_full)


@dataclass(frozen=True)
class PreparedScene:
    """Everything the frames need, computed once per photo."""

    plan: Plan
    scene: SceneGeometry
    cloud: PointCloud
    depth_backend: str
    disparity: np.ndarray  # relative, at the working size
    risk: Risk | None = None
    points_per_working_px: float = 1.0  # the cloud's density, along each side


def cloud_scale(preset: Preset, plan: Plan, scene: SceneGeometry, source_long_px: int) -> float:
    """Point density relative to the working size: one point per output pixel at the widest
    crop when the photo has the pixels, and never so sparse that splats stop meeting."""
    widest = max(plan.start.width_px, plan.end.width_px)
    tightest = min(plan.start.width_px, plan.end.width_px)
    source_scale = source_long_px / max(scene.width_px, scene.height_px)
    wanted = min(preset.width_px / widest, source_scale)
    needed = preset.width_px / tightest / MAX_POINT_SPACING_PX
    return max(wanted, needed, 1.0)


MAX_PHOTO_ENLARGEMENT = 16.0
"""A crop the tool chose is enlarged at most this much to the output width: a 4000 x 12 px strip
planned a 16 px crop for a 640 px clip (40x, a 23 M-point cloud), spent 39 s in the fill and
gave a smear. (A manifest's crop is the user's choice, bound by the cloud size alone.)"""


class CropTooSmallError(ValueError):
    """A crop so tight that its clip would need an unbounded point cloud."""


def check_cloud_size(scale: float, plan: Plan, scene: SceneGeometry, preset: Preset,
                     source_width_px: int, photo_path: Path | None) -> None:
    points = scene.width_px * scene.height_px * scale * scale
    to_source = source_width_px / scene.width_px
    tightest_px = min(plan.start.width_px, plan.end.width_px) * to_source
    enlargement = preset.width_px / tightest_px
    chosen = plan.planner != "manifest"  # the tool chose the crop: the photo is too small
    if chosen and (points > MAX_CLOUD_POINTS or enlargement > MAX_PHOTO_ENLARGEMENT):
        raise CropTooSmallError(
            f"{photo_path or 'photo'}: too small for {preset.width_px} px wide clips (its "
            f"tightest crop, {tightest_px:.4g} of its {source_width_px} px, would be enlarged "
            f"{enlargement:,.1f}x into a {points / 1e6:,.0f} M-point cloud; the limits are "
            f"{MAX_PHOTO_ENLARGEMENT:.0f}x and {MAX_CLOUD_POINTS / 1e6:.0f} M): use a larger "
            "photo, or a preset with a smaller output")
    if points <= MAX_CLOUD_POINTS:
        return
    # the scale a crop needs is inversely proportional to its width: the narrowest crop within
    # the bound, computed without the scale (for a crop of 1e-307 px it overflows to inf)
    largest_scale = (MAX_CLOUD_POINTS / (scene.width_px * scene.height_px)) ** 0.5
    smallest_px = preset.width_px / (MAX_POINT_SPACING_PX * largest_scale) * to_source
    cloud = f"a {points / 1e6:,.0f} M-point" if math.isfinite(points) else "an unbounded"
    raise CropTooSmallError(
        f"{photo_path or 'photo'}: a crop {tightest_px:.4g} px wide (of {source_width_px} px) "
        f"is too tight for {preset.width_px} px output: it needs {cloud} point cloud (limit "
        f"{MAX_CLOUD_POINTS / 1e6:.0f} M); make the tightest crop at least "
        f"{math.ceil(smallest_px)} px wide")


def check_photo_size(photo_width_px: int, photo_height_px: int, preset: Preset,
                     photo_path: Path | None) -> None:
    """Refuse, before depth and planning, a photo whose widest crop of the clip's aspect would
    be enlarged more than MAX_PHOTO_ENLARGEMENT: any crop the tool chose would be (it is never
    wider), and a strip a few pixels high (5000 x 5) broke the planner's views, which round to
    no rows, with a ValueError in place of this message."""
    widest_px = min(float(photo_width_px), photo_height_px * preset.aspect)
    enlargement = preset.width_px / widest_px
    if enlargement > MAX_PHOTO_ENLARGEMENT:
        raise CropTooSmallError(
            f"{photo_path or 'photo'}: too small for {preset.width_px} px wide clips (it is "
            f"{photo_width_px}x{photo_height_px} px: its widest {preset.width_px}:"
            f"{preset.height_px} crop, {widest_px:.4g} px wide, would be enlarged "
            f"{enlargement:,.1f}x; the limit is {MAX_PHOTO_ENLARGEMENT:.0f}x): use a larger "
            "photo, or a preset with a smaller output")


def resize_to(image: np.ndarray, width: int, height: int) -> np.ndarray:
    shrinking = width < image.shape[1]
    interpolation = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interpolation)


STILL_TOLERANCE_PX = 0.5
"""Crops whose every edge moves less than this (working pixels) make no visible move."""


def _is_still(plan: Plan) -> bool:
    start, end = plan.start, plan.end
    return all(abs(a - b) < STILL_TOLERANCE_PX for a, b in (
        (start.left_px, end.left_px), (start.right_px, end.right_px),
        (start.top_px, end.top_px), (start.bottom_px, end.bottom_px)))


def prepare_scene(
    photo: np.ndarray,
    photo_path: Path | None,
    preset: Preset,
    options: ClipOptions,
    timings: dict[str, float],
    plan: Plan | None = None,
    content: str | None = None,
) -> PreparedScene:
    """Depth, plan and the extended point cloud for one photo (content: the sha256 of the
    bytes it was read from, when the caller has it)."""
    if plan is None:  # a manifest's crops are the user's: bound by the cloud size alone
        check_photo_size(photo.shape[1], photo.shape[0], preset, photo_path)
    clock = time.perf_counter()
    working, depth_result, depth = working_depth(photo, photo_path, options, content)
    height, width = working.shape[:2]
    timings["depth"] = time.perf_counter() - clock

    clock = time.perf_counter()
    if plan is None:
        plan = plan_photo(working, depth_result, depth, preset, options.planner)
    if not plan.parallax:
        depth = np.full_like(depth, float(depth.min()))
    scene = SceneGeometry(width, height, nearest_depth(depth))
    # the cloud a crop needs, checked before any view is rendered from it (a crop of 1e-300
    # px went through the risk's renders first: warnings of division by zero, and nonsense)
    scale = cloud_scale(preset, plan, scene, max(photo.shape[:2]))
    check_cloud_size(scale, plan, scene, preset, photo.shape[1], photo_path)
    if _is_still(plan):  # said of a clip that is made: crops too tight to render fail first
        log.warning("%s: the start and end crops are the same, so the clip is a still picture "
                    "(give the preset a zoom above 1, or the manifest two different crops)",
                    photo_path or "photo")
    risk = assess_risk(working, depth, plan, scene)
    relief = 1.0
    if risk.relief < 1.0 and risk.reasons:  # do no harm: less parallax, not a broken clip
        log.warning("%s: parallax reduced to %d%%: %s", photo_path or "photo",
                    round(100 * risk.relief), "; ".join(risk.reasons))
        relief = risk.relief
        depth = relieved(depth, relief)
        scene = SceneGeometry(width, height, nearest_depth(depth))
    timings["plan"] = time.perf_counter() - clock

    clock = time.perf_counter()
    # The height follows the rounded width, so the cloud keeps the scale the views assume.
    cloud_width = round(width * scale)
    photo_cloud = resize_to(photo, cloud_width, round(height * cloud_width / width))
    extension = build_extended_cloud(photo_cloud, depth, plan, scene, colour_inpainter(),
                                     enlargement=width / photo.shape[1], relief=relief)
    timings["inpaint"] = time.perf_counter() - clock
    return PreparedScene(plan, scene, extension.cloud, depth_result.backend,
                         depth_result.disparity, risk, cloud_width / width)


def plan_photo(working: np.ndarray, depth_result: DepthResult, depth: np.ndarray,
               preset: Preset, planner: str) -> Plan:
    """The named planner's plan."""
    return get_planner(planner).plan(plan_request(working, depth_result, depth, preset))


def plan_request(working: np.ndarray, depth_result: DepthResult, depth: np.ndarray,
                 preset: Preset) -> PlanRequest:
    """What a planner sees; ISNet's map, if it asks for it, is the one the depth stage worked
    out or the depth cache kept (else worked out now, and kept); known_saliency gives only
    the depth stage's own, alike on a depth-cache hit and a miss. With the ramp prior, chosen
    to run no network, there is none."""
    if depth_result.backend == "ramp":
        return PlanRequest(working, depth, preset)
    context = depth_result.segmentation or SceneContext(working)
    # what the depth stage worked out itself (before the planner asks for anything)
    stage_map = None if context.saliency_by_planner else context.known_saliency()
    return PlanRequest(working, depth, preset, lambda: context.saliency, lambda: stage_map)


def working_depth(photo: np.ndarray, photo_path: Path | None, options: ClipOptions,
                  content: str | None = None) -> tuple[np.ndarray, DepthResult, np.ndarray]:
    """The photo at the working size, its depth result, and depth in working units."""
    width, height = compute_working_size(photo.shape[1], photo.shape[0])
    working = resize_to(photo, width, height)
    depth_result = cached_disparity(working, photo_path, options, content)
    depth = depth_from_disparity(depth_result.disparity, paper.focal_px(max(width, height)))
    return working, depth_result, depth


def cached_disparity(working: np.ndarray, photo_path: Path | None, options: ClipOptions,
                     content: str | None = None) -> DepthResult:
    """The depth stage, through the on-disk cache when the photo is a file (keyed by content,
    the sha256 of the bytes working was read from; the file's, hashed now, without it)."""
    from kbbatch.fingerprint import depth_inputs, file_sha256

    if photo_path is None or not options.cache_depth:
        return estimate_disparity(working, photo_path, options.depth)
    key = depth_inputs(photo_path, content or file_sha256(photo_path), options.depth).digest(
        working.shape[:2])
    # ISNet's map, when the planner works it out after the entry is written, joins the entry
    keep_saliency = functools.partial(depth_cache.add_saliency, key)
    cached = depth_cache.load(key, working)
    if cached is not None and cached.disparity.shape == working.shape[:2]:
        if cached.segmentation is not None:
            return cached
        return replace(cached, segmentation=SceneContext(working, keep_saliency))
    result = estimate_disparity(working, photo_path, options.depth)
    depth_cache.store(key, result)
    if result.segmentation is not None and result.segmentation.known_saliency() is None:
        result.segmentation.on_saliency = keep_saliency
    return result


def frame_view(prepared: PreparedScene, preset: Preset, t: float) -> View:
    """The camera of the output frame at time t in [0, 1]."""
    return output_view(prepared.plan, prepared.scene, t, preset.width_px, preset.height_px)


def disparity_scale(prepared: PreparedScene) -> float:
    """Inverse depth to working disparity pixels, for the renderer's tolerances."""
    return prepared.scene.focal_px * paper.DISPARITY_MAX_PX


def point_spacing_px(prepared: PreparedScene, preset: Preset, t: float) -> float:
    """How far apart neighbouring points land in the output frame at time t (in the plane of
    the crops)."""
    return preset.width_px / (crop_at(prepared.plan, t).width_px
                              * prepared.points_per_working_px)


def clip_spacing_px(prepared: PreparedScene, preset: Preset) -> float:
    """How far apart points land at the clip's tightest crop (the start's or the end's: a
    crop's size moves monotonically between them)."""
    return max(point_spacing_px(prepared, preset, 0.0), point_spacing_px(prepared, preset, 1.0))


def render_view(view: View, spacing_px: float, clip_spacing: float | None = None) -> View:
    """The view a frame is rendered in before it is enlarged to the output view.

    Where points land well over a pixel apart, bilinear splats stop interpolating between
    them: each pixel copies its nearest point, in blocks (a tight crop of a small photo showed
    stair-stepped edges and blocky skin at 1080p). The frame is then rendered smaller, so that
    points land MAX_RENDER_SPACING_PX apart (or closer: the scale is at most
    MAX_SHRUNK_SCALE), and enlarged with linear
    interpolation. The scale is a whole number of steps of the sides' common divisor, so both
    sides stay whole and the enlargement is exact; sides with a divisor under
    MIN_RENDER_STEPS are rendered at the output size. The spacing is the crops' plane's (the
    nearest surface's): farther surfaces, magnified less, are rendered a little smaller than
    they need.

    clip_spacing, the clip's widest spacing (clip_spacing_px()): a clip is rendered smaller
    in all its frames or in none. Decided frame by frame, the frame where the spacing crossed
    the threshold went from sharp to soft at once: the variance of the Laplacian fell from
    373 to 142 between two frames of a 1700 px photo's clip.
    """
    widest = spacing_px if clip_spacing is None else max(spacing_px, clip_spacing)
    steps = math.gcd(view.width_px, view.height_px)
    if widest <= MAX_RENDER_SPACING_PX or steps < MIN_RENDER_STEPS:
        return view
    count = max(1, min(math.floor(steps * MAX_RENDER_SPACING_PX / spacing_px),
                       math.floor(steps * MAX_SHRUNK_SCALE)))
    scale = count / steps
    return View(view.position, view.focal_px * scale, view.principal_x_px * scale,
                view.principal_y_px * scale, view.width_px // steps * count,
                view.height_px // steps * count)


def rendered_view(prepared: PreparedScene, preset: Preset, t: float) -> View:
    """The view the frame at time t is rendered in (see render_view)."""
    return render_view(frame_view(prepared, preset, t), point_spacing_px(prepared, preset, t),
                       clip_spacing_px(prepared, preset))


def frame_at(prepared: PreparedScene, preset: Preset, t: float) -> np.ndarray:
    """One output frame at time t in [0, 1], every pixel filled."""
    rendered = rendered_view(prepared, preset, t)
    frame = render_frame(prepared.cloud, rendered, disparity_scale(prepared))
    if rendered.width_px == preset.width_px:
        return frame
    return cv2.resize(frame, (preset.width_px, preset.height_px), interpolation=cv2.INTER_LINEAR)


def frame_times(preset: Preset) -> list[float]:
    count = preset.frames_forward
    return [i / (count - 1) for i in range(count)]


GPU_BATCHES_AHEAD = 2
"""Launches of frames a GPU may render ahead of the encoder (bounded memory)."""


def render_clip_frames(
    prepared: PreparedScene,
    preset: Preset,
    threads: int,
    progress: Callable[[int], None] | None = None,
    device: str = "cpu",
) -> Iterator[np.ndarray]:
    """The palindromic frame sequence; each time step is rendered once, on the CPU in
    parallel threads, or on a GPU in launches of several frames while the encoder takes the
    previous ones. device: as ClipOptions.device."""
    device = frames_device(device)
    times = frame_times(preset)
    shape = (len(times), preset.height_px, preset.width_px, 3)
    with contextlib.ExitStack() as cleanup:
        store = frame_store(shape, cleanup)
        if device == "cpu":
            rendered = ordered_map(lambda t: frame_at(prepared, preset, t), times, threads)
        else:
            from kbbatch.device import torch_device
            from kbbatch.render_torch import render_batches

            views = [rendered_view(prepared, preset, t) for t in times]
            batches = render_batches(prepared.cloud, views, disparity_scale(prepared),
                                     torch_device(device), (preset.width_px, preset.height_px))
            rendered = (frame for batch in prefetched(batches, GPU_BATCHES_AHEAD)
                        for frame in batch)
        for index, frame in enumerate(rendered):
            store[index] = frame
            if progress:
                progress(1)
            yield frame
        for index in palindrome_order(len(times))[len(times):]:
            yield store[index]
        del store


def frame_store(shape: tuple[int, ...], cleanup: contextlib.ExitStack) -> np.ndarray:
    """Room for a clip's forward frames: in memory, or a temporary file whose disk space is
    reserved first. A sparse file on a temporary disk that filled up killed the whole batch
    with SIGBUS; now the clip fails at once as out of space, naming the folder."""
    if math.prod(shape) <= FRAME_STORE_RAM_BYTES:
        return np.empty(shape, np.uint8)
    scratch = Path(cleanup.enter_context(
        tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-")))
    path = scratch / "frames.npy"
    store = np.lib.format.open_memmap(path, "w+", np.uint8, shape)
    try:
        with path.open("r+b") as handle:
            os.posix_fallocate(handle.fileno(), 0, path.stat().st_size)
    except OSError as error:
        if not is_disk_full(error):
            raise
        raise OSError(error.errno, f"its {math.prod(shape) / 2**30:.1f} GB of frames need "
                      "room in the temporary folder: free some, or set TMPDIR to a folder on a "
                      "larger disk", tempfile.gettempdir()) from error
    return store


def progress_bar(iterable: Iterable | None = None, **options) -> tqdm | LogProgress:
    """A tqdm bar on a terminal; into a log or a pipe, plain lines now and then instead (no 0 %
    line, no carriage returns or escape codes)."""
    if sys.stderr.isatty():
        return tqdm(iterable, **options)
    return LogProgress(iterable, options.get("total"), options.get("desc", "").strip(),
                       options.get("unit", "it"), options.get("disable", False))


class LogProgress:
    """Progress for logs: `photos 3/12` at most every PROGRESS_LOG_INTERVAL_S, and at the end."""

    def __init__(self, iterable: Iterable | None, total: int | None, desc: str, unit: str,
                 disable: bool) -> None:
        self.iterable = iterable
        self.total = total if total is not None else (
            len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.unit, self.disable = desc, unit, disable
        self.count = 0
        self.last_written = time.monotonic()

    def __iter__(self) -> Iterator:
        for item in self.iterable or ():
            yield item
            self.update(1)

    def update(self, count: int = 1) -> None:
        self.count += count
        finished = self.total is not None and self.count >= self.total
        if not self.disable and (finished or time.monotonic() - self.last_written
                                 >= PROGRESS_LOG_INTERVAL_S):
            of = f"/{self.total}" if self.total is not None else ""
            print(f"{self.desc} {self.count}{of} {self.unit}(s)", file=sys.stderr, flush=True)
            self.last_written = time.monotonic()

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        """Nothing to clear: finished lines are already written (tqdm's close, for callers)."""


def remove_stale_scratch() -> list[Path]:
    """Remove frame stores whose process is gone (kill -9 skips cleanup; 4K ones take GBs)."""
    removed = []
    for folder in Path(tempfile.gettempdir()).glob(f"{SCRATCH_PREFIX}*-*"):
        owner = folder.name.removeprefix(SCRATCH_PREFIX).split("-")[0]
        if owner.isdigit() and not process_alive(int(owner)):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def ordered_map(function: Callable, items: list, threads: int) -> Iterator:
    """Results in order, computed by threads with at most 2 x threads in flight (bounded memory)."""
    threads = max(1, threads)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(function, item))
            if len(pending) >= 2 * threads:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def prefetched(items: Iterator, ahead: int) -> Iterator:
    """The items of an iterator, produced by a background thread at most `ahead` in advance
    (a bounded queue), so that producing and consuming overlap. Its errors are raised here;
    closing this generator stops the producer."""
    import queue
    import threading

    buffer: queue.Queue = queue.Queue(maxsize=ahead)
    stop = threading.Event()
    finished = object()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        buffer.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            buffer.put((finished, None))
        except BaseException as error:  # handed to the consumer
            buffer.put((finished, error))

    producer = threading.Thread(target=produce, name="kbbatch-prefetch", daemon=True)
    producer.start()
    try:
        while True:
            item, error = buffer.get()
            if error is not None:
                raise error
            if item is finished:
                return
            yield item
    finally:
        stop.set()
        while producer.is_alive():
            with contextlib.suppress(queue.Empty):
                buffer.get(timeout=0.1)
        producer.join()


def save_depth_images(clip_path: Path, disparity: np.ndarray, source_sha256: str | None = None
                      ) -> list[Path]:
    """A 16-bit disparity PNG (for other tools) and a coloured preview (for people). The map
    records the sha256 of its photo: found beside another photo of its name, it is not taken
    for that photo's depth (kbbatch.depth.file). A file of either name that kbbatch did not
    write is the user's: left as it is and returned (a clip keeps its name through a
    re-render, so its depth images' names may have been taken since it was first made)."""
    from kbbatch.images import SOURCE_SHA256_KEY, depth_image_names, is_users_file, write_image
    from kbbatch.review import depth_picture, normalised_disparity

    map_name, picture_name = depth_image_names(clip_path.name)
    text = {SOURCE_SHA256_KEY: source_sha256} if source_sha256 else None
    images = {clip_path.with_name(map_name):
              lambda: (normalised_disparity(disparity) * 65535 + 0.5).astype(np.uint16),
              clip_path.with_name(picture_name): lambda: depth_picture(disparity)}
    users = []
    for path, pixels in images.items():
        if is_users_file(path):
            users.append(path)
            continue
        write_image(path, pixels(), own=True, text=text if path.name == map_name else None)
    return users


def joined_notes(*notes: str | None) -> str | None:
    """The notes of one clip, all said (None when there is none)."""
    return "; ".join(note for note in notes if note) or None


def users_files_note(users: list[Path]) -> str:
    """Why --save-depth left out a depth image."""
    names = " and ".join(path.name for path in users)
    return (f"{users[0].parent}: {names} not written with the clip: a file of that name there "
            "is not kbbatch's and is left as it is")


def depth_images_missing(clip_path: Path) -> bool:
    """Whether a depth image --save-depth writes beside this clip is not there (deleted since:
    the clip, up to date, was skipped and the map never came back)."""
    from kbbatch.images import depth_image_names

    return any(not os.path.lexists(clip_path.with_name(name))
               for name in depth_image_names(clip_path.name))


def remove_stale_depth_images(clip_path: Path) -> list[Path]:
    """The depth images kbbatch wrote beside an earlier make of this clip, removed when it is
    made again without --save-depth: left, they showed the old photo beside the new clip.
    Only kbbatch's own (marked) files; a user's file of that name is never touched."""
    from kbbatch.images import depth_image_names, is_own_png

    removed = []
    for name in depth_image_names(clip_path.name):
        path = clip_path.with_name(name)
        if is_own_png(path):
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def plan_summary(plan: Plan, to_photo: float) -> dict:
    """The plan for the run report, its crops in the photo's own pixels (as a manifest gives
    them; to_photo: photo pixels per working pixel)."""
    return {"planner": plan.planner, "easing": plan.easing, "parallax": plan.parallax,
            "start": asdict(plan.start.scaled(to_photo)), "end": asdict(plan.end.scaled(to_photo))}


def apply_entry(entry: ManifestEntry | None, preset: Preset, options: ClipOptions
                ) -> tuple[Preset, ClipOptions]:
    """The preset and options for one photo, with its manifest entry's overrides."""
    if entry is None:
        return preset, options
    data = entry.data
    try:
        if "preset" in data:
            preset = with_overrides(load_preset(data["preset"],
                                                relative_to=entry.manifest.parent),
                                    **dict(options.preset_overrides))
    except PresetError as error:
        raise ManifestError(f"{entry.where('preset')}: {error}") from error
    try:
        preset = with_overrides(preset, duration_s=data.get("duration_s"))
    except PresetError as error:  # blamed on 'preset' before, which the entry may not have
        raise ManifestError(f"{entry.where('duration_s')}: {error}") from error
    # the entry's easing for the planner's crops too, not only its own (checked on loading)
    preset = with_overrides(preset, easing=data.get("easing"))
    if "planner" in data:  # a registered name: checked when the manifest loaded
        options = replace(options, planner=data["planner"])
    if entry.depth_file is not None and not entry.depth_file.is_file():
        raise ManifestError(f"{entry.where('depth')}: {entry.depth_file} is not a file")
    return preset, replace(options, depth=entry_depth(entry, options.depth))


def check_depth_is_not_the_photo(entry: ManifestEntry | None, source: Path) -> None:
    """Refuse an entry whose `depth` names its own photo (read as its own depth map, a grey
    photo was taken for one)."""
    if entry is not None and entry.depth_file == source.resolve():
        raise ManifestError(f"{entry.where('depth')}: names the photo itself; its depth map is "
                            "a file of its own (<stem>.depth.png, or .npy)")


def entry_depth(entry: ManifestEntry | None, depth: DepthOptions) -> DepthOptions:
    """The depth options for a photo: with the depth file its manifest entry names."""
    if entry is None or entry.depth_file is None:
        return depth
    return replace(depth, file=str(entry.depth_file))


def make_clip(
    source: Path,
    output: Path,
    preset: Preset,
    options: ClipOptions,
    show_progress: bool = True,
    entry: ManifestEntry | None = None,
    mark: str | None = None,
) -> ClipResult:
    """Render one photo into one clip; failures are returned, never raised. mark: the mark
    the clip carries where the caller knows it better than this process (a Ray worker's entry
    is rewritten to its scratch copies: the mark it made of that was no clip's, and a lost
    journal's clips were never adopted); else own_clip_mark."""
    started = time.perf_counter()
    timings: dict[str, float] = {}
    result = ClipResult(str(source), None, "failed", 0.0)
    given = preset, options  # the settings the clip's mark digests, as the runner does
    try:
        preset, options = apply_entry(entry, preset, options)
        result.preset = preset.name
        check_depth_is_not_the_photo(entry, source)
        clock = time.perf_counter()
        photo, result.content = read_photo(source)
        timings["read"] = time.perf_counter() - clock
        plan = None
        if entry is not None and entry.has_crops:
            working_width, _ = compute_working_size(photo.shape[1], photo.shape[0])
            plan = entry.plan(photo.shape[1], photo.shape[0], working_width, preset.aspect,
                              preset.easing)
            result.note = entry.planned_for_another(source)
        try:
            prepared = prepare_scene(photo, source, preset, options, timings, plan,
                                     result.content)
        except DepthError as error:  # the map a manifest names: said as the entry's fault
            if entry is None or not str(error).startswith(f"{entry.depth_file}: "):
                raise
            raise ManifestError(f"{entry.where('depth')}: {error}") from error
        result.depth_backend = prepared.depth_backend
        result.risk = prepared.risk.summary() if prepared.risk else None
        result.plan = plan_summary(prepared.plan, photo.shape[1] / prepared.scene.width_px)
        clock = time.perf_counter()
        result.device = frames_device(options.device)
        with progress_bar(total=preset.frames_forward, desc=f"  frames {source.name}",
                          unit="frame", leave=False, disable=not show_progress) as bar:
            frames = render_clip_frames(prepared, preset, options.threads, bar.update,
                                        result.device)
            with atomic_output(output, CLIP_SUFFIX, make_folder=False) as temp_path:
                result.frames = encode_frames(temp_path, frames, preset, mark or own_clip_mark(
                    source, result.content, *given, entry))
        timings["frames+encode"] = time.perf_counter() - clock
        # The depth images after the clip: written first, a run killed mid-encode left the new
        # photo's maps beside no clip (or beside the old photo's clip).
        if options.save_depth:
            users = save_depth_images(output, prepared.disparity, result.content)
            if users:
                result.note = joined_notes(result.note, users_files_note(users))
        else:
            removed = remove_stale_depth_images(output)
            if removed:
                result.note = joined_notes(result.note, (
                    f"{output.parent}: {' and '.join(p.name for p in removed)} removed: an "
                    "earlier make of this clip wrote them with --save-depth, and this one "
                    "does not (--save-depth writes them again)"))
        result.output = str(output)
        result.status = "done"
    except (ImageReadError, DepthError, ManifestError, CropTooSmallError,
            DeviceError) as error:
        result.error = str(error)
        if isinstance(error, DepthError) and not result.error.startswith(f"{source}: "):
            result.error = f"{source}: {result.error}"  # the photo, not only its map, named
    except EncoderStoppedError as error:  # a stop signal reached ffmpeg: the photo is taken again
        result.status = "interrupted"
        result.error = str(error)
    except Exception as error:  # one photo must never stop the batch
        if interrupted(error):  # but a Ctrl-C does, whatever a library made of it
            raise KeyboardInterrupt from error
        if is_disk_full(error):
            full = Path(error.filename) if error.filename else output.parent
            full = full if full.is_dir() else full.parent
            result.found_disk_full(full, error.strerror)
        else:
            result.error = f"{source}: {type(error).__name__}: {error}"
            result.detail = traceback.format_exc()
    result.seconds = time.perf_counter() - started
    result.stage_seconds = {k: round(v, 3) for k, v in timings.items()}
    return result


def own_clip_mark(source: Path, content: str, preset: Preset, options: ClipOptions,
                  entry: ManifestEntry | None) -> str | None:
    """The mark a clip carries (encode.clip_mark); None where its settings cannot be read."""
    try:
        return clip_mark(content, clip_fingerprints(source, content, preset, options, entry)[0])
    except OSError:
        return None


def clip_fingerprints(source: Path, content: str, preset: Preset, options: ClipOptions,
                      entry: ManifestEntry | None) -> tuple[str, ...]:
    """The digest of every input of a clip (kbbatch.fingerprint): photo, depth file, models,
    settings and the stages' code; then any other digest an up-to-date clip may have been
    recorded with. Threads and device are left out: the frames do not depend on them (the
    GPU renderer's are within 50 dB PSNR of the CPU's). Raises OSError when a depth file
    named for the photo cannot be read."""
    from kbbatch.fingerprint import clip_inputs

    # The entry's own preset file is an input too, by its settings: an edit to them makes a
    # new clip, a new name for the file does not. A bad entry is make_clip's to report (the
    # clip fails and is not skipped), so its words stay in the digest.
    entry_data = entry.data if entry else None
    try:
        preset, options = apply_entry(entry, preset, options)
        if entry_data is not None:
            entry_data = {k: v for k, v in entry_data.items() if k != "preset"}
    except ManifestError:
        pass

    def settings(save_depth: bool) -> tuple:
        return preset.frame_settings(), options.planner, entry_data, save_depth

    inputs = clip_inputs(source, content, options.depth, settings(options.save_depth))
    # With --save-depth the maps are outputs too: asking for them makes the clip again. A clip
    # made with them is the same clip without: a plain re-run made it again and removed the
    # maps a user had saved for compositing.
    if options.save_depth:
        return (inputs.digest,)
    return inputs.digest, inputs.with_settings(settings(True)).digest


@dataclass(frozen=True)
class ClipJob:
    """One photo of a batch to make into the clip at output (named and journaled already)."""

    source: Path
    output: Path
    entry: ManifestEntry | None = None
    name_note: str | None = None  # why output is not the name the naming rule wanted
    replaces_other_bytes: bool = False  # output holds a clip of this photo's earlier bytes
    content: str = ""  # sha256 of the photo's bytes when the job was started


class ClipExecutor(Protocol):
    """Makes the clips of a batch, yielding each job with its result once it is finished.

    Jobs are pulled lazily (each is started in the journal when pulled); results may come in
    any order; closing the iterator cancels what is outstanding."""

    def render(self, jobs: Iterable[ClipJob], preset: Preset, options: ClipOptions,
               show_progress: bool) -> Iterator[tuple[ClipJob, ClipResult]]: ...


class LocalExecutor:
    """One clip after another in this process, each using options.threads threads."""

    def render(self, jobs: Iterable[ClipJob], preset: Preset, options: ClipOptions,
               show_progress: bool) -> Iterator[tuple[ClipJob, ClipResult]]:
        for job in jobs:
            yield job, make_clip(job.source, job.output, preset, options, show_progress,
                                 job.entry)
