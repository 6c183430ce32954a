"""kbbatch: 3D Ken Burns clips from still photos, in batches."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def _compiled_code_cache() -> None:
    """Give numba a folder for its compiled kernels when neither of its own can be written.

    It caches beside the installed sources or in the user's home; a service account with no
    writable home running a root-owned install (the README's systemd unit) had every command
    fail at import ("cannot cache function"). Then a per-user folder under the temporary
    directory is used. Set before any kernel module imports numba.
    """
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    beside_sources = Path(__file__).parent / "__pycache__"
    if os.access(beside_sources if beside_sources.is_dir() else beside_sources.parent,
                 os.W_OK):
        return
    home_cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    writable = home_cache if home_cache.exists() else home_cache.parent
    if os.access(writable, os.W_OK):
        return
    per_user = f"kbbatch-numba-{os.getuid()}"
    os.environ["NUMBA_CACHE_DIR"] = str(Path(tempfile.gettempdir()) / per_user)


_compiled_code_cache()
