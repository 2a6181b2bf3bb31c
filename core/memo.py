"""A small bounded memo for set-ups that the arrays of one session share (FFT plans, steering grids)."""
from __future__ import annotations

import threading


class SetupCache:
    """``get(key, make)``: ``make()``'s result, computed once per key; emptied when ``size`` keys are held
    (a session uses a few keys, so a full cache means an earlier session's, not this one's).

    Thread-safe (the frontend may process arrays in threads): two threads missing the same key may both
    call ``make`` (the values are equal); the one stored last stays."""

    def __init__(self, size=8):
        self.size = size
        self._items = {}
        self._lock = threading.Lock()

    def get(self, key, make):
        with self._lock:
            value = self._items.get(key, _MISSING)
        if value is _MISSING:
            value = make()
            with self._lock:
                if len(self._items) >= self.size:
                    self._items.clear()
                self._items[key] = value
        return value


_MISSING = object()
