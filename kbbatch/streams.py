"""Standard streams that cannot stop a batch. What kbbatch says on stderr (progress, notes, log
lines) is for whoever watches; the clips, the journal and the run report are the work. Light:
the command's entry point uses it before anything heavy is loaded."""

from __future__ import annotations

import io
import os
import sys


class ForgivingStream(io.TextIOBase):
    """A text stream whose writes never raise: once one fails (the reader of a pipe gone, as
    with `| head` or quitting `less`; a full disk under `2>>log`; a closed terminal), what is
    written is dropped. A failed progress line was taken for ffmpeg's pipe breaking, and the
    batch waited for good on an encoder still waiting for frames; on a full disk, for the
    output disk being full: no clip was made."""

    def __init__(self, stream: io.TextIOBase) -> None:
        self.stream = stream
        self.failed: OSError | ValueError | None = None

    def write(self, text: str) -> int:
        if self.failed is None:
            try:
                return self.stream.write(text)
            except (OSError, ValueError) as error:  # ValueError: the stream was closed
                self.failed = error
        return len(text)

    def flush(self) -> None:
        if self.failed is None:
            try:
                self.stream.flush()
            except (OSError, ValueError) as error:
                self.failed = error

    def isatty(self) -> bool:
        try:
            return self.failed is None and self.stream.isatty()
        except (OSError, ValueError):
            return False

    def fileno(self) -> int:
        return self.stream.fileno()

    def writable(self) -> bool:
        return True

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return getattr(self.stream, "encoding", None) or "utf-8"

    @property
    def errors(self) -> str | None:  # type: ignore[override]
        return getattr(self.stream, "errors", None)


def standard_streams_ready() -> None:
    """Descriptors 0 to 2 open (on /dev/null where a launcher closed them: the first file
    kbbatch opened would take the number, and whatever a library or ffmpeg writes to "stderr"
    would go into it), and sys.stderr a ForgivingStream."""
    for descriptor in (0, 1, 2):
        try:
            os.fstat(descriptor)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)
            if null != descriptor:
                os.dup2(null, descriptor)
                os.close(null)
    for name, descriptor in (("stdin", 0), ("stdout", 1), ("stderr", 2)):
        if getattr(sys, name) is None:  # closed when Python started: /dev/null now
            setattr(sys, name, open(descriptor, "r" if descriptor == 0 else "w",  # noqa: SIM115
                                    closefd=False))
    if not isinstance(sys.stderr, ForgivingStream):
        sys.stderr = ForgivingStream(sys.stderr)


def stdout_lost(error: OSError) -> str:
    """After stdout failed (a full disk under `>>log`, a pipe's reader gone): later writes and
    the flush at exit go to /dev/null, which would otherwise fail again (status 120); the
    reason, for a note."""
    sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process
    return error.strerror or str(error)
