"""One independent piece of work in a second process while this one goes on (``calib estimate``: the set-up
findings a features folder shows, meanwhile the estimator runs: 2.5 s of 10 at 40 arrays × 1000 events).

    with Background(feature_findings, feats) as job:
        calib = calibrate(feats)
        found = job.result()

The second process is forked (it inherits the arguments: nothing is copied up front) and sends back only
the result. Where fork is not available, or on one core, ``result()`` runs the function here instead; so it
does if the second process dies. An exception in the function is raised again by ``result()``. Leaving the
``with`` block ends a second process still running (an error in the main work, Ctrl-C).
"""
from __future__ import annotations

import multiprocessing
import os
import signal


def _child(conn, fn, args):
    # the parent's handlers (calib.cli.signals) turn SIGTERM into an exception, which a forked child would print
    # as a traceback when close() ends it mid-send: here SIGTERM just ends it, and Ctrl-C (sent to the whole
    # process group) is the parent's to handle (it then ends this one)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        out = ("ok", fn(*args))
    except BaseException as exc:  # noqa: BLE001 (handed to the parent, which raises it)
        out = ("error", exc)
    try:
        conn.send(out)
    except Exception as exc:  # noqa: BLE001 (an unpicklable result or exception: say so)
        conn.send(("error", RuntimeError(f"background {fn.__name__}: {type(exc).__name__}: {exc}")))
    finally:
        conn.close()


class Background:
    """``fn(*args)`` in a forked process from construction on; :meth:`result` waits for it."""

    def __init__(self, fn, *args):
        self.fn, self.args, self.proc, self.conn = fn, args, None, None
        if (os.cpu_count() or 1) > 1 and "fork" in multiprocessing.get_all_start_methods():
            ctx = multiprocessing.get_context("fork")
            self.conn, child = ctx.Pipe(duplex=False)
            self.proc = ctx.Process(target=_child, args=(child, fn, args), daemon=True)
            self.proc.start()
            child.close()

    def result(self):
        """The function's value (or its exception raised here)."""
        if self.proc is None:
            return self.fn(*self.args)
        try:
            status, value = self.conn.recv()
        except EOFError:   # the second process died without an answer: do the work here
            status, value = "ok", self.fn(*self.args)
        finally:
            self.close()
        if status == "error":
            raise value
        return value

    def close(self):
        """End the second process (if still running) and release it."""
        if self.proc is not None:
            if self.proc.is_alive():
                self.proc.terminate()
            self.proc.join()
            self.conn.close()
            self.proc = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
