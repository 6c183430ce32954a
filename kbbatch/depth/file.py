"""Depth or disparity maps supplied by the user beside the photo.

`<stem>.depth.png|.npy|.exr` holds depth (larger is farther); `<stem>.disparity.png|.npy|.exr`
holds disparity (larger is nearer). PNGs may be 8 or 16-bit; zero marks an unknown pixel, and
so does infinite depth (a renderer's empty sky). OpenEXR files, as 3D software writes its depth
passes, need the optional OpenEXR package (`pip install "kbbatch[exr]"`).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import time
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from kbbatch.camera import ASPECT_TOLERANCE
from kbbatch.depth import DepthError, DepthResult
from kbbatch.images import (
    DEPTH_MAP_NAME,
    SOURCE_SHA256_KEY,
    map_stem,
    own_png_text,
    read_image_bytes,
)
from kbbatch.layers import nearest_pixels, nearest_with_distance

log = logging.getLogger(__name__)

DEPTH_FILE_KINDS = ("depth", "disparity")
DEPTH_FILE_SUFFIXES = (".png", ".npy", ".exr")

FRESH_LISTING_S = 2.0
"""A folder's list of maps is kept while its modification time is at least this old."""

EXR_DEPTH_CHANNELS = ("Z", "depth", "*.Z", "Y", "R")
"""Channels an OpenEXR map is read from, in order of preference (*.Z: a render layer's depth
pass; Y or R: a map saved as an image); else the only channel there is."""


def find_depth_file(photo_path: Path) -> Path | None:
    """The user's depth or disparity map beside a photo, if any: `<stem>.depth.png` and the
    rest of images.DEPTH_MAP_NAME, in any case (`.depth.PNG` from a camera tool was left out
    of the photos as a map, yet never used as one). Depth before disparity, PNG before .npy
    before .exr, the lower-case spelling first."""
    try:
        listing = os.stat(photo_path.parent).st_mtime_ns
    except OSError:
        return None
    # A folder changed within its clock's resolution of now may change again unseen under
    # the same time (a network share's is 1 to 2 s): its listing is read afresh.
    recent = time.time_ns() - listing < FRESH_LISTING_S * 1e9
    maps_in = _maps_in.__wrapped__ if recent else _maps_in
    names = maps_in(str(photo_path.parent), listing).get(photo_path.stem, ())

    def preference(name: str) -> tuple[int, int, bool]:
        kind, suffix = _map_kind(name), name.rsplit(".", 1)[1].lower()
        return (DEPTH_FILE_KINDS.index(kind), DEPTH_FILE_SUFFIXES.index(f".{suffix}"),
                name != name.lower())

    usable = []
    for name in sorted(names, key=preference):
        candidate = photo_path.with_name(name)
        if not candidate.is_file():
            with contextlib.suppress(OSError):  # gone since the listing: nothing to say
                _say_not_a_file(str(candidate), os.lstat(candidate).st_ino, str(photo_path))
            continue
        if not is_another_photos_map(candidate, photo_path):
            usable.append(name)
    if len(usable) > 1:
        _say_one_of_several(str(photo_path), tuple(usable))
    return photo_path.with_name(usable[0]) if usable else None


@functools.lru_cache(maxsize=64)
def _say_one_of_several(photo_name: str, map_names: tuple[str, ...]) -> None:
    """Said once: with a depth and a disparity map beside a photo, one was used without a
    word, and the clip looked wrong if the user had meant the other."""
    log.warning("%s: %s are maps of this photo; %s is used (depth before disparity, PNG "
                "before .npy before .exr): remove the others", photo_name,
                " and ".join(map_names), map_names[0])


@functools.lru_cache(maxsize=64)
def _say_not_a_file(map_name: str, _inode: int, photo_name: str) -> None:
    """Said once per file: a named pipe, a folder or a link to a device under a map's name
    was passed over without a word, and the clip made with another depth."""
    log.warning("%s: not used as the depth map of %s: not a regular file (a named pipe, "
                "device, folder, or a link to one or to nothing)", map_name, photo_name)


def is_another_photos_map(map_path: Path, photo_path: Path) -> bool:
    """Whether a map is one kbbatch wrote (`--save-depth`) from another photo than this one,
    or from a photo it did not record: an output folder that also holds photos had
    `IMG_1.disparity.png` of one photo taken for the depth of another `IMG_1.jpg`. A map of
    the user's (one kbbatch did not write, or one edited since, which loses the mark) is
    theirs to pair with the photo."""
    if map_path.suffix.lower() != ".png":
        return False  # kbbatch writes PNG maps only
    try:
        map_stat, photo_stat = map_path.stat(), photo_path.stat()
    except OSError:
        return False
    return _is_another_photos_map(
        str(map_path), (map_stat.st_ino, map_stat.st_size, map_stat.st_mtime_ns),
        str(photo_path), (photo_stat.st_ino, photo_stat.st_size, photo_stat.st_mtime_ns))


