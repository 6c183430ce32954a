"""Reading photos (any common format, orientation, depth and colour model) and writing previews.

Everything here is at the edge of the pipeline: it turns files into 8-bit RGB arrays and
arrays into files, and names the file in every error.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import io
import logging
import os
import re
import secrets
import shutil
import stat
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageCms, ImageOps, UnidentifiedImageError

PHOTO_KINDS = ("jpg", "jpeg", "jpe", "jfif", "jif", "png", "webp", "tif", "tiff", "bmp")
"""The photo formats read, by file name (any case): a JPEG saved as .jfif or .jpe (as some
browsers and cameras name them) was passed over without a word."""

IMAGE_SUFFIXES = frozenset(f".{kind}" for kind in PHOTO_KINDS)

UNREAD_PHOTO_SUFFIXES = frozenset({
    ".heic", ".heif", ".hif", ".avif", ".gif", ".jxl", ".dng", ".cr2", ".cr3", ".crw", ".nef",
    ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2", ".pef", ".srw", ".iiq", ".3fr",
    ".x3f", ".erf", ".mrw", ".kdc", ".dcr", ".mos", ".rwl"})
"""Photo formats kbbatch does not read (a phone's HEIC, a camera's raw files): said, not passed
over in silence with an exit status of success."""

UNREAD_FORMAT_REASON = ("a photo format kbbatch does not read (convert it to JPEG, PNG, WebP, "
                        "TIFF or BMP)")

NAME_END_REASON = ("the name ends in a space or a dot (after the photo's own extension); not "
                   "taken: rename it to render it")
"""`IMG_1.jpg ` (a copy from a system that kept the space): its extension is no photo's, and it
was passed over without a word."""

MAX_SOURCE_PIXELS = 120_000_000
"""Larger images are decoded at a reduced size (JPEG) or refused, so memory stays bounded."""

DECODE_LONG_SIDE_PX = 6000
"""JPEGs above MAX_SOURCE_PIXELS are decoded at a power-of-two reduction near this size."""

ALPHA_MATTE_RGB = (0, 0, 0)
"""Transparent pixels are composited onto black, the video convention for an empty frame."""

Image.MAX_IMAGE_PIXELS = None  # we enforce our own, clearer limit below

log = logging.getLogger(__name__)



class ImageReadError(Exception):
    """A photo that cannot be used; the message names the file and the reason."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason


DEPTH_PREVIEW_SUFFIX = ".depth-preview.png"
"""The coloured depth picture `--save-depth` writes beside a clip: never a photo to render."""

SAVED_DISPARITY_SUFFIX = ".disparity.png"
"""The 16-bit disparity map `--save-depth` writes beside a clip."""


def depth_image_names(clip_name: str) -> tuple[str, str]:
    """The files `--save-depth` writes beside a clip: its disparity map and depth picture."""
    stem = Path(clip_name).stem
    return fitted_name(stem, SAVED_DISPARITY_SUFFIX), fitted_name(stem, DEPTH_PREVIEW_SUFFIX)


NAME_MAX_BYTES = 255
"""The longest file name (in bytes) the usual file systems take."""

NAME_DIGEST_HEX = 8
"""Hex digits of the digest that marks a stem cut to fit a name."""


def fitted_name(stem: str, tail: str) -> str:
    """stem + tail within NAME_MAX_BYTES: a stem too long for it is cut (at a character's
    start) and marked with a digest of the whole, so that two long stems differing only at
    their ends stay two names. A photo's name of 255 bytes is valid, and the names made from
    it (its content name, its depth maps, its failure report) failed only after the render."""
    name = stem + tail
    if len(os.fsencode(name)) <= NAME_MAX_BYTES:
        return name
    raw = os.fsencode(stem)
    mark = "~" + hashlib.sha256(raw).hexdigest()[:NAME_DIGEST_HEX]
    room = max(0, NAME_MAX_BYTES - len(os.fsencode(mark + tail)))
    while 0 < room < len(raw) and raw[room] & 0xC0 == 0x80:  # not inside a UTF-8 character
        room -= 1
    return os.fsdecode(raw[:room]) + mark + tail


DEPTH_MAP_NAME = re.compile(r"\.(depth|disparity)\.(png|npy|exr)$", re.IGNORECASE)
"""How a user's depth map's name ends (`IMG_1.depth.png`, kbbatch.depth.file): never a photo.
Only the end: `dive.depth.40m.jpg` is a photo (any `.depth.` in a name once hid it silently)."""


