"""calib.frontend.schedule: two-phase work on threads, results in item order whatever the timing."""
from __future__ import annotations

import threading
import time

import pytest

from calib.frontend.schedule import _Board, two_phase


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_results_come_in_item_order_with_the_extra_task_last(workers):
    rng_delay = [0.004, 0.0, 0.002, 0.0, 0.003, 0.001, 0.0]  # later items often finish first

    def first(k):
        time.sleep(rng_delay[k])
        return 10 * k

    def second(k, st):
        time.sleep(rng_delay[-1 - k])
        return (k, st + 1, threading.current_thread().name)

    seen = []
    out = two_phase(first, second, 7, workers, extra=lambda: "beta", waiting=seen.append)
    assert [(k, st) for k, st, _ in out[:-1]] == [(k, 10 * k + 1) for k in range(7)]
    assert out[-1] == "beta" and seen == list(range(7))
    assert len({name for *_, name in out[:-1]}) <= workers
    assert not [t for t in threading.enumerate() if t.name.startswith("calib-array-")]  # joined


@pytest.mark.parametrize("phase", ["first", "second"])
def test_the_first_failing_item_in_order_is_raised_after_the_items_before_it(phase):
    done, started = [], []

    def first(k):
        started.append(k)
        if phase == "first" and k in (3, 5):
            raise ValueError(f"bad file {k}")
        return k

    def second(k, st):
        if phase == "second" and k in (3, 5):
            raise ValueError(f"bad file {k}")
        done.append(k)
        return k

    discarded = []
    with pytest.raises(ValueError, match="bad file 3"):
        two_phase(first, second, 8, 2, discard=discarded.append)
    assert {0, 1, 2} <= set(done) and 3 not in done
    # every first phase that ran either reached its second phase or was handed to discard
    finished = set(done) | set(discarded) | ({3, 5} if phase == "second" else set())
    assert set(started) - ({3, 5} if phase == "first" else set()) <= finished
    assert not [t for t in threading.enumerate() if t.name.startswith("calib-array-")]


def test_every_item_failing_does_not_hang():
    def first(k):
        raise OSError(k)

    with pytest.raises(OSError):
        two_phase(first, lambda k, st: st, 5, 2, extra=lambda: 1)


def test_a_free_thread_takes_the_phase_fewer_threads_are_running():
    b = _Board(3, extra=None)
    assert b.pick() == ("first", 0, None)  # nothing running: detections feed the rest
    b.running["first"] = 1
    assert b.pick() == ("first", 1, None)  # no second phase ready yet: another first
    b.second_todo.append((0, "s0"))
    assert b.pick() == ("second", 0, "s0")  # one thread in a first phase: this one takes a second
    b.running["second"] = 1
    b.second_todo.append((1, "s1"))
    assert b.pick() == ("first", 2, None)  # one of each running: a first phase, while there is one
    assert b.pick() == ("second", 1, "s1")
    assert b.pick() is None and not b.idle_for_good()  # a first phase still running may add work
    b.running["first"] = 0
    assert b.idle_for_good()
