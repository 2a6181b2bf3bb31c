"""A small bounded memo for set-ups that the arrays of one session share (FFT plans, steering grids)."""
from __future__ import annotations


class SetupCache:
    """``get(key, make)``: ``make()``'s result, computed once per key; emptied when ``size`` keys are held
    (a session uses a few keys, so a full cache means an earlier session's, not this one's)."""

    def __init__(self, size=8):
        self.size = size
        self._items = {}

    def get(self, key, make):
        if key not in self._items:
            if len(self._items) >= self.size:
                self._items.clear()
            self._items[key] = make()
        return self._items[key]