@functools.lru_cache(maxsize=64)
def _is_another_photos_map(map_name: str, map_version: tuple[int, int, int], photo_name: str,
                           photo_version: tuple[int, int, int]) -> bool:
    """is_another_photos_map for one version of each file: the photo is hashed, and the
    warning given, once while neither changes (a photo's map is looked for several times)."""
    from kbbatch.fingerprint import file_sha256

    text = own_png_text(Path(map_name))
    if text is None:
        return False
    recorded = text.get(SOURCE_SHA256_KEY)
    try:
        if recorded is not None and recorded == file_sha256(Path(photo_name)):
            return False
    except OSError:  # the photo cannot be read: reading it says so, and why
        return False
    made_from = "another photo" if recorded else "a photo it did not record"
    log.warning("%s: not used as the depth map of %s: kbbatch wrote it (--save-depth) from %s",
                map_name, photo_name, made_from)
    return True


@functools.lru_cache(maxsize=8)
def _maps_in(folder: str, listing_mtime_ns: int) -> dict[str, list[str]]:
    """The map files of a folder by their photo's stem, listed once while the folder stays
    unchanged (a batch looks for every photo's map)."""
    maps: dict[str, list[str]] = {}
    try:
        entries = os.listdir(folder)
    except OSError:
        return maps
    for name in entries:
        stem = map_stem(name)
        if stem is not None:
            maps.setdefault(stem, []).append(name)
    return maps


def _map_kind(name: str) -> str:
    """"depth" or "disparity": what a map's name says it holds (a manifest may name any file:
    then depth, unless "disparity" is one of its dotted parts)."""
    found = DEPTH_MAP_NAME.search(name)
    if found is not None:
        return found.group(1).lower()
    return "disparity" if "disparity" in name.lower().split(".")[1:-1] else "depth"


NPY_MAGIC = b"\x93NUMPY"


def load_map(path: Path) -> np.ndarray:
    """A single-channel float32 map from a PNG (8/16-bit), .npy or OpenEXR file."""
    if path.suffix.lower() == ".exr":
        data = load_exr(path)
    elif path.suffix.lower() == ".npy":
        try:
            with path.open("rb") as handle:
                is_npy = handle.read(len(NPY_MAGIC)) == NPY_MAGIC
            if not is_npy:  # np.load reads other bytes as pickled data, and says so
                raise ValueError("it does not begin as a NumPy .npy file does")
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise DepthError(f"{path}: not a readable .npy array ({error})") from error
    else:
        try:  # read by Python: cv2.imread takes only UTF-8 names
            data = read_image_bytes(path)
        except OSError as error:
            raise DepthError(f"{path}: not a readable image ({error.strerror or error})"
                             ) from error
        if data is None:
            raise DepthError(f"{path}: not a readable image")
    data = np.asarray(data)
    if data.ndim > 2 and sum(side > 1 for side in data.shape) == 2:
        data = data.squeeze()  # a (1, H, W) array, as a network's output is saved
    if data.ndim == 3:  # grey saved as colour is fine; a colour-mapped picture is no depth
        colour = data[..., :3]
        if not all(np.array_equal(colour[..., k], colour[..., 0], equal_nan=True)
                   for k in range(1, colour.shape[-1])):
            raise DepthError(f"{path}: is a colour picture; a depth map has one channel "
                             "(grey levels)")
        data = data[..., 0]
    if data.ndim != 2:
        raise DepthError(f"{path}: expected a 2D map, got shape {data.shape}")
    if data.dtype == np.bool_:  # read as 0 and 1 it was "constant", which it is not
        raise DepthError(f"{path}: holds true/false values (a mask?), not depths")
    if np.iscomplexobj(data):  # cast, the imaginary parts were dropped with a warning
        raise DepthError(f"{path}: holds complex numbers, not depths")
    data = _in_float32_range(data)
    try:
        return data.astype(np.float32)
    except (TypeError, ValueError) as error:  # records, strings: no depth
        raise DepthError(f"{path}: holds {data.dtype}, not numbers") from error


