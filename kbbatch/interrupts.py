"""A Ctrl-C, told apart from what a library made of it. Light: the command's entry point
uses it before anything heavy is loaded."""

from __future__ import annotations


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