def map_stem(name: str) -> str | None:
    """The photo stem a depth map's file name is for (`a.depth.png`: `a`), else None."""
    found = DEPTH_MAP_NAME.search(name)
    return name[:found.start()] if found is not None and found.start() > 0 else None


OLD_PLAN_SHEET_SUFFIX = "-contact.jpg"
"""Versions before 0.x wrote `kbbatch plan`'s contact sheet as `<manifest>-contact.jpg` beside the
manifest and its `<manifest>-previews/` folder, often in the photo folder: not a photo."""

OLD_PLAN_SHEET_REASON = ("contact sheet of an earlier `kbbatch plan` (beside its previews "
                         "folder); not a photo, not rendered")


def is_old_plan_sheet(path: Path) -> bool:
    """Whether a file is a contact sheet an earlier `kbbatch plan` left among the photos."""
    name = path.name
    if not name.lower().endswith(OLD_PLAN_SHEET_SUFFIX):
        return False
    stem = name[: -len(OLD_PLAN_SHEET_SUFFIX)]
    return (path.parent / (stem + "-previews")).is_dir()


def is_image_file(path: Path) -> bool:
    """Whether a file looks like a photo we should process (hidden and depth maps excluded)."""
    name = path.name
    return (
        path.suffix.lower() in IMAGE_SUFFIXES
        and not name.startswith(".")
        and DEPTH_MAP_NAME.search(name) is None
        and not name.lower().endswith(DEPTH_PREVIEW_SUFFIX)
    )


def list_images(folder: Path) -> list[Path]:
    """Photos directly inside a folder, in name order."""
    return scan_folder(folder).photos


@dataclass(frozen=True)
class FolderScan:
    """What a folder holds for us: photos, and what looks like one but cannot be used."""

    photos: list[Path]
    broken_links: list[Path]  # photo names whose symbolic link points nowhere
    subfolders: list[Path]  # not searched: one folder is one batch
    not_files: list[Path] = field(default_factory=list)  # a photo's name on a pipe, a device
    unread_formats: list[Path] = field(default_factory=list)  # HEIC, raw: not read
    name_ends: list[Path] = field(default_factory=list)  # `IMG_1.jpg `: NAME_END_REASON
    plan_sheets: list[Path] = field(default_factory=list)  # an old `kbbatch plan`'s sheet
    hidden: list[Path] = field(default_factory=list)  # `.IMG_1.jpg`: photos by name, not taken
    lone_maps: list[Path] = field(default_factory=list)  # `x.depth.png`, no photo `x.*`


def broken_link_reason(link: Path) -> str:
    """Why a symbolic link leads to no photo: its target is missing, or links loop."""
    try:
        link.resolve(strict=True)
    except RuntimeError:  # Python 3.11 and 3.12 say a loop so
        return "symbolic link in a loop (it leads back to itself)"
    except OSError as error:
        if error.errno == errno.ELOOP:
            return "symbolic link in a loop (it leads back to itself)"
    try:
        return f"broken symbolic link (its target {os.readlink(link)} is missing)"
    except OSError:  # replaced meanwhile
        return "broken symbolic link"


def entry_kind(path: Path) -> str | None:
    """What a folder entry is to a runner: "subfolder", "photo", or a photo's name on what
    cannot be read as one, "broken_link" or "not_file" (a named pipe, socket or device: reading
    it would block); "gone" for a photo's name with nothing there now; "unread_format" for a
    photo in a format not read (UNREAD_PHOTO_SUFFIXES); "name_end" for a photo's name with
    spaces or dots after its extension (NAME_END_REASON); "plan_sheet" for an old version's
    contact sheet (is_old_plan_sheet); None for anything else. One answer for the batch's scan
    and the daemon's inbox."""
    if path.is_dir():
        return "subfolder"
    if not is_image_file(path):
        if path.suffix.lower() in UNREAD_PHOTO_SUFFIXES:
            return "unread_format"
        trimmed = path.name.rstrip(" .")  # empty for a name of dots and spaces only
        if trimmed and trimmed != path.name and is_image_file(path.with_name(trimmed)):
            return "name_end"
        return None
    if is_old_plan_sheet(path):
        return "plan_sheet"
    if path.is_file():
        return "photo"
    if path.is_symlink() and not path.exists():
        return "broken_link"
    return "not_file" if path.exists() else "gone"


