"""BLAS threads: one, where the matrices are small.

Multi-threaded BLAS on small matrices (a few thousand × a few columns, ~400 × 100) only adds
synchronisation: measured 2–4× more CPU on 2 cores for the estimator and the set-up stage's fits, whose
parallelism goes across arrays or calibrations instead.
"""
from __future__ import annotations

import functools


@functools.cache
def _controller():
    """The process's one ThreadpoolController, made on first use (it scans the loaded libraries: ~5 ms)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def single_thread_blas():
    """Context manager limiting BLAS to one thread. One shared controller: ``threadpool_limits`` scanned
    the process's libraries on every entry, 5–6 ms per array of a session (~4 % of the hall's frontend)."""
    return _controller().limit(limits=1, user_api="blas")
