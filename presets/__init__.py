"""Presets: output size, timing, motion and encoding, as TOML files validated into a dataclass.

Each setting is described once, in the dataclass field's metadata (meaning and bounds); the
validation, `kbbatch presets` and the README table are all derived from it.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

from kbbatch.camera import EASINGS

ZOOM_DIRECTIONS = ("in", "out")


class PresetError(ValueError):
    """A preset that cannot be used; the message names the file and the field."""


def _setting(doc: str, **bounds: Any) -> Any:
    return field(metadata={"doc": doc, **bounds})


@dataclass(frozen=True)
class Preset:
    name: str = _setting("preset name")
    description: str = _setting("what the preset is for")
    width_px: int = _setting("output width", min=16, max=8192, even=True)
    height_px: int = _setting("output height", min=16, max=8192, even=True)
    fps: float = _setting("frames per second", min=1, max=120)
    duration_s: float = _setting("forward move in seconds (the clip plays it back too)",
                                 min=0.2, max=120)
    easing: str = _setting("speed curve of the move", choices=EASINGS)
    zoom: float = _setting("crop-width ratio between the wide and the tight view", min=1.0,
                           max=4.0)
    zoom_direction: str = _setting("'in' ends on the tight view, 'out' starts on it",
                                   choices=ZOOM_DIRECTIONS)
    max_shift_px: float = _setting("largest lateral move of the crop centre, working px",
                                   min=0, max=512)
    codec: str = _setting("ffmpeg video encoder, e.g. libx264, libx265, libvpx-vp9")
    crf: int = _setting("encoder constant-rate factor (lower is better and larger)", min=0,
                        max=63)
    pix_fmt: str = _setting("pixel format of the encoded video")
    encoder_preset: str = _setting("encoder speed preset (x264/x265), empty for none")

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


def settings() -> list[tuple[str, str]]:
    """(name, meaning) of every preset setting, in order."""
    return [(f.name, f.metadata["doc"]) for f in fields(Preset)]


def preset_from_mapping(data: dict[str, Any], source: str) -> Preset:
    """Validate a mapping into a Preset; every error names the source and the field."""
    known = {f.name: f for f in fields(Preset)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise PresetError(f"{source}: unknown setting(s) {', '.join(unknown)}; "
                          f"known: {', '.join(known)}")
    missing = [name for name in known if name not in data]
    if missing:
        raise PresetError(f"{source}: missing setting(s) {', '.join(missing)}")
    values: dict[str, Any] = {}
    for name, spec in known.items():
        values[name] = _validate(source, name, data[name], spec.type, spec.metadata)
    return Preset(**values)


def _validate(source: str, name: str, value: Any, kind: Any, rules: dict[str, Any]) -> Any:
    where = f"{source}: setting '{name}'"
    if kind in ("int", int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise PresetError(f"{where} must be an integer, got {value!r}")
    elif kind in ("float", float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise PresetError(f"{where} must be a number, got {value!r}")
        value = float(value)
    elif not isinstance(value, str):
        raise PresetError(f"{where} must be text, got {value!r}")
    if "min" in rules and value < rules["min"]:
        raise PresetError(f"{where} must be at least {rules['min']}, got {value!r}")
    if "max" in rules and value > rules["max"]:
        raise PresetError(f"{where} must be at most {rules['max']}, got {value!r}")
    if rules.get("even") and value % 2:
        raise PresetError(f"{where} must be even (yuv420p needs even sizes), got {value!r}")
    if "choices" in rules and value not in rules["choices"]:
        raise PresetError(f"{where} must be one of {', '.join(rules['choices'])}, got {value!r}")
    return value


def builtin_names() -> list[str]:
    """Names of the presets shipped in the presets package."""
    folder = resources.files(__name__)
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_preset(name_or_path: str) -> Preset:
    """A shipped preset by name, or a TOML file by path."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise PresetError(f"{path}: preset file not found")
        text = path.read_text(encoding="utf-8")
        source = str(path)
    else:
        resource = resources.files(__name__) / f"{name_or_path}.toml"
        if not resource.is_file():
            shipped = ", ".join(builtin_names())
            raise PresetError(f"unknown preset {name_or_path!r}; shipped presets: {shipped}, "
                              "or give a path to a .toml file")
        text = resource.read_text(encoding="utf-8")
        source = f"preset {name_or_path!r}"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise PresetError(f"{source}: not valid TOML ({error})") from error
    data.setdefault("name", path.stem if path.suffix == ".toml" else name_or_path)
    return preset_from_mapping(data, source)


def with_overrides(preset: Preset, **overrides: Any) -> Preset:
    """The preset with some settings replaced (None means keep), validated again."""
    changes = {k: v for k, v in overrides.items() if v is not None}
    if not changes:
        return preset
    merged = {f.name: getattr(preset, f.name) for f in fields(Preset)} | changes
    return preset_from_mapping(merged, f"preset {preset.name!r} with overrides")