def scan_folder(folder: Path, ignore: tuple[str, ...] = ()) -> FolderScan:
    """Photos directly inside a folder in name order, and the broken links and subfolders that
    would otherwise be passed over without a word."""
    found: dict[str | None, list[Path]] = {"photo": [], "broken_link": [], "subfolder": [],
                                           "not_file": [], "unread_format": [],
                                           "name_end": [], "plan_sheet": []}
    hidden = []
    for path in sorted(folder.iterdir()):
        if path.name in ignore:
            continue
        if path.name.startswith("."):  # a hidden file (or kbbatch's own temporary one)
            if is_hidden_photo(path):
                hidden.append(path)
            continue
        found.setdefault(entry_kind(path), []).append(path)
    stems = {path.stem for kind in ("photo", "broken_link", "not_file", "unread_format")
             for path in found[kind]} | {path.name.rstrip(" .").rsplit(".", 1)[0]
                                        for path in found["name_end"]}
    lone_maps = [path for path in found.get(None, ())
                 if (map_stem(path.name) not in (None, *stems)
                     or path.name.lower().endswith(DEPTH_PREVIEW_SUFFIX)) and path.is_file()]
    return FolderScan(found["photo"], found["broken_link"], found["subfolder"],
                      found["not_file"], found["unread_format"], found["name_end"],
                      found["plan_sheet"], hidden, lone_maps)


LONE_MAP_REASON = ("named as a depth map (`<photo>.depth.png`, `.disparity.png`, .npy, .exr) "
                   "or as kbbatch's depth preview (`.depth-preview.png`), with no photo of its "
                   "name beside it; not used (a photo named so is taken for one: rename it to "
                   "render it)")


def is_hidden_photo(path: Path) -> bool:
    """A photo's name made hidden by a leading dot: said, not taken (hidden files are not
    the user's photos to render, but one skipped without a word looked lost). macOS's `._`
    resource forks and kbbatch's temporary files are no photos."""
    return (path.name.startswith(".") and not path.name.startswith("._")
            and not TEMP_NAME.match(path.name) and is_image_file(path.with_name(path.name[1:]))
            and path.is_file())


TRUNCATED_JPEG_ROWS = 16
"""A JPEG whose data ends early still decodes (libjpeg only warns, and Pillow does not say):
its missing blocks come out the exact mid grey, to the bottom of the image. So many exactly
grey bottom rows (one or two rows of blocks) below other content mark it; a photo has noise
there. (A picture that really ends in a band of exactly #808080 is refused too, saying so: the
row where such a band begins cannot be told from the row where the data stopped, as chroma
upsampling tints both.)"""

_MISSING_BLOCK_LEVEL = 128  # a block with no coefficients: mid grey, every channel


def _ends_blank(image: Image.Image) -> bool:
    if image.mode not in ("RGB", "L") or image.height < TRUNCATED_JPEG_ROWS:
        return False
    tail = image.crop((0, image.height - TRUNCATED_JPEG_ROWS, image.width, image.height))
    if not np.all(np.asarray(tail) == _MISSING_BLOCK_LEVEL):
        return False
    # ... below something else: a wholly mid-grey picture is a (dull) picture
    return bool(np.any(np.asarray(image) != _MISSING_BLOCK_LEVEL))


def unreadable_reason(error: OSError) -> str:
    """Why a file could not be opened, in words (a permission problem is not corruption)."""
    if isinstance(error, PermissionError):
        return "cannot be read: permission denied"
    return f"cannot be read ({error.strerror or error})"


def read_image(path: Path) -> np.ndarray:
    """An 8-bit RGB array, upright as the camera's EXIF says, from any supported file.

    What the decoders warn of (Pillow: "Corrupt EXIF data") is logged with the file's name:
    printed as Python warnings, they named no photo, twice per file in a plan and render."""
    return read_photo(path, hashed=False)[0]


