"""Presets: output size, timing, motion and encoding, as TOML files validated into a dataclass.

Each setting is described and bounded once, in preset.schema.json beside the shipped files,
and validated by the same JSON Schema machinery as manifests. A preset may name another as its
`base` and set only what differs. Codec, pixel format and encoder preset are checked against
the ffmpeg binary when the preset loads, so a bad one fails once, naming the file and field.
"""

from __future__ import annotations

import functools
import json
import math
import tomllib
from dataclasses import dataclass, fields
from importlib import resources
from pathlib import Path
from typing import Any

from kbbatch.camera import EASINGS


class PresetError(ValueError):
    """A preset that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class Preset:
    """A validated preset; preset.schema.json says what each setting means."""

    name: str
    description: str
    width_px: int
    height_px: int
    fps: float
    duration_s: float
    easing: str
    zoom: float
    zoom_direction: str
    max_shift_px: float
    codec: str
    crf: int
    pix_fmt: str
    encoder_preset: str

    @property
    def frames_forward(self) -> int:
        """Distinct time steps rendered; the clip plays them forward, then back."""
        return max(2, round(self.duration_s * self.fps))

    @property
    def frames_total(self) -> int:
        return 2 * self.frames_forward - 2

    @property
    def aspect(self) -> float:
        return self.width_px / self.height_px

    def frame_settings(self) -> dict[str, Any]:
        """The settings a clip's frames and encoding are made from: all but the preset's
        name and description, which label it. Renaming a preset file or rewording its
        description made every clip of a folder again."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name not in LABEL_FIELDS}


LABEL_FIELDS = ("name", "description")
"""A preset's words about itself, not settings of its clips."""


@functools.cache
def schema() -> dict[str, Any]:
    data = json.loads(resources.files(__name__).joinpath("preset.schema.json").read_text())
    data["properties"]["easing"]["enum"] = list(EASINGS)  # the camera's own list
    return data


def setting_docs() -> dict[str, str]:
    """Meaning of every preset setting, from the schema (for `kbbatch presets`)."""
    return {name: rule["description"] for name, rule in schema()["properties"].items()}


def _check(data: dict[str, Any], source: str, complete: bool) -> None:
    """Validate against the schema; `complete` also requires every setting (after bases)."""
    import jsonschema

    rules = schema() if complete else {k: v for k, v in schema().items() if k != "required"}
    errors = sorted(jsonschema.Draft202012Validator(rules).iter_errors(data),
                    key=lambda e: list(e.absolute_path))
    if any(error.validator == "additionalProperties" for error in errors):
        unknown = sorted(set(data) - set(rules["properties"]))
        raise PresetError(f"{source}: unknown setting(s) {', '.join(unknown)}; known: "
                          f"{', '.join(rules['properties'])}")
    missing = [error for error in errors if error.validator == "required"]
    if missing and len(missing) == len(errors):  # a few settings alone: no base named
        names = ", ".join(repr(error.message.split("'")[1]) for error in missing)
        raise PresetError(f"{source}: missing setting(s) {names}; give them, or start the "
                          f"file with base = \"slideshow\" (or another preset) to take the "
                          "rest from it")
    if errors:  # every one at once: a file with two bad sizes was fixed in two rounds
        said = []
        for error in errors:
            field = ".".join(str(p) for p in error.absolute_path)
            said.append(f"setting '{field}': {error.message}" if field else error.message)
        raise PresetError(f"{source}: {'; '.join(said)}")
    for name, value in data.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise PresetError(f"{source}: setting '{name}' must be a finite number, got {value}")


def preset_from_mapping(data: dict[str, Any], source: str) -> Preset:
    """A complete, validated Preset from a mapping; every error names the source and field."""
    _check(data, source, complete=True)
    known = {f.name for f in fields(Preset)}
    values = {"description": ""} | {k: v for k, v in data.items() if k in known}
    for f in fields(Preset):
        if f.type in ("float", float):
            values[f.name] = float(values[f.name])
        elif f.type in ("int", int):  # JSON Schema counts 640.0 an integer; ffmpeg does not
            values[f.name] = int(values[f.name])
    return Preset(**values)


def builtin_names() -> list[str]:
    """Names of the presets shipped in the presets package."""
    folder = resources.files(__name__)
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


