"""A small bounded memo for set-ups that the arrays of one session share (FFT plans, steering grids)."""
from __future__ import annotations

import threading


class SetupCache:
    """``get(key, make)``: ``make()``'s result, computed once per key; emptied when ``size`` keys are held
    (a session uses a few keys, so a full cache means an earlier session's, not this one's).

    Thread-safe (the frontend may process arrays in threads): a thread asking for a key another thread is
    computing waits for that value instead of computing it again (the arrays of a session start together
    and share their set-ups: ~20 ms of steering grids and FFT set-ups each, on both cores at once). If that
    computation fails, the waiting thread computes the value itself."""

    def __init__(self, size=8):
        self.size = size
        self._items = {}
        self._pending = {}  # key → threading.Event set when its computation ends
        self._lock = threading.Lock()

    def get(self, key, make):
        while True:
            with self._lock:
                value = self._items.get(key, _MISSING)
                if value is not _MISSING:
                    return value
                pending = self._pending.get(key)
                if pending is None:  # this thread computes it
                    pending = self._pending[key] = threading.Event()
                    break
            pending.wait()  # another thread computes it: take its value (or try again if it failed)
        try:
            value = make()
            with self._lock:
                if len(self._items) >= self.size:
                    self._items.clear()
                self._items[key] = value
            return value
        finally:
            with self._lock:
                del self._pending[key]
            pending.set()


_MISSING = object()
