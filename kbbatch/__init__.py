"""kbbatch: 3D Ken Burns clips from still photos, in batches."""

from __future__ import annotations

import os
import sys

EXIT_INTERRUPTED = 130
"""Exit status of a run stopped by Ctrl-C or SIGTERM before it was through."""

INTERRUPTED_LINE = "\ninterrupted: nothing partial is left; run again to finish"
"""What the command says, on stderr, when a Ctrl-C stopped it before a command could."""


def ignore_stop_signals() -> None:
    """The run is stopped and cleaned up: a SIGTERM, hang-up or another Ctrl-C while the
    interpreter shuts down (a supervisor's SIGTERM a moment after the Ctrl-C, a key pressed
    again) is ignored, so the status is 130, not death by the signal (as if the stop had not
    finished). Ignored, not handled: CPython puts handled signals back to their default
    action as it finalises."""
    import signal

    for number in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(number, signal.SIG_IGN)


def _as_the_command() -> bool:
    """Whether this process is the `kbbatch` command (its script, or `python -m kbbatch`), not
    a program or worker that imports kbbatch."""
    return (os.path.basename(sys.argv[0]) == "kbbatch"
            or sys.orig_argv[1:3] == ["-m", "kbbatch"])


def interrupted_while_loading() -> None:
    """A Ctrl-C while the command's first modules load, before kbbatch.entry can take it (a
    traceback, and death by SIGINT): said as entry says it, status 130. Elsewhere it returns,
    and the caller raises the interrupt again."""
    if not _as_the_command():
        return
    ignore_stop_signals()
    print(INTERRUPTED_LINE, file=sys.stderr)
    raise SystemExit(EXIT_INTERRUPTED)


try:
    from pathlib import Path
except KeyboardInterrupt:
    interrupted_while_loading()
    raise


def _writable(folder: Path, base: Path) -> bool:
    """Whether files can be made in folder, or in the folders between it and base, which must
    exist (a new user's home has no ~/.cache yet: the first run compiled into the temporary
    folder, the second into ~/.cache/numba, each from scratch; a home that does not exist is
    no place to make one)."""
    if not base.is_dir():
        return False
    while not folder.exists() and folder != base and folder.parent != folder:
        folder = folder.parent
    return os.access(folder, os.W_OK)


PRIVATE_CACHE_NAMES = 4
"""Names tried for a user's compiled-code folder in the temporary folder."""


def _compiled_code_cache() -> None:
    """Give numba a folder for its compiled kernels when neither of its own can be written.

    It caches beside the installed sources or in the user's home; a service account with no
    writable home running a root-owned install (the README's systemd unit) had every command
    fail at import ("cannot cache function"). Then a private folder of this user's under the
    temporary directory is used, made with mode 0700 and used only while this user owns it and
    no one else may write it (numba unpickles what it finds there). Set before any kernel
    module imports numba.
    """
    import atexit
    import contextlib
    import shutil
    import stat
    import tempfile

    package = Path(__file__).parent
    if "NUMBA_CACHE_DIR" in os.environ or _writable(package / "__pycache__", package):
        return
    try:
        xdg = os.environ.get("XDG_CACHE_HOME")
        home_cache, base = (Path(xdg), Path(xdg)) if xdg else (Path.home() / ".cache",
                                                                 Path.home())
    except RuntimeError:  # no HOME and no account entry to find one
        home_cache = base = None
    if home_cache is not None and _writable(home_cache / "numba", base):
        return
    # A name taken by another user (a stale uid's, or a squatter's) gets the next one: a new
    # folder every run compiled every kernel again and was left behind, 0.7 MB a run.
    for number in range(PRIVATE_CACHE_NAMES):
        private = Path(tempfile.gettempdir()) / (f"kbbatch-numba-{os.getuid()}"
                                                 + (f".{number}" if number else ""))
        try:
            private.mkdir(mode=0o700, exist_ok=True)
            status = private.lstat()
        except OSError:
            continue
        if (stat.S_ISDIR(status.st_mode) and status.st_uid == os.getuid()
                and not status.st_mode & (stat.S_IWGRP | stat.S_IWOTH)):
            os.environ["NUMBA_CACHE_DIR"] = str(private)
            return
    with contextlib.suppress(OSError):  # else numba says why it cannot cache
        os.environ["NUMBA_CACHE_DIR"] = fresh = tempfile.mkdtemp(prefix="kbbatch-numba-")
        atexit.register(shutil.rmtree, fresh, ignore_errors=True)


try:
    _compiled_code_cache()
except KeyboardInterrupt:
    interrupted_while_loading()
    raise

# onnxruntime 1.29 and later, on Linux and macOS, send usage telemetry to Microsoft unless
# this is set before the library loads; on import they also wrote a session file into TMPDIR
# and a database under ~/.cache/Microsoft. A batch tool run over people's photos sends nothing
# anywhere: off unless the user sets ORT_DISABLE_TELEMETRY=0 themselves.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
