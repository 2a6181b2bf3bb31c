"""The C allocator's settings for a short-lived process that allocates and frees large arrays (the CLI).

glibc's malloc serves a block above its mmap threshold (128 KiB at start, raised on its own up to 32 MiB)
with a fresh ``mmap`` and returns it with ``munmap`` when freed, and returns heap memory above its trim
threshold to the kernel. The frontend allocates arrays of megabytes per detection block and per chunk of
events, over and over: every fresh mapping is zeroed page by page (a page fault per 4 KiB), and with the
arrays processed in threads every ``munmap`` also stalls the other core (a TLB shoot-down). Keeping the
freed blocks in the heap halves the page faults of ``calib features`` on a hall session (its CPU: 0–12 %
less in paired fresh runs, docs/results.md); the process holds up to ``trim_threshold`` of freed memory
for reuse.

Only the CLI calls :func:`keep_freed_memory` (a library does not change its host process's allocator); in a
long-lived process the same effect comes from the environment: ``MALLOC_MMAP_THRESHOLD_=67108864
MALLOC_TRIM_THRESHOLD_=268435456`` before Python starts.
"""
from __future__ import annotations

import ctypes
import os
import platform

MMAP_THRESHOLD = 64 << 20   # blocks up to 64 MiB come from the heap (a timing chunk is at most 128 MB in all)
TRIM_THRESHOLD = 256 << 20  # freed heap memory kept for reuse up to 256 MiB before it goes back to the kernel
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (glibc's malloc.h)
_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory(mmap_threshold=MMAP_THRESHOLD, trim_threshold=TRIM_THRESHOLD):
    """Set glibc's mmap and trim thresholds (bytes) for this process: large freed blocks are reused.

    Does nothing (returns False) with another C library, or when the environment already sets either
    threshold (the user's choice stands). Returns True when both were set.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc" or any(k in os.environ for k in _ENV):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # the mmap threshold first: setting the trim threshold alone would freeze the mmap threshold at 128 KiB
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))