def read_photo(path: Path, hashed: bool = True) -> tuple[np.ndarray, str]:
    """read_image's array and the sha256 of the very bytes decoded ("" unless hashed).

    Both come from one read of the file: hashed by one read and decoded from another, a photo
    saved again between them had its clip journaled as made from bytes it was not made from,
    and once the file held those bytes again, every run took the wrong clip for up to date."""
    path = Path(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            data = _photo_bytes(path)
            return _read_image(path, data), hashlib.sha256(data).hexdigest() if hashed else ""
        finally:
            for warning in dict.fromkeys(str(w.message) for w in caught):
                log.warning("%s: %s", path, warning)


MAX_PHOTO_BYTES = 2 << 30
"""Larger files are refused before they are read into memory: a photo is held whole while it
is decoded, so that it is hashed and decoded from the same bytes (120 MP of 16-bit RGB
uncompressed is 720 MB; a layered TIFF or a JPEG decoded at a reduced size may be larger,
and is refused)."""


def _photo_bytes(path: Path) -> bytes:
    try:
        size = path.stat().st_size
        if size > MAX_PHOTO_BYTES:
            raise ImageReadError(path, f"is {size / 2**30:.1f} GiB, more than the "
                                 f"{MAX_PHOTO_BYTES / 2**30:.0f} GiB this tool reads")
        data = path.read_bytes()
    except OSError as error:
        raise ImageReadError(path, unreadable_reason(error)) from error
    if not data:
        raise ImageReadError(path, "is empty (0 bytes)")
    return data


EXIF_ORIENTATION = 0x0112
TURNED_ORIENTATIONS = (5, 6, 7, 8)
"""EXIF orientations that swap width and height (the camera held on its side)."""


EXIF_IFD = 0x8769
EXIF_TAKEN = 0x9003  # DateTimeOriginal (to the second: editors drop or rewrite SubsecTime)


def capture_time(path: Path) -> str | None:
    """When the camera took the photo (EXIF DateTimeOriginal), None where the file does not
    say: an edit keeps it, another card's photo of the same name does not share it."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # said with the file's name when it is read
            with Image.open(path) as image:
                taken = image.getexif().get_ifd(EXIF_IFD)
    except Exception:  # a header Pillow cannot read (or a bomb) says nothing of it
        return None
    when = taken.get(EXIF_TAKEN)
    if not isinstance(when, str) or not when.strip(" :0\x00"):
        return None
    return when


def upright_size(path: Path) -> tuple[int, int]:
    """(width, height) of the photo read_image gives, from its header where Pillow reads one:
    `plan` checking kept crops against each photo's size decoded every photo whole. (A JPEG
    so large that it is decoded smaller, or a file Pillow cannot open, is read.)"""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # said with the file's name when it is read
            with Image.open(path) as image:
                width, height = image.size
                if width * height <= MAX_SOURCE_PIXELS:
                    turned = image.getexif().get(EXIF_ORIENTATION) in TURNED_ORIENTATIONS
                    return (height, width) if turned else (width, height)
    except (OSError, ValueError, SyntaxError, UnidentifiedImageError):
        pass
    height, width = read_image(path).shape[:2]
    return width, height


def _read_image(path: Path, data: bytes) -> np.ndarray:
    """The picture in data, the bytes of the file at path (named in errors)."""
    try:
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
            if width * height > MAX_SOURCE_PIXELS:
                if image.format != "JPEG":
                    raise ImageReadError(
                        path,
                        f"is {width}x{height} px, more than the {MAX_SOURCE_PIXELS:,} px this "
                        "tool decodes; downscale it first",
                    )
                image.draft("RGB", (DECODE_LONG_SIDE_PX, DECODE_LONG_SIDE_PX))
            image.load()
            if image.format == "JPEG" and _ends_blank(image):
                raise ImageReadError(path, "is corrupt or truncated (its image data ends early: "
                                     f"the last {TRUNCATED_JPEG_ROWS} rows or more are blank "
                                     "mid grey; if the picture really ends in a #808080 band, "
                                     "save it as PNG)")
            # an animated WebP, a multi-page TIFF (a camera's MPO holds its previews: no news)
            if getattr(image, "n_frames", 1) > 1 and image.format != "MPO":
                log.warning("%s: holds %d frames or pages; the first is used", path,
                            image.n_frames)
            image = ImageOps.exif_transpose(in_srgb(image))
            return _to_rgb8(image)
    except ImageReadError:
        raise
    except UnidentifiedImageError as error:
        picture = (_read_with_opencv(path, data) if path.suffix.lower() in (".tif", ".tiff")
                   else None)
        if picture is None:
            raise ImageReadError(path, "is not an image this tool can read") from error
        return picture
    except (OSError, ValueError, SyntaxError) as error:
        raise ImageReadError(path, f"is corrupt or truncated ({error})") from error


PROFILED_MODES = ("RGB", "RGBA", "CMYK")
"""Modes whose embedded colour profile is applied: the frames are sRGB, and a Display P3 or
Adobe RGB photo read as if it were sRGB came out dull (a green of 180 as 176 with red 85)."""


def in_srgb(image: Image.Image) -> Image.Image:
    """The image converted to sRGB by its embedded ICC profile; as it is without one, with an
    sRGB one, or with a profile LittleCMS cannot use."""
    icc = image.info.get("icc_profile")
    if not icc or image.mode not in PROFILED_MODES:
        return image
    try:
        profile = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        if ImageCms.getProfileDescription(profile).strip().lower().startswith("srgb"):
            return image
        return ImageCms.profileToProfile(image, profile, _srgb_profile(),
                                         outputMode="RGBA" if image.mode == "RGBA" else "RGB")
    except (ImageCms.PyCMSError, OSError, ValueError, TypeError):
        return image


@functools.cache
def _srgb_profile() -> ImageCms.ImageCmsProfile:
    return ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB"))


FLOAT_RANGE_PERCENTILE = 99.0
FLOAT_HEADROOM = 16.0
"""A float image is 0-1 when its brightest pixel is at most 1, or at most FLOAT_HEADROOM with
FLOAT_RANGE_PERCENTILE of its pixels at most 1 (highlights above white, as an HDR merge or a
raw converter writes them, clipped); else 0-255, or 0-65535 above 255. (A dark 0-255 star
field, its sky below 1 and its stars at 255, stays 0-255.)"""


def _to_8bit(values: np.ndarray, is_float: bool, is_16bit: bool) -> np.ndarray:
    """Pixel values of a wide type in 0..255. Floats have no fixed range (FLOAT_HEADROOM): a
    0-1 image with a few highlights above 1 was read as 0-255 and came out almost black; what
    lies above the range is clipped."""
    values = np.nan_to_num(values.astype(np.float64), posinf=0.0, neginf=0.0)
    top = float(values.max())
    peak = 65535.0 if is_16bit or top > 255 else 255.0
    if is_float and (top <= 1.0 or (top <= FLOAT_HEADROOM and
                                    np.percentile(values, FLOAT_RANGE_PERCENTILE) <= 1.0)):
        peak = 1.0
    return np.clip(values / peak * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _read_with_opencv(path: Path, data: bytes) -> np.ndarray | None:
    """A TIFF Pillow cannot open (32-bit float RGB, as HDR merges save) read by OpenCV, or
    None. Its orientation tag is not applied."""
    try:
        with opencv_silenced():  # libtiff's own lines
            picture = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    if picture is None or picture.ndim not in (2, 3) or picture.size == 0:
        return None
    if picture.shape[0] * picture.shape[1] > MAX_SOURCE_PIXELS:
        raise ImageReadError(path, f"is {picture.shape[1]}x{picture.shape[0]} px, more than "
                             f"the {MAX_SOURCE_PIXELS:,} px this tool decodes; downscale it first")
    if picture.ndim == 2:
        picture = picture[..., None]
    alpha = picture[..., 3] if picture.shape[2] == 4 else None
    picture = picture[..., :3] if picture.shape[2] >= 3 else picture[..., :1]
    if picture.dtype != np.uint8:
        is_float = np.issubdtype(picture.dtype, np.floating)
        picture = _to_8bit(picture, is_float, picture.dtype == np.uint16)
        if alpha is not None:  # its own range: 0-1 for floats, the type's for integers
            alpha = np.clip(np.nan_to_num(alpha.astype(np.float64)) * 255.0
                            / (1.0 if is_float else np.iinfo(alpha.dtype).max), 0, 255)
    rgb = picture[..., ::-1] if picture.shape[2] == 3 else np.repeat(picture, 3, axis=2)
    if alpha is not None:  # over the matte, as Pillow's images are
        share = alpha.astype(np.float64)[..., None] / 255.0
        rgb = rgb * share + np.float64(ALPHA_MATTE_RGB) * (1.0 - share) + 0.5
        rgb = np.clip(rgb, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(rgb)


def _to_rgb8(image: Image.Image) -> np.ndarray:
    """Convert any Pillow mode (16-bit, float, grey, palette, CMYK, alpha) to 8-bit RGB."""
    mode = image.mode
    if mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        grey = _to_8bit(np.asarray(image), mode == "F", mode.startswith("I;16"))
        return np.ascontiguousarray(np.repeat(grey[..., None], 3, axis=2))
    if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in image.info):
        rgba = image.convert("RGBA")
        matte = Image.new("RGBA", rgba.size, (*ALPHA_MATTE_RGB, 255))
        return np.asarray(Image.alpha_composite(matte, rgba).convert("RGB")).copy()
    return np.asarray(image.convert("RGB")).copy()


TEMP_STEM_MAX_BYTES = 100
"""A temporary file is named after its final name's stem up to this many bytes; a longer stem,
or one that is not UTF-8 (ffmpeg-python and OpenCV take only UTF-8 names), gives a generic
name: a valid 240-byte name failed as its temporary one passed the 255-byte limit."""


def _temp_prefix(stem: str) -> str:
    try:
        size = len(stem.encode("utf-8"))
    except UnicodeEncodeError:
        return ".kbbatch."
    return f".{stem}." if size <= TEMP_STEM_MAX_BYTES else ".kbbatch."


TEMP_NAME = re.compile(r"^\..*\.[a-z0-9_]{8}\.part\.[A-Za-z0-9]+$")
"""The names atomic_output gives its temporary files (mkstemp's 8 random characters between
_temp_prefix and `.part.<suffix>`): the only hidden files a run may remove as its own (a
looser `.*.part*` took a user's `.vacation.part1.rar`)."""


@contextmanager
def atomic_output(final_path: Path, suffix: str, make_folder: bool = True):
    """A temporary path beside final_path, renamed onto it only if the block succeeds; the
    folder is made unless make_folder is False (a clip's: an output folder removed mid-run
    was made again, under the run's feet)."""
    if make_folder:
        final_path.parent.mkdir(parents=True, exist_ok=True)
    temp_path = _new_temp_file(final_path.parent, _temp_prefix(final_path.stem),
                               f".part{suffix}")
    try:
        yield temp_path
        # a file replaced keeps its own mode (a private 0600 manifest became world-readable)
        with contextlib.suppress(FileNotFoundError):
            os.chmod(temp_path, stat.S_IMODE(os.stat(final_path).st_mode))
        os.replace(temp_path, final_path)
    finally:
        temp_path.unlink(missing_ok=True)


TEMP_NAME_CHARACTERS = "abcdefghijklmnopqrstuvwxyz0123456789_"


def _new_temp_file(folder: Path, prefix: str, suffix: str) -> Path:
    """An empty file of a new name, made as open() makes one: with the umask's mode, or the
    folder's default ACL. mkstemp's 0600, widened by hand with the umask, dropped the group
    write a default ACL gives the users who share a folder."""
    for _ in range(TEMP_NAME_TRIES):
        name = "".join(secrets.choice(TEMP_NAME_CHARACTERS) for _ in range(8))
        path = folder / f"{prefix}{name}{suffix}"
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return path
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(folder))


