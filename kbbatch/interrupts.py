"""A Ctrl-C, told apart from what a library made of it. Light: the command's entry point
uses it before anything heavy is loaded."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator


def interrupted(error: BaseException) -> bool:
    """Whether error is a Ctrl-C, or came of one: a Ctrl-C while onnxruntime's compiled
    module loads comes out as "ImportError: initialization failed", caused by the
    KeyboardInterrupt (a traceback and status 1, or a photo failed while the batch went on)."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


_holding = 0
_pending = False


@contextlib.contextmanager
def held() -> Iterator[None]:
    """A Ctrl-C in the block is raised at its end, where a SIGINT handler that asks
    deferred() lets it be (the batch's does). Around the start of ffmpeg: an interrupt
    inside subprocess.Popen, after the fork, left an encoder no one knew of, which wrote its
    clip's temporary file after the clean-up had removed it (a partial clip left, under
    load, in about one Ctrl-C of three)."""
    global _holding, _pending
    if threading.current_thread() is not threading.main_thread():  # handlers run there only
        yield
        return
    _holding += 1
    try:
        yield
    finally:
        _holding -= 1
        if not _holding and _pending:
            _pending = False
            raise KeyboardInterrupt


def deferred() -> bool:
    """For a SIGINT handler: whether the interrupt is kept for the end of a held() block."""
    global _pending
    if _holding:
        _pending = True
    return bool(_holding)
