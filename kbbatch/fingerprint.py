"""One fingerprint of every input of a clip, computed here and nowhere else.

A clip depends on the photo's bytes, a depth map beside it or named by the manifest, which
networks are in the models folder (depth is different with a detector present), the settings
(preset, planner, depth options, manifest entry) and the code of the stages. The journal skips a
photo only when all of these are unchanged; the depth cache keys on the part that shapes depth.
Both use the functions below, so the two can never disagree about what an input is.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from kbbatch.depth import DepthOptions

DIGEST_HEX = 32
"""Hex digits kept of a fingerprint's sha256 (128 bits: no two inputs ever collide)."""

DEPTH_MODEL_ROLES = ("depth", "salient", "semantic", "detector")
"""Registry roles whose networks shape the depth map (inpainting shapes only the frames)."""

KBBATCH_ROOT = Path(__file__).resolve().parent
DEPTH_CODE = ("depth", "segment.py", "models.py")
"""The depth stage's code, relative to the package: its version is a hash of these sources."""

RUNNER_CODE = ("cli.py", "batch.py", "watch.py", "ray_executor.py", "outputs.py", "journal.py",
               "review.py", "__main__.py", "web")
"""Code that runs stages but does not shape a clip's pixels: left out of the clip's version, so
a change to the command line or the daemon does not re-render a library."""


@dataclass(frozen=True)
class FileStamp:
    """A file by name and content: the name says how a depth map is read (depth or disparity)."""

    name: str
    sha256: str


@dataclass(frozen=True)
class ModelStamp:
    """A network present in the models folder; size and time stand for its bytes (hashing
    hundreds of MB per photo would cost more than the depth it guards)."""

    name: str
    size_bytes: int
    mtime_ns: int


@dataclass(frozen=True)
class DepthInputs:
    """Everything the depth stage reads; its digest is the depth cache's key."""

    photo_sha256: str
    depth_file: FileStamp | None
    models: tuple[ModelStamp, ...]
    options: DepthOptions
    code_version: str

    def digest(self, size: tuple[int, int]) -> str:
        """The key of a depth map of these inputs at this working size (height, width)."""
        return digest_of(asdict(self), list(size))


@dataclass(frozen=True)
class ClipInputs:
    """Everything a clip is made from; the journal calls a clip up to date only while its
    digest is the one recorded when the clip was written."""

    depth: DepthInputs
    models: tuple[ModelStamp, ...]  # every model present (inpainting included)
    settings: str  # preset, planner and manifest entry, as canonical JSON
    code_version: str

    @property
    def digest(self) -> str:
        return digest_of(asdict(self))

    def with_settings(self, settings: Any) -> ClipInputs:
        """The same inputs under other settings (nothing read again)."""
        return replace(self, settings=_settings_text(settings))


def _settings_text(settings: Any) -> str:
    return json.dumps(settings, sort_keys=True, default=str)


def digest_of(*parts: Any) -> str:
    """A short sha256 of JSON-able parts (keys sorted, so equal inputs give equal digests)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:DIGEST_HEX]


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def depth_file_for(photo_path: Path, options: DepthOptions) -> Path | None:
    """The depth map the depth stage will read for this photo, if any: the manifest's, else one
    beside the photo; only the `auto` and `file` backends read one (as get_backend decides)."""
    from kbbatch.depth.file import find_depth_file

    if options.backend not in ("auto", "file"):
        return None
    if options.file:
        return Path(options.file)
    return find_depth_file(photo_path)


def models_present(roles: Iterable[str] | None = None) -> tuple[ModelStamp, ...]:
    """The registered networks now in the models folder (of the given roles, else all)."""
    from kbbatch.models import REGISTRY, cached_path

    wanted = set(roles) if roles is not None else None
    stamps = []
    for name in sorted(REGISTRY):
        if wanted is not None and REGISTRY[name].role not in wanted:
            continue
        path = cached_path(name)
        if path is None:
            continue
        try:
            stat = path.stat()
        except OSError:
            continue  # removed since it was seen: not present
        stamps.append(ModelStamp(name, stat.st_size, stat.st_mtime_ns))
    return tuple(stamps)


@functools.cache
def code_version(*relative_paths: str, exclude: tuple[str, ...] = ()) -> str:
    """A hash of the Python sources at these paths (files or folders) under the package: a
    change to the code of a stage is a change to its output. Computed once per process."""
    files: set[Path] = set()
    for relative in relative_paths:
        path = KBBATCH_ROOT / relative
        files.update(path.rglob("*.py") if path.is_dir() else [path])
    for relative in exclude:
        path = KBBATCH_ROOT / relative
        files.difference_update(path.rglob("*.py") if path.is_dir() else [path])
    digest = hashlib.sha256()
    for path in sorted(files):
        digest.update(str(path.relative_to(KBBATCH_ROOT)).encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:DIGEST_HEX]


def clip_code_version() -> str:
    """The version of every stage of a clip: the package and its planners and presets
    modules, less the runners (RUNNER_CODE)."""
    import kbbatch.planners
    import kbbatch.presets

    parts = [code_version(".", exclude=RUNNER_CODE)]
    for package in (kbbatch.planners, kbbatch.presets):
        parts.append(_package_version(Path(package.__file__).resolve().parent))
    return digest_of(parts)


@functools.cache
def _package_version(folder: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:DIGEST_HEX]


def depth_inputs(photo_path: Path, photo_sha256: str, options: DepthOptions) -> DepthInputs:
    """The inputs of the depth stage for a photo file. Raises OSError when the photo's depth
    file cannot be read (the depth stage would fail on it too)."""
    depth_file = depth_file_for(photo_path, options)
    stamp = None
    if depth_file is not None and depth_file.is_file():
        stamp = FileStamp(depth_file.name, file_sha256(depth_file))
    elif depth_file is not None:
        stamp = FileStamp(depth_file.name, "missing")
    return DepthInputs(photo_sha256, stamp, models_present(DEPTH_MODEL_ROLES), options,
                       code_version(*DEPTH_CODE))


def clip_inputs(photo_path: Path, photo_sha256: str, depth: DepthOptions, settings: Any
                ) -> ClipInputs:
    """Every input of one clip: the depth inputs, all models present, the settings (any
    JSON-able description of preset, planner and manifest entry) and the stages' code."""
    return ClipInputs(depth_inputs(photo_path, photo_sha256, depth), models_present(),
                      _settings_text(settings), clip_code_version())