def _in_float32_range(data: np.ndarray) -> np.ndarray:
    """A float64 map scaled to its largest value where its values lie beyond float32's range:
    cast as they were, 1e-60 m depths all became 0 ("fewer than half of its pixels hold a
    positive value") and 1e300 ones infinite. A map's scale is free: depth is relative."""
    if not np.issubdtype(data.dtype, np.floating) or data.dtype.itemsize <= 4:
        return data
    positive = np.abs(data[np.isfinite(data) & (data != 0)])
    limits = np.finfo(np.float32)
    if positive.size == 0 or (positive.max() <= limits.max and positive.min() >= limits.tiny):
        return data
    return data / positive.max()


def load_exr(path: Path) -> np.ndarray:
    """The depth channel of an OpenEXR file (see EXR_DEPTH_CHANNELS)."""
    try:
        import OpenEXR
    except ImportError:
        raise DepthError(f'{path}: reading OpenEXR needs the OpenEXR package: '
                         f'pip install "kbbatch[exr]"') from None
    try:
        with contextlib.ExitStack() as stack:
            exr = stack.enter_context(OpenEXR.File(_exr_source(path, stack),
                                                   separate_channels=True))
            channels = {name: channel.pixels for name, channel in exr.channels().items()}
    except Exception as error:  # the bindings raise plain exceptions for bad files
        raise DepthError(f"{path}: not a readable OpenEXR file ({error})") from error
    preferred = [
        name for wanted in EXR_DEPTH_CHANNELS for name in sorted(channels)
        if name == wanted or (wanted.startswith("*") and name.endswith(wanted[1:]))
    ]
    if preferred:
        return np.asarray(channels[preferred[0]])
    if len(channels) == 1:
        return np.asarray(next(iter(channels.values())))
    raise DepthError(f"{path}: no depth channel among {sorted(channels)} "
                     f"(expected one of {', '.join(EXR_DEPTH_CHANNELS)})")


def _exr_source(path: Path, stack: contextlib.ExitStack) -> str | BinaryIO:
    """What OpenEXR.File reads: the path, or a file Python opened where the name is not UTF-8
    (the bindings refuse such a name; a stream they read; a UTF-8 name stays a name, as every
    OpenEXR release the `exr` extra allows reads one)."""
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return stack.enter_context(path.open("rb"))
    return name


def disparity_from_map(data: np.ndarray, kind: str, path: Path, image: np.ndarray
                       ) -> np.ndarray:
    """Validate a user map and turn it into disparity at the photo's (image's) size."""
    height, width = image.shape[:2]
    if np.isnan(data).any() or (kind == "disparity" and np.isinf(data).any()):
        raise DepthError(f"{path}: contains NaN or infinite values")
    valid = (data > 0) & np.isfinite(data)  # infinite depth: as far as the farthest known
    if valid.sum() < 0.5 * data.size:
        raise DepthError(f"{path}: fewer than half of its pixels hold a positive value")
    values = data[valid]
    if float(values.max() - values.min()) <= 1e-6 * max(1.0, float(values.max())):
        raise DepthError(f"{path}: is constant, so it holds no depth")
    map_aspect = data.shape[1] / data.shape[0]
    photo_aspect = width / height
    if abs(map_aspect / photo_aspect - 1.0) > ASPECT_TOLERANCE:
        raise DepthError(f"{path}: is {data.shape[1]}x{data.shape[0]} (aspect {map_aspect:.3f}) "
                         f"but the photo's aspect is {photo_aspect:.3f}")
    disparity = np.zeros(data.shape, np.float32)
    disparity[valid] = values if kind == "disparity" else 1.0 / values
    farthest = float(disparity[valid].min())
    # Infinite depth (a renderer's empty sky) is the farthest of all; an unknown pixel (a
    # sensor's shadow, a stereo occlusion) lies beside an object, on the far side.
    disparity[np.isinf(data)] = farthest
    colour = cv2.resize(image, (data.shape[1], data.shape[0]), interpolation=cv2.INTER_AREA)
    disparity = far_side_fill(disparity, disparity > 0, farthest, colour)
    if data.shape[0] <= height and data.shape[1] <= width:
        # Kept at its own size, as a network's map is: the depth stage's refinement brings it
        # up with its edges on the photo's colour edges. Enlarged here, every edge would be a
        # ramp of depths between the two sides, which no surface has.
        return disparity
    return cv2.resize(disparity, (width, height), interpolation=cv2.INTER_AREA)


NEAR_SIDE_COLOUR_RATIO = 2.0
"""An unknown pixel takes the near side's depth where its colour is this many times nearer
the near side's than the far side's: the colours of a shadow and of the surface it falls on
are alike; where both sides are alike, the far side keeps it."""

