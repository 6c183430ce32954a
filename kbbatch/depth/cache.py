"""On-disk cache of final depth maps, so re-runs and the daemon never recompute them.

The key is the photo's content hash with everything that shapes the depth: backend, model,
options and the working size. Files are written atomically; a damaged entry is recomputed.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from kbbatch.depth import DepthOptions, DepthResult
from kbbatch.images import atomic_output

CACHE_ENV = "KBBATCH_CACHE"
CACHE_VERSION = 4
"""Bump when a change to the depth code changes its output."""


def cache_dir() -> Path:
    override = os.environ.get(CACHE_ENV)
    if override:
        return Path(override).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("kbbatch")) / "depth"


def cache_key(photo_bytes_hash: str, options: DepthOptions, size: tuple[int, int],
              depth_file_hash: str | None) -> str:
    from kbbatch.models import cache_fingerprint

    settings = {"photo": photo_bytes_hash, "options": asdict(options), "size": size,
                "depth_file": depth_file_hash, "models": cache_fingerprint(),
                "version": CACHE_VERSION}
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:32]


def file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load(key: str) -> DepthResult | None:
    path = cache_dir() / f"{key}.npz"
    try:
        with np.load(path, allow_pickle=False) as data:
            return DepthResult(data["disparity"], str(data["backend"]), str(data["source"]))
    except (OSError, ValueError, KeyError):
        return None


def store(key: str, result: DepthResult) -> None:
    path = cache_dir() / f"{key}.npz"
    try:
        with atomic_output(path, ".npz") as temp_path, temp_path.open("wb") as handle:
            np.savez(handle, disparity=result.disparity, backend=result.backend,
                     source=result.source)
    except OSError:
        pass  # a cache that cannot be written only costs time