TEMP_NAME_TRIES = 100


DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
"""A write that fails with these failed for want of room (or of the user's quota), not for
anything in the photo: the runners keep the photo queued instead of failing it."""


def is_disk_full(error: BaseException) -> bool:
    return isinstance(error, OSError) and error.errno in DISK_FULL_ERRNOS


def free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def disk_full_message(folder: Path, source: Path, reason: str | None, free: int | None
                      ) -> str:
    room = "" if free is None else f" ({free // 1024} KB free)"
    why = f"{reason}; " if reason else ""
    return (f"{folder}: its disk is full{room}; the clip of {source.name} could not be written "
            f"({why}the photo is not at fault and stays queued)")


OWN_MARK = "kbbatch"
"""kbbatch's mark on the images it writes where a user's files may be: the PNG `Software` text
of those beside clips (`--save-depth`), the comment of the JPEG previews of `kbbatch plan`. A
file of such a name without it is the user's, never replaced."""

OWN_JPEG_QUALITY = 95
"""Quality of the JPEG previews kbbatch writes (OpenCV's default, which wrote them before)."""


SOURCE_SHA256_KEY = "kbbatch-source-sha256"
"""The PNG text of a disparity map kbbatch wrote that holds the sha256 of the photo it was made
from: in a folder that also holds photos, `IMG_1.disparity.png` of one photo was taken for the
map of another `IMG_1.jpg` (kbbatch.depth.file)."""


