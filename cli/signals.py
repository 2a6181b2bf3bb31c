"""Signals and exit codes of the ``calib`` command (light: imported before numpy, pandas or typer).

SIGTERM (what ``kill`` and job schedulers send) is handled like SIGINT (Ctrl-C): it raises
:class:`Terminated`, a ``KeyboardInterrupt``, so every ``with``/``finally`` clean-up runs (temporary
folders removed, locks released, worker pools stopped), then the command exits with 143 (SIGINT: 130).
"""
from __future__ import annotations

import signal
import sys
import threading

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_FAILED = 3     # the calibration ran but its verdict is "failed" (report.json: verdict)
EXIT_SIGINT = 130   # 128 + SIGINT
EXIT_SIGTERM = 143  # 128 + SIGTERM


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM."""


def _on_sigterm(signum, frame):
    raise Terminated()


def install():
    """Route SIGTERM to :class:`Terminated` and SIGINT to KeyboardInterrupt (main thread only).

    Returns the previous handlers, for :func:`restore`.
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    return (signal.signal(signal.SIGTERM, _on_sigterm), signal.signal(signal.SIGINT, signal.default_int_handler))


def restore(previous):
    if previous is not None:
        signal.signal(signal.SIGTERM, previous[0])
        signal.signal(signal.SIGINT, previous[1])


def interrupt_code(exc):
    """Exit code for an interrupt: 143 after SIGTERM, 130 after SIGINT."""
    return EXIT_SIGTERM if isinstance(exc, Terminated) else EXIT_SIGINT


def interrupted(exc, message="interrupted; nothing partial was kept"):
    """Print the one-line interrupt message and return the exit code."""
    what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted (SIGINT)"
    print(f"{what}: {message.removeprefix('interrupted; ').removeprefix('interrupted: ')}", file=sys.stderr)
    return interrupt_code(exc)
