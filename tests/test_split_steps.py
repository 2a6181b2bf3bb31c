"""Breaks in an array's chain of arrivals (pipeline.setupcheck.split_steps): a logged emission interval off by a
fraction of a millisecond, or a dropped block of samples, shifts every later arrival of the chain."""
from __future__ import annotations

import numpy as np
import pytest

from calib.pipeline.setupcheck import _step_scores, split_steps

C = 343.0
SIG_T = 2e-5   # s


def chain(seed, k=60, step_at=None, step_s=0.0, segments=(0,)):
    rng = np.random.default_rng(seed)
    odo = np.column_stack([rng.uniform(-3, 3, k), rng.uniform(-2, 2, k), rng.uniform(0, 1, k)])
    e = np.cumsum(rng.uniform(2, 4, k))
    x = np.array([4.0, 3.0, 1.5])
    seg = np.searchsorted(np.asarray(segments), np.arange(k), side="right") - 1
    y = 0.05 * seg + 2e-5 * e + np.linalg.norm(odo - x, axis=1) / C + rng.normal(0, SIG_T, k)
    if step_at is not None:
        y[step_at:] += step_s
    return odo, e, y, seg, x


def explicit_gain(odo, e, y, seg, x, j):
    """RSS(no step) − RSS(a step before arrival j in its segment), each a least-squares refit."""
    def rss(sg):
        A = np.column_stack([np.eye(sg.max() + 1)[sg], e, np.linalg.norm(odo - x, axis=1)])
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        return r @ r
    trial = np.where((np.arange(len(y)) >= j) & (seg == seg[j]), seg + 1, seg + (seg > seg[j]))
    return rss(seg) - rss(trial)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_step_scores_equal_the_refits_they_stand_for(seed):
    odo, e, y, seg, x = chain(seed, k=40, step_at=23, step_s=4e-4, segments=(0, 30))
    got = _step_scores(odo, e, y, seg, x)
    want = np.array([0.0 if j == 0 or seg[j] != seg[j - 1] else explicit_gain(odo, e, y, seg, x, j)
                     for j in range(len(y))])
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-12 * want.max())
    assert got[0] == 0 and got[30] == 0   # a segment's first arrival: nothing before it to break from


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("step_s", [-7e-4, 9e-4, 20e-3])
def test_a_step_is_broken_out_where_it_is(seed, step_s):
    odo, e, y, seg, _ = chain(seed, step_at=37, step_s=step_s)
    out = split_steps(odo, e, y, seg, SIG_T)
    assert out.max() == 1 and np.flatnonzero(np.diff(out))[0] + 1 == 37


@pytest.mark.parametrize("seed", range(5))
def test_a_clean_chain_is_left_whole(seed):
    odo, e, y, seg, _ = chain(seed, segments=(0, 25))
    np.testing.assert_array_equal(split_steps(odo, e, y, seg, SIG_T), seg)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_long_chain_is_started_coarse_to_fine_as_the_full_search_starts_it(seed, monkeypatch):
    """Above COARSE_ARRIVALS the starts are searched on a spread subset first, then refined on every arrival:
    the same minima as the 20 starts run on every arrival (positions within the search's tolerance)."""
    import calib.pipeline.setupcheck as S

    odo, e, y, seg, x = chain(seed, k=3 * S.COARSE_ARRIVALS, segments=(0, 500))
    coarse = S._arrival_starts(odo, e, y, seg)
    monkeypatch.setattr(S, "COARSE_ARRIVALS", len(y))
    full = S._arrival_starts(odo, e, y, seg)
    assert len(coarse) == len(full)
    for a, b in zip(coarse, full):
        np.testing.assert_allclose(a[:3], b[:3], atol=1e-5)      # m
        np.testing.assert_allclose(a[-1], b[-1], rtol=1e-6)      # 1/c
    assert np.linalg.norm(coarse[0][:3] - x) < 0.05 and abs(1 / coarse[0][-1] - C) < 1.0
