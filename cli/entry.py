"""The ``calib`` console script: signal handlers first, then the (slow) imports, then the command.

An interrupt during the imports (the first seconds) exits quietly with 130/143 instead of a traceback.
"""
from __future__ import annotations

from . import signals


def main():
    signals.install()
    try:
        from calib.cli.main import app
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
