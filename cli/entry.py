"""The ``calib`` console script: signal handlers first, then the (slow) imports, then the command.

The first lines install handlers that only remember a SIGINT/SIGTERM; ``main`` then reports it (exit 130/143,
one line), so an interrupt while the command starts gives no traceback. Before Python has imported this
module (the interpreter's own start, tens of milliseconds) the interpreter's defaults apply.
"""
from __future__ import annotations

import signal as _signal
import sys

_early: list[int] = []  # signals received while the command starts (before the handlers of cli/signals.py are in place)


def _defer(signum, frame):
    _early.append(signum)


for _s in (_signal.SIGINT, _signal.SIGTERM):  # first of all: an interrupt while importing is kept for main()
    _signal.signal(_s, _defer)

from . import signals  # noqa: E402  (after the deferring handlers, on purpose)


def main():
    try:
        signals.install()
        if _early:
            raise signals.exception_for(_early[0])
        from calib.cli.main import app_for

        app = app_for(sys.argv[1:])
    except KeyboardInterrupt as exc:
        signals.leave(signals.interrupted(exc, "interrupted while starting; nothing was written"))
    try:
        app()
    except KeyboardInterrupt as exc:  # outside a command (argument parsing): nothing to clean up
        signals.leave(signals.interrupted(exc, "interrupted; nothing was written"))
    except SystemExit as exc:
        signals.leave(exc.code)
    signals.leave(0)


if __name__ == "__main__":
    main()
