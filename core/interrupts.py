"""Interrupts held back across the few statements that must run together.

A temporary made and the clean-up that removes it armed, a lock taken and its release armed, an output's
folders renamed into place: an interrupt landing between two such statements would leave litter, or half an
output, behind. Inside :func:`deferred` the command's interrupt handler (``calib.cli.signals``) only records
the signal (:func:`hold`); it is raised again, with ``signal.raise_signal``, as the outermost block ends.

Only the main thread defers (it is the one Python runs signal handlers in). A library caller with its own
handlers (a notebook's default SIGINT) is unaffected: its interrupts come as they always did.
"""
from __future__ import annotations

import contextlib
import signal
import threading

_depth = 0       # nesting of deferred() blocks in the main thread
_held: list[int] = []  # signals that arrived inside them, in order


def deferring():
    """Whether an interrupt arriving now should be held (the main thread is inside :func:`deferred`)."""
    return _depth > 0


def hold(signum):
    """Record ``signum`` to be raised again when the outermost :func:`deferred` block ends."""
    _held.append(signum)


@contextlib.contextmanager
def deferred():
    """Run the block without interruption by a handler that honours :func:`deferring`; then deliver what came."""
    global _depth
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _held:
            signum = _held[0]
            _held.clear()
            signal.raise_signal(signum)  # the handler runs now, outside the block