FAR_SIDE_COLOUR_DIFFERENCE = 30.0
"""... and differs from the far side's by more than this (RGB distance, of 0-255 levels): a
floor that runs on across a sensor's unknown frame edge is near and far at once."""

NEAR_SIDE_REACH_FRACTION = 0.015
"""... and lies within this share of the map's long side (or NEAR_SIDE_MEDIAN_PX) of the near
side: a black desk leg the sensor missed took, in parts, the depth of a black chair base
beside it, torn apart."""

NEAR_SIDE_MEDIAN_PX = 5
"""The pixels taking the near side's depth are cleaned by a median of this size (map px):
strips under half of it wide stay with the far side."""

GUIDE_BLUR_PX = 1.0
"""The colours compared are blurred by this (sigma, map px) so that noise does not decide."""


def far_side_fill(disparity: np.ndarray, known: np.ndarray, fallback: float,
                  colour: np.ndarray) -> np.ndarray:
    """Each unknown region filled from the far side of its border: every unknown pixel takes
    the value of the nearest border pixel at most halfway from the border's farthest
    disparity to its nearest; unless its colour (the photo at the map's size) is clearly
    nearer that of the nearest pixel on the near side (NEAR_SIDE_COLOUR_RATIO).

    A depth sensor's or a stereo pair's unknown pixels are mostly the shadow an object casts
    on what lies behind it. Set to the farthest depth of the whole map, each became a pit
    beside the object's outline, which the move opened into torn shards of fill; filled from
    the object's side, it would widen the object by its shadow. But a sensor also leaves its
    frame's edge unknown, across objects too: filled from the far side, a chair's edge there
    (TUM RGB-D) went to the floor's depth, a sliver torn off the chair by a dotted crack."""
    unknown = ~known
    if not unknown.any():
        return disparity.astype(np.float32)
    count, labels = cv2.connectedComponents(unknown.astype(np.uint8), connectivity=8)
    ring = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
    border = (ring > 0) & known
    label_of, value = ring[border], disparity[border]
    lowest = np.full(count, np.inf)
    highest = np.zeros(count)  # disparities are positive
    np.minimum.at(lowest, label_of, value)
    np.maximum.at(highest, label_of, value)
    far_side = np.zeros_like(known)
    far_side[border] = value <= 0.5 * (lowest + highest)[label_of]
    filled = disparity.astype(np.float32).copy()
    if not far_side.any():  # nothing known around anything unknown
        filled[unknown] = fallback
        return filled
    far = nearest_pixels(far_side, unknown)
    filled[unknown] = filled[far]
    near_side = border & ~far_side
    if near_side.any():
        near_rows, near_cols, distance = nearest_with_distance(near_side, unknown)
        near = (near_rows, near_cols)
        guide = cv2.GaussianBlur(colour.astype(np.float32), (0, 0), GUIDE_BLUR_PX)
        own = guide[unknown]
        far_difference = np.linalg.norm(own - guide[far], axis=1)
        near_difference = np.linalg.norm(own - guide[near], axis=1)
        of_near_side = np.zeros_like(known, dtype=np.uint8)
        reach = max(NEAR_SIDE_REACH_FRACTION * max(known.shape), NEAR_SIDE_MEDIAN_PX)
        of_near_side[unknown] = ((near_difference * NEAR_SIDE_COLOUR_RATIO < far_difference)
                                 & (far_difference > FAR_SIDE_COLOUR_DIFFERENCE)
                                 & (distance[unknown] <= reach))
        # a region, not scattered pixels (each a spike in the depth, cracks in the frame),
        # and one joined to the near side (an island of it would float, a fragment)
        of_near_side = cv2.medianBlur(of_near_side * 255, NEAR_SIDE_MEDIAN_PX)
        _, pieces = cv2.connectedComponents(of_near_side, connectivity=8)
        touching = np.unique(pieces[cv2.dilate(near_side.astype(np.uint8), np.ones((3, 3)))
                                    .astype(bool)])
        of_near_side = np.isin(pieces, touching[touching > 0])
        filled[unknown] = np.where(of_near_side[unknown], disparity[near], filled[unknown])
    return filled


class FileDepth:
    name = "file"

    def __init__(self, path: Path) -> None:
        self.path = path

    def disparity(self, image: np.ndarray, photo_path: Path | None, context: object = None
                  ) -> DepthResult:
        if not self.path.is_file():
            raise DepthError(f"{self.path}: depth file not found")
        kind = _map_kind(self.path.name)
        data = load_map(self.path)
        return DepthResult(disparity_from_map(data, kind, self.path, image), self.name,
                           str(self.path))
