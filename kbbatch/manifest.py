"""The JSON manifest: per-image crops (the paper's interactive mode, offline) and overrides.

Validated against the JSON Schema shipped beside this module; every error names the manifest,
the image and the field.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import stat
import sys
import unicodedata
from importlib import resources
from pathlib import Path
from typing import Any

from kbbatch.camera import ASPECT_TOLERANCE, Crop, Plan

FLAT_PLANNER = "2d"
"""The one planner an entry with crops may name: its crops, rendered without parallax."""



class ManifestError(ValueError):
    pass


class CropAspectError(ManifestError):
    """An entry's crop of another aspect than the clip's: made for another preset."""

    def __init__(self, message: str, field: str, crop_aspect: float, output_aspect: float
                 ) -> None:
        super().__init__(message)
        self.field, self.crop_aspect, self.output_aspect = field, crop_aspect, output_aspect


@dataclasses.dataclass(frozen=True)
class ManifestEntry:
    image: str
    data: dict[str, Any]
    manifest: Path

    def where(self, field: str) -> str:
        return f"{self.manifest}: image {self.image!r}: field '{field}'"

    @property
    def has_crops(self) -> bool:
        return "start" in self.data

    def planned_for_another(self, source: Path) -> str | None:
        """What to say when the photo now under this entry's name is not the one its crops
        were planned on (a second card's IMG_0001.JPG planned into the first card's
        manifest kept the first one's hand-edited crops, and rendered with them)."""
        planned_on = self.data.get("photo_sha256")
        if not planned_on or not self.has_crops:
            return None
        from kbbatch.fingerprint import file_sha256

        try:
            if file_sha256(source) == planned_on:
                return None
        except OSError:
            return None  # unreadable: said when it is read
        return (f"{source}: its crops in {self.manifest} were planned on another photo of this "
                "name (its content differs: another card's, or edited since); check them, or "
                "plan it again (kbbatch plan --replan)")

    @property
    def excluded(self) -> bool:
        return bool(self.data.get("exclude", False))

    @property
    def depth_file(self) -> Path | None:
        depth = self.data.get("depth")
        return (self.manifest.parent / depth).resolve() if depth else None

    def plan(self, source_width_px: int, source_height_px: int, working_width_px: int,
             aspect: float, easing: str) -> Plan:
        """The entry's crops as a plan in working pixels, checked against the photo."""
        to_working = working_width_px / source_width_px
        crops = []
        for field in ("start", "end"):
            crop = self.data[field]
            if self.data.get("units", "px") == "fraction":
                beyond = [name for name in ("center_x", "center_y", "width", "height")
                          if abs(crop.get(name, 0.0)) > 1.0]
                if beyond:  # pixel numbers under "units": "fraction" were blamed on the aspect
                    raise ManifestError(f"{self.where(field)}: {beyond[0]} "
                                        f"{crop[beyond[0]]:g} is no fraction of the photo "
                                        "(0 to 1 with \"units\": \"fraction\"; pixel numbers "
                                        "need \"units\": \"px\")")
                scale_x, scale_y = source_width_px, source_height_px
            else:
                given = [crop.get(name, 0.0) for name in ("center_x", "center_y", "width",
                                                           "height")]
                if all(0 <= value <= 1 for value in given):  # no crop of 1 px or less renders
                    raise ManifestError(f"{self.where(field)}: a crop {crop['width']:g} px "
                                        "wide, its centre within 1 px of the photo's corner: "
                                        "fractions of the photo need \"units\": \"fraction\"")
                scale_x, scale_y = self.resized(source_width_px, source_height_px)
            width = crop["width"] * scale_x
            height = crop["height"] * scale_y if "height" in crop else width / aspect
            if min(width, height) < sys.float_info.min:  # below floating point's precision
                raise ManifestError(f"{self.where(field)}: crop {crop['width']:.4g} wide is "
                                    "too small to frame anything")
            if abs(width / height / aspect - 1) > ASPECT_TOLERANCE:
                raise CropAspectError(f"{self.where(field)}: aspect {width / height:.3f} "
                                      f"differs from the output's {aspect:.3f}", field,
                                      width / height, aspect)
            source_crop = Crop(crop["center_x"] * scale_x, crop["center_y"] * scale_y, width,
                               height)
            if not source_crop.inside(source_width_px, source_height_px, tolerance_px=0.5):
                size = f"{source_width_px}x{source_height_px}"
                raise ManifestError(f"{self.where(field)}: crop {_describe(source_crop)} lies "
                                    f"outside the {size} photo")
            crops.append(source_crop.scaled(to_working))
        return Plan(crops[0], crops[1], easing=self.data.get("easing", easing),
                    planner="manifest", parallax=self.data.get("planner") != FLAT_PLANNER)

    def resized(self, source_width_px: int, source_height_px: int) -> tuple[float, float]:
        """How much the photo was enlarged across and down since its pixel crops were made
        (1, 1 when the entry does not say for what size): crops made for a photo that has
        been resized since framed a corner of it. A photo cropped or turned since (another
        aspect) is refused: no scale maps its old crops onto it."""
        made_for = self.data.get("photo_size")
        if not made_for or self.data.get("units", "px") == "fraction":
            return 1.0, 1.0
        scale_x = source_width_px / made_for["width"]
        scale_y = source_height_px / made_for["height"]
        if abs(scale_x / scale_y - 1) > ASPECT_TOLERANCE:
            raise ManifestError(
                f"{self.where('photo_size')}: its crops were made for the photo at "
                f"{made_for['width']}x{made_for['height']} px; it is {source_width_px}x"
                f"{source_height_px} px now, cropped or turned since: plan it again "
                "(kbbatch plan --replan) or edit its crops")
        return scale_x, scale_y


def _describe(crop: Crop) -> str:
    """[left, top, right, bottom] in px; a number too large to read is said as such (1e300
    printed as its 301 digits, four times, on one line)."""
    def px(value: float) -> str:
        return f"{value:.0f}" if abs(value) < 1e9 else f"{value:.3g}"

    return (f"[{px(crop.left_px)}, {px(crop.top_px)}, {px(crop.right_px)}, "
            f"{px(crop.bottom_px)}]")


def loose_name(key: str) -> str:
    """A manifest key or file name as a near miss is matched: its file name, case-folded."""
    return Path(key.strip()).name.casefold()


def _normal(name: str) -> str:
    """A file name in Unicode's composed form: `café.jpg` typed (composed) in a manifest names
    the photo a Mac wrote decomposed; the two look the same and are different strings."""
    return unicodedata.normalize("NFC", name)


@dataclasses.dataclass(frozen=True)
class Manifest:
    path: Path
    entries: dict[str, ManifestEntry]
    normal_entries: dict[str, ManifestEntry] = dataclasses.field(init=False, repr=False,
                                                                 compare=False)
    version_read: tuple[int, int] | None = dataclasses.field(default=None, compare=False)
    """(mtime_ns, size) of the file taken before it was read: a reader that follows it (the
    daemon) sees a change made since, however soon."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "normal_entries",
                           {_normal(name): entry for name, entry in self.entries.items()})

    def entry(self, image_name: str, folder: Path | None = None) -> ManifestEntry | None:
        """The entry of a photo: its own key, else a key in the other Unicode form, unless that
        key names a file of its own in folder (two photos whose names differ only in form,
        as Linux allows, shared one entry: the second was rendered with the first's crops,
        and `plan` wrote its plan over the first's)."""
        found = self.entries.get(image_name)
        if found is not None:
            return found
        found = self.normal_entries.get(_normal(image_name))
        if found is not None and folder is not None and os.path.lexists(folder / found.image):
            return None
        return found

    def near_key(self, image_name: str) -> str | None:
        """A key that names this photo but for case, spaces around it or a folder before it:
        its entry does not apply, silently unless said."""
        wanted = loose_name(image_name)
        return next((key for key in self.entries
                     if key != image_name and loose_name(key) == wanted), None)

    def depth_map_of(self, path: Path) -> str | None:
        """The image whose entry names this file as its depth map, if any: such a map in the
        photo folder is no photo (it was rendered as one); unless it has an entry of its own
        (a photo named as another's map, or as its own, was dropped, and its entry then said
        there was no photo of that name)."""
        if self.entry(path.name, path.parent) is not None:
            return None  # a photo with an entry of its own: its map is refused when read
        resolved = path.resolve()
        return next((name for name, entry in self.entries.items()
                     if entry.depth_file == resolved), None)

    def unmatched_images(self, photo_names: set[str]) -> list[str]:
        """Keys that name none of the folder's photos (entries apply by plain file name: a
        key with a folder, or naming a file that is not a photo, would be silently unused)."""
        normal_names = {_normal(name) for name in photo_names}
        return sorted(name for name in self.entries
                      if name not in photo_names and _normal(name) not in normal_names)


def schema() -> dict[str, Any]:
    return json.loads(resources.files("kbbatch").joinpath("manifest.schema.json").read_text())


class ManifestContentError(ValueError):
    """What JSON can say but a manifest cannot hold (NaN, huge numbers, repeated keys)."""


def _refuse_constant(name: str) -> float:
    """Python's JSON reader takes NaN and Infinity, which JSON has not: with them a duration
    or a crop passed the schema and failed later under another field's name."""
    raise ManifestContentError(f"{name} is not a number a manifest can hold (JSON has no "
                               "NaN or Infinity)")


def _finite_float(text: str) -> float:
    """A JSON number; one too large for a float (1e999) would be infinity."""
    value = float(text)
    if not math.isfinite(value):
        raise ManifestContentError(f"{text} is too large a number for a manifest")
    return value


INTEGER_DIGITS_MAX = 15
"""An integer in a manifest has at most this many digits: a longer one is no pixel count or
duration, and from 4,300 digits Python's reader raised its own error (a traceback)."""


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > INTEGER_DIGITS_MAX:
        raise ManifestContentError(f"{text[:20]}... is too large a number for a manifest")
    return int(text)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """JSON objects whose keys are unique: of two entries for one photo, Python's reader kept
    the last without a word (an `exclude` above a second entry was ignored)."""
    found: dict[str, Any] = {}
    for key, value in pairs:
        if key in found:
            raise ManifestContentError(f"key {key!r} appears twice in one object; keep one")
        found[key] = value
    return found


NESTING_MAX = 16
"""Deepest nesting of lists and objects a manifest may have (it needs 4): a document nested
just under the JSON reader's limit overflowed the stack later, in the schema's messages."""


def _nesting(data: Any) -> int:
    deepest, stack = 0, [(data, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict | list):
            deepest = max(deepest, depth)
            if depth <= NESTING_MAX:  # deeper is refused: no need to walk it all
                children = value.values() if isinstance(value, dict) else value
                stack.extend((child, depth + 1) for child in children)
    return deepest


def parse_manifest_text(text: str) -> Any:
    """A manifest's JSON, refusing what JSON has not (NaN, Infinity), numbers no manifest
    holds, and repeated keys; raises ManifestContentError or json.JSONDecodeError."""
    try:
        data = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float,
                          parse_int=_bounded_int, object_pairs_hook=_unique_keys)
    except RecursionError as error:
        raise ManifestContentError("nested too deeply to be a manifest") from error
    if _nesting(data) > NESTING_MAX:
        raise ManifestContentError(f"nested too deeply to be a manifest (more than "
                                   f"{NESTING_MAX} levels)")
    return data


MANIFEST_BYTES_MAX = 256 << 20
"""Largest manifest file read (about 600,000 entries): `--manifest /dev/zero` or a huge file
given by mistake filled the memory (10 GB in 13 s) before any error."""


def manifest_bytes(path: Path) -> bytes:
    """A manifest file's bytes. Only a regular file is read, opened without waiting, so that a
    named pipe given as the manifest is refused instead of waiting for a writer without a word
    (`plan` already refused to write one)."""
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        status = os.fstat(descriptor)
        if stat.S_ISDIR(status.st_mode):
            raise ManifestContentError("is a folder; give the manifest's file name")
        if not stat.S_ISREG(status.st_mode):
            raise ManifestContentError("is not a regular file (a named pipe, socket or "
                                       "device); not read")
        data = bytearray()
        while len(data) <= MANIFEST_BYTES_MAX:
            chunk = os.read(descriptor, 1 << 20)
            if not chunk:
                break
            data += chunk  # in place: bytes += bytes copied the whole file at every chunk
    finally:
        os.close(descriptor)
    if len(data) > MANIFEST_BYTES_MAX:
        raise ManifestContentError(f"is larger than any manifest (over "
                                   f"{MANIFEST_BYTES_MAX >> 20} MiB); not read")
    return bytes(data)


def load_manifest(path: Path) -> Manifest:
    """Read and validate a manifest; raises ManifestError naming the file, image and field."""
    try:
        version = file_version(Path(path))
        # utf-8-sig: a byte-order mark (Notepad writes one) is not an error
        data = parse_manifest_text(manifest_bytes(Path(path)).decode("utf-8-sig"))
    except UnicodeDecodeError as error:
        raise ManifestError(f"{path}: is not UTF-8 text (byte {error.start}); save it as "
                            "UTF-8") from error
    except OSError as error:
        raise ManifestError(f"{path}: cannot be read ({error.strerror})") from error
    except ManifestContentError as error:
        raise ManifestError(f"{path}: {error}") from error
    except json.JSONDecodeError as error:
        raise ManifestError(f"{path}: malformed JSON at line {error.lineno} column "
                            f"{error.colno}: {error.msg}") from error
    return dataclasses.replace(manifest_from_data(data, Path(path)), version_read=version)


def file_version(path: Path) -> tuple[int, int] | None:
    """A file's (mtime_ns, size), or None where it cannot be seen."""
    try:
        status = path.stat()
    except OSError:
        return None
    return status.st_mtime_ns, status.st_size


def manifest_from_data(data: Any, path: Path) -> Manifest:
    """Validate a parsed manifest document; errors name path, image and field."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema())
    errors = sorted(validator.iter_errors(data), key=lambda e: list(e.absolute_path))
    if errors:
        error = errors[0]
        location = list(error.absolute_path)
        if len(location) >= 2 and location[0] == "images":
            field = ".".join(str(p) for p in location[2:]) or "(entry)"
            where = f"image {location[1]!r}: field '{field}'"
        else:
            where = f"field '{'.'.join(str(p) for p in location) or '(top level)'}'"
        raise ManifestError(f"{path}: {where}: {error.message}")
    entries = {name: ManifestEntry(name, entry, Path(path)) for name, entry in
               data["images"].items()}
    for entry in entries.values():
        _check_planner(entry)
    return Manifest(Path(path), entries)


def _check_planner(entry: ManifestEntry) -> None:
    """A registered planner, and with crops only `2d` (crops are already the camera path)."""
    from kbbatch.planners import PLANNER_NAMES

    planner = entry.data.get("planner")
    if planner is None:
        return
    if planner not in PLANNER_NAMES:
        raise ManifestError(f"{entry.where('planner')}: unknown planner {planner!r}; "
                            f"available: {', '.join(PLANNER_NAMES)}")
    if entry.has_crops and planner != FLAT_PLANNER:
        raise ManifestError(f"{entry.where('planner')}: the entry gives crops and planner "
                            f"{planner!r}; crops are the plan, so remove 'planner' (or set it "
                            f"to {FLAT_PLANNER!r} to render these crops without parallax)")


def plan_to_entry(plan: Plan, source_width_px: int, source_height_px: int,
                  working_width_px: int, photo_sha256: str | None = None) -> dict[str, Any]:
    """A plan as a manifest entry in source pixels (what `kbbatch plan` writes), with the
    photo's size they are pixels of and, when given, the digest of the photo file."""
    to_source = source_width_px / working_width_px

    def crop(c: Crop) -> dict[str, float]:
        s = c.scaled(to_source)
        return {"center_x": round(s.center_x_px, 2), "center_y": round(s.center_y_px, 2),
                "width": round(s.width_px, 2), "height": round(s.height_px, 2)}

    entry = {"units": "px", "photo_size": {"width": source_width_px, "height": source_height_px},
             "start": crop(plan.start), "end": crop(plan.end), "easing": plan.easing}
    if photo_sha256 is not None:
        entry["photo_sha256"] = photo_sha256
    if not plan.parallax:
        entry["planner"] = FLAT_PLANNER
    return entry


def write_manifest(path: Path, entries: dict[str, dict[str, Any]]) -> None:
    """Write atomically, through a symbolic link: a manifest kept elsewhere (in a repository)
    and linked in was replaced by a plain file, and the kept one silently went stale."""
    from kbbatch.images import atomic_output

    real = Path(os.path.realpath(path))
    if is_read_only(real):
        raise PermissionError(errno.EACCES, "read-only (its write permission is off); not "
                              "replaced", str(path))
    text = json.dumps({"version": 1, "images": entries}, indent=2)
    with atomic_output(real, ".json") as temp_path:
        temp_path.write_text(text + "\n", encoding="utf-8")


def is_read_only(path: Path) -> bool:
    """A file whose write permission is off for everyone: the user's way to say "keep"; a
    rename would replace it all the same (for root, and for any owner of the folder)."""
    try:
        return not os.stat(path).st_mode & 0o222
    except OSError:
        return False
