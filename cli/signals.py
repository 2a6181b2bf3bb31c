"""Signals and exit codes of the ``calib`` command (light: imported before numpy, pandas or typer).

SIGTERM (what ``kill`` and job schedulers send) is handled like SIGINT (Ctrl-C): it raises
:class:`Terminated`, a ``KeyboardInterrupt``, so every ``with``/``finally`` clean-up runs (temporary
folders removed, locks released, worker pools stopped), then the command exits with 143 (SIGINT: 130).
"""
from __future__ import annotations

import gc
import os
import signal
import sys
import threading

from calib import interrupts

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_FAILED = 3     # the calibration ran but its verdict is "failed" (report.json: verdict)
EXIT_SIGINT = 130   # 128 + SIGINT
EXIT_SIGTERM = 143  # 128 + SIGTERM


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM."""


# The signal whose interrupt has not reached one of our handlers yet. Python swallows an exception raised
# inside a finaliser or weakref callback ("Exception ignored in ..."), so an interrupt that lands there
# would be lost and the command would run on; :func:`check` raises it again at the next progress point.
_pending = None


def exception_for(signum):
    """The exception an interrupt by ``signum`` raises: :class:`Terminated` (SIGTERM) or KeyboardInterrupt."""
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_signal(signum, frame):
    global _pending
    if interrupts.deferring():  # a few statements that must run together (calib.interrupts): raised after them
        interrupts.hold(signum)
        return
    _pending = signum
    raise exception_for(signum)


def _unraisable(info):
    """``sys.unraisablehook``: an interrupt swallowed in a finaliser is re-raised by :func:`check`, silently."""
    if _pending is not None and isinstance(info.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(info)


def install():
    """Route SIGTERM to :class:`Terminated` and SIGINT to KeyboardInterrupt (main thread only).

    Returns the previous handlers, for :func:`restore`.
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    sys.unraisablehook = _unraisable
    return (signal.signal(signal.SIGTERM, _on_signal), signal.signal(signal.SIGINT, _on_signal))


def check():
    """Raise again an interrupt that Python swallowed in a finaliser (called at every progress point)."""
    if _pending is not None:
        raise exception_for(_pending)


def checked(callback=None):
    """``callback`` (a progress callback, or None) that first calls :func:`check`."""

    def call(*args, **kwargs):
        check()
        return None if callback is None else callback(*args, **kwargs)

    return call


def restore(previous):
    if previous is not None:
        signal.signal(signal.SIGTERM, previous[0])
        signal.signal(signal.SIGINT, previous[1])


def interrupt_code(exc):
    """Exit code for an interrupt: 143 after SIGTERM, 130 after SIGINT."""
    return EXIT_SIGTERM if isinstance(exc, Terminated) else EXIT_SIGINT


def interrupted(exc, message="interrupted; nothing partial was kept"):
    """Print the one-line interrupt message and return the exit code (the interrupt is handled)."""
    global _pending
    _pending = None
    what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted (SIGINT)"
    try:
        print(f"{what}: {message.removeprefix('interrupted; ').removeprefix('interrupted: ')}", file=sys.stderr)
    except (OSError, ValueError):
        pass  # stderr is a closed pipe (e.g. `calib run ... 2>&1 | head` stopped reading): the exit code still tells
    return interrupt_code(exc)


def leave(code):
    """Exit the process with ``code`` (from ``SystemExit.code``), keeping the interrupt exit codes exact.

    A command that finished although an interrupt was swallowed on the way (see :func:`check`) exits as
    interrupted: the user asked it to stop. After an interrupt every clean-up has already run, so the
    process ends with ``os._exit``: CPython may otherwise turn a KeyboardInterrupt it saw during the run,
    even a handled one, into death by SIGINT at shutdown (exit -2 instead of 130).
    """
    if code in (None, EXIT_OK) and _pending is not None:
        code = interrupted(exception_for(_pending), "interrupted as the command finished; its outputs are complete")
    elif code == EXIT_SIGINT and _pending is not None:
        # typer turns an interrupt outside the command's own handling (parsing the arguments, entering the
        # command) into a silent exit 130, whatever the signal: report it as any other, with its own code
        code = interrupted(exception_for(_pending))
    if code in (EXIT_SIGINT, EXIT_SIGTERM):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    gc.freeze()  # the interpreter's exit then skips collecting every object again (0.1-0.7 s of a command's wall)
    sys.exit(code)