PRESET_BASES_MAX = 16
"""A preset's chain of bases is at most this long (a chain of 1,200 files overflowed Python's
stack with a traceback)."""


PRESET_BYTES_MAX = 1 << 20
"""Largest preset file read (a preset is a few hundred bytes): a 3 GB file given by mistake
took the memory of the whole batch (MemoryError) before it could be refused."""


def _read(name_or_path: str, relative_to: Path | None, chain: tuple[str, ...]
          ) -> tuple[dict[str, Any], str]:
    """The settings of a preset file with its bases applied (not yet complete-checked)."""
    path = Path(name_or_path)
    if relative_to is not None and not path.is_absolute():
        path = relative_to / path
    # A shipped preset's bare name means that preset, whatever the current folder holds (an
    # output folder named after its preset, `-o preview --preset preview`, shadowed it on
    # the second run); a file of that name is given as ./preview.toml.
    shipped_name = name_or_path in builtin_names()
    if not shipped_name and (path.suffix == ".toml" or path.exists()):
        if not path.is_file():
            reason = ("a folder, not a preset file" if path.is_dir()
                      else "not a regular file (a device or pipe)" if path.exists()
                      else "preset file not found")
            raise PresetError(f"{path}: {reason}")
        try:
            if path.stat().st_size > PRESET_BYTES_MAX:
                raise PresetError(f"{path}: is larger than any preset (over "
                                  f"{PRESET_BYTES_MAX >> 10} KiB); not read")
            text = path.read_text(encoding="utf-8-sig")  # a BOM, as manifests allow
        except UnicodeDecodeError as error:
            raise PresetError(f"{path}: not a UTF-8 text file (byte {error.start}); TOML "
                              "files are UTF-8") from error
        except OSError as error:
            raise PresetError(f"{path}: cannot be read ({error.strerror or error})") from error
        source, stem, folder = str(path), path.stem, path.parent
        key = str(path.resolve())  # `../pre/a.toml` from pre/a.toml is a.toml itself
    else:
        resource = resources.files(__name__) / f"{name_or_path}.toml"
        if not resource.is_file():
            shipped = ", ".join(builtin_names())
            raise PresetError(f"unknown preset {name_or_path!r}; shipped presets: {shipped}, "
                              "or give a path to a .toml file")
        text = resource.read_text(encoding="utf-8")
        source, stem, folder = f"preset {name_or_path!r}", name_or_path, None
        key = source
    if key in chain:
        raise PresetError(f"{source}: 'base' loops back to itself ({' -> '.join(chain)})")
    if len(chain) >= PRESET_BASES_MAX:
        raise PresetError(f"{source}: more than {PRESET_BASES_MAX} bases deep "
                          f"({chain[0]} -> ... -> {chain[-1]})")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise PresetError(f"{source}: not valid TOML ({error})") from error
    _check(data, source, complete=False)
    data.setdefault("name", stem)
    base = data.pop("base", None)
    if base is None:
        return data, source
    data.setdefault("description", f"{base} with changes")  # not the base's own words
    try:
        base_data, _ = _read(base, folder, (*chain, key))
    except PresetError as error:
        if str(error).startswith(source):  # already names this file (a loop)
            raise
        raise PresetError(f"{source}: setting 'base': {error}") from error
    return base_data | data, source


def load_preset(name_or_path: str, relative_to: Path | None = None) -> Preset:
    """A shipped preset by name, or a TOML file by path (relative to relative_to when given,
    as a manifest's entries are), checked against ffmpeg."""
    from kbbatch.encode import EncoderError, check_encoder

    data, source = _read(name_or_path, relative_to, ())
    preset = preset_from_mapping(data, source)
    try:
        check_encoder(preset)
    except EncoderError as error:
        raise PresetError(f"{source}: setting '{error.field}': {error}") from error
    return preset


def with_overrides(preset: Preset, **overrides: Any) -> Preset:
    """The preset with some settings replaced (None means keep), validated again."""
    changes = {k: v for k, v in overrides.items() if v is not None}
    if not changes:
        return preset
    merged = {f.name: getattr(preset, f.name) for f in fields(Preset)} | changes
    return preset_from_mapping(merged, f"preset {preset.name!r} with overrides")

