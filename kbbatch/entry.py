"""The `kbbatch` command itself: loads the CLI and runs it, so that Ctrl-C at any moment ends
with one line and status 130. Pressed while the modules loaded, it gave a traceback; pressed
while a command set up, click's "Aborted!" and status 1, the status of a batch with failed
photos. Nothing heavy is imported before the handler is in place."""

from __future__ import annotations

import sys

from kbbatch import (
    EXIT_INTERRUPTED,
    INTERRUPTED_LINE,
    ignore_stop_signals,
    interrupted_while_loading,
)

try:
    from kbbatch.interrupts import interrupted
    from kbbatch.streams import standard_streams_ready
except KeyboardInterrupt:
    interrupted_while_loading()
    raise


def main() -> None:
    standard_streams_ready()
    try:
        status = _run()
    except SystemExit as exit_:  # said and settled (an interrupt the command caught included)
        if exit_.code == EXIT_INTERRUPTED:  # first: a Ctrl-C pressed again landed in the exec
            ignore_stop_signals()           # below, with a traceback and death by SIGINT
        _forget_uncaught_interrupt()
        raise
    except BaseException as error:
        if not interrupted(error):
            raise
        ignore_stop_signals()
        print(INTERRUPTED_LINE, file=sys.stderr)
        _forget_uncaught_interrupt()
        sys.exit(EXIT_INTERRUPTED)
    sys.exit(status if isinstance(status, int) else 0)


def _forget_uncaught_interrupt() -> None:
    """A Ctrl-C that lands in code run from a string (dataclasses build their methods so, while
    the modules load) sets CPython's flag of an uncaught KeyboardInterrupt, though it was
    caught: under `python -m kbbatch` the process then killed itself with SIGINT at exit
    instead of ending with status 130 (4 of 60 Ctrl-Cs 0.15 to 0.53 s into `kbbatch plan`).
    CPython clears the flag before it runs any code from a string."""
    exec("pass")  # noqa: S102 - a constant string: clears the flag, runs nothing


def _run() -> object:
    import click

    from kbbatch.cli import main as command

    try:
        return command.main(standalone_mode=False)
    except click.Abort:  # click's word for a Ctrl-C it caught
        raise KeyboardInterrupt from None
    except click.ClickException as error:  # said as click's standalone mode says it
        error.show()
        sys.exit(error.exit_code)
