"""Two-phase work on threads, the phases staggered: the interpreter's lock decides the speed.

Each array's work has a first phase whose time is mostly in FFTs and whole-array numpy calls, which run
without the interpreter's lock (detection), and a second made of many small numpy calls over its events,
each holding the lock for most of its duration (timing, DOA). Two threads both in their second phase
queue for the lock; a thread in its first phase runs beside one in its second. :func:`two_phase` runs
``second(k, first(k))`` for every item on ``workers`` threads and gives a free thread the phase fewer
threads are running, so the arrays' detections overlap the other arrays' timing instead of each other's.
"""
from __future__ import annotations

import threading
from collections import deque


class _Board:
    """The shared state of :func:`two_phase`'s threads (every field guarded by ``cond``)."""

    def __init__(self, n, extra):
        self.cond = threading.Condition()
        self.first_todo = deque(range(n))  # items whose first phase has not started
        self.second_todo = deque()         # items whose first phase is done: (k, state)
        self.extra = extra                 # a second-phase task of its own, or None (taken / none)
        self.running = {"first": 0, "second": 0}
        self.done = {}                     # k or "extra" → (ok, result or exception)
        self.stop = False

    def pick(self):
        """The next task (kind, k, state), or None if none is ready (or the work stopped); the phase fewer
        threads run first."""
        if self.stop:
            return None
        second_ready = bool(self.second_todo) or self.extra is not None
        if self.first_todo and (not second_ready or self.running["first"] <= self.running["second"]):
            return "first", self.first_todo.popleft(), None
        if self.second_todo:
            k, state = self.second_todo.popleft()
            return "second", k, state
        if self.extra is not None:
            task, self.extra = self.extra, None
            return "second", "extra", task
        return None

    def idle_for_good(self):
        """Nothing left for a thread to start, now or later."""
        return self.stop or not (self.first_todo or self.second_todo or self.extra is not None
                                 or self.running["first"])


def _worker(board, first, second):
    while True:
        with board.cond:
            task = board.pick()
            while task is None:
                if board.idle_for_good():
                    return
                board.cond.wait()
                task = board.pick()
            kind, k, state = task
            board.running[kind] += 1
        try:
            if k == "extra":
                out = (True, state())
            else:
                out = (True, first(k) if kind == "first" else second(k, state))
        except BaseException as exc:  # handed to the caller, raised there in item order
            out = (False, exc)
        with board.cond:
            board.running[kind] -= 1
            if kind == "first" and out[0]:
                board.second_todo.append((k, out[1]))
            else:
                board.done[k] = out
            board.cond.notify_all()


def two_phase(first, second, n, workers, extra=None, waiting=None, discard=None):
    """Results of ``second(k, first(k))`` for k = 0 .. n − 1 in that order, then ``extra()``'s if given,
    computed on ``workers`` threads (:class:`_Board` for the order of work; the results do not depend on it).

    An exception of item k (either phase) is raised when k's turn comes, after the results of the items
    before it; then no further task starts (the running ones finish) and the threads are joined.
    waiting : optional ``waiting(k)`` called before waiting for item k (progress).
    discard : optional ``discard(state)`` for every first-phase result whose second phase never started
    (after an error: e.g. close the file it holds open).
    Returns a list of n results (+ extra's).
    """
    board = _Board(n, extra)
    threads = [threading.Thread(target=_worker, args=(board, first, second), name=f"calib-array-{i}", daemon=True)
               for i in range(workers)]
    for t in threads:
        t.start()
    try:
        out = []
        for k in list(range(n)) + (["extra"] if extra is not None else []):
            if waiting is not None and k != "extra":
                waiting(k)
            with board.cond:
                while k not in board.done:
                    board.cond.wait()
                ok, value = board.done[k]
            if not ok:
                raise value
            out.append(value)
        return out
    finally:
        with board.cond:
            board.stop = True
            board.cond.notify_all()
        for t in threads:
            t.join()
        while discard is not None and board.second_todo:
            discard(board.second_todo.popleft()[1])