def own_image_text(path: Path) -> dict[str, str] | None:
    """The text of an image that write_image wrote marked as kbbatch's (a PNG's text; none for
    a JPEG, whose comment is the mark alone); None for any other file (a link never is
    kbbatch's)."""
    if path.is_symlink():
        return None
    try:
        with Image.open(path) as image:
            if image.format == "PNG" and image.text.get("Software") == OWN_MARK:
                return dict(image.text)
            if image.format == "JPEG" and image.info.get("comment") == OWN_MARK.encode():
                return {}
    except (OSError, ValueError, UnidentifiedImageError):
        pass
    return None


def own_png_text(path: Path) -> dict[str, str] | None:
    """The text of a PNG that write_image wrote marked as kbbatch's; None for any other file."""
    return own_image_text(path) or None  # a marked PNG's text holds the mark: never empty


def is_own_png(path: Path) -> bool:
    """Whether a file is a PNG that write_image wrote marked as kbbatch's (a link never is)."""
    return own_png_text(path) is not None


def is_users_file(path: Path) -> bool:
    """Something at path that kbbatch did not write (a link, a folder, a file without its
    mark): never replaced by an image kbbatch writes beside a clip or a plan."""
    return os.path.lexists(path) and own_image_text(path) is None


def write_image(path: Path, rgb: np.ndarray, own: bool = False,
                text: dict[str, str] | None = None) -> None:
    """Write an RGB (or single-channel, 8 or 16-bit) image atomically; own: a PNG marked as
    kbbatch's (OWN_MARK) and carrying `text` too, or a JPEG with that mark as its
    comment, which OpenCV cannot write, so Pillow writes it. OpenCV only encodes to memory and
    Python writes the bytes: cv2.imwrite took the path as UTF-8 and crashed the process (a
    segfault) on a name that is not."""
    path = Path(path)
    with atomic_output(path, path.suffix) as temp_path:
        if own and path.suffix.lower() in (".jpg", ".jpeg"):
            with temp_path.open("wb") as handle:
                Image.fromarray(np.ascontiguousarray(rgb)).save(
                    handle, format="JPEG", quality=OWN_JPEG_QUALITY,
                    comment=OWN_MARK.encode())
            return
        if own:
            from PIL.PngImagePlugin import PngInfo

            info = PngInfo()
            info.add_text("Software", OWN_MARK)
            for key, value in (text or {}).items():
                info.add_text(key, value)
            with temp_path.open("wb") as handle:
                Image.fromarray(np.ascontiguousarray(rgb)).save(handle, format="PNG",
                                                                pnginfo=info)
            return
        data = rgb[..., ::-1] if rgb.ndim == 3 else rgb
        try:
            encoded, buffer = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(data))
        except cv2.error as error:  # a suffix OpenCV has no encoder for
            raise OSError(f"{path}: could not be written ({error})") from error
        if not encoded:
            raise OSError(f"{path}: could not be written")
        temp_path.write_bytes(buffer.tobytes())


def read_image_bytes(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """An image OpenCV decodes from a file Python reads (None: not one it decodes):
    cv2.imread takes only UTF-8 names, any path the OS accepts is read here."""
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        return None
    with opencv_silenced():  # a damaged PNG's "[ERROR:0@3.9] global grfmt_png.cpp" lines
        return cv2.imdecode(data, flags)


_silenced = {"depth": 0, "level": 0}
_silenced_lock = threading.Lock()


@contextmanager
def opencv_silenced() -> Iterator[None]:
    """OpenCV's own log lines kept off the terminal while it decodes: what is wrong with a
    file is said once, in this tool's words, naming the file. (Its log level is the
    process's: counted, so that two decodes at once do not leave it silent for good.)"""
    with _silenced_lock:
        if not _silenced["depth"]:
            _silenced["level"] = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        _silenced["depth"] += 1
    try:
        yield
    finally:
        with _silenced_lock:
            _silenced["depth"] -= 1
            if not _silenced["depth"]:
                cv2.utils.logging.setLogLevel(_silenced["level"])
