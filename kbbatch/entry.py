"""The `kbbatch` command itself: loads the CLI and runs it, so that Ctrl-C at any moment ends
with one line and status 130. Pressed while the modules loaded, it gave a traceback; pressed
while a command set up, click's "Aborted!" and status 1, the status of a batch with failed
photos. Nothing heavy is imported before the handler is in place."""

from __future__ import annotations

import sys

from kbbatch.interrupts import interrupted

EXIT_INTERRUPTED = 130
"""Exit status of a run stopped by Ctrl-C or SIGTERM before it was through."""


def main() -> None:
    try:
        status = _run()
    except SystemExit:  # said and settled (an interrupt the command caught included)
        raise
    except BaseException as error:
        if not interrupted(error):
            raise
        print("\ninterrupted: nothing partial is left; run again to finish", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    sys.exit(status if isinstance(status, int) else 0)


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
