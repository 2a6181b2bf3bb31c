"""A weak direct path just before a strong reflection (an array mounted 10 cm in front of a wall, its direct
path attenuated 10-20 dB by the mount): the onset search takes the reflection, whose sidelobes hide the
direct path; :func:`calib.frontend.nlos.retime_earlier` finds it after subtracting the timed path and times
the arrival on it. Truth: signals built here with known per-mic delays."""
from __future__ import annotations

import numpy as np
import pytest

from calib.frontend.nlos import earlier_paths, retime_earlier
from calib.frontend.signals import sweep
from calib.frontend.timing import locate, segment_spectra, spectra_setup

FS, F0, F1, T = 16000, 500.0, 4000.0, 0.25
KW = {"lo": 40, "hi": int(0.12 * FS), "half_width": 6, "smear": 0}  # 6 samples: mics 4 cm apart, half a pulse


def _session(paths, rng, n_events=4, tilt=0.0):
    """Spectra of ``n_events`` events at six mics: each path (delay s after the direct path, gain, per-mic
    delay spread s) a copy of the chirp, plus white noise 40 dB below the strongest path and a weak diffuse
    tail. ``tilt``: the received chirp's spectrum rises by this factor across the band (a frequency-dependent
    wall and mic: the template no longer matches the path exactly). Returns (c, c_plain, setup, starts (J, 6))."""
    n = int(0.4 * FS)
    t = np.arange(n) / FS
    tmpl = sweep(np.arange(int(T * FS) + 1) / FS, F0, F1, T, 0.005)
    x, starts = [], []
    for _ in range(n_events):
        s0 = 0.1 + rng.uniform(-1e-4, 1e-4, 6)
        sig = np.zeros((6, n))
        for delay, gain, spread in paths:
            d = delay + rng.uniform(-spread, spread, 6)
            # a linear sweep's instantaneous frequency grows with time: a gain ramp over the sweep tilts its spectrum
            sig += np.stack([gain * sweep(t - s - dd, F0, F1, T, 0.005) * (1 + tilt * np.clip((t - s - dd) / T, 0, 1))
                             for s, dd in zip(s0, d)])
        tail = rng.normal(size=(6, n)) * np.exp(-np.maximum(t - 0.11, 0) / 0.1) * (t > 0.11) * 0.01
        x.append(sig + tail + rng.normal(0, 1e-2 * max(g for _, g, _ in paths) / np.sqrt(FS / 2 / (F1 - F0)), (6, n)))
        starts.append(s0)
    setup = spectra_setup(tmpl, FS, (F0, F1), n)
    cs = [segment_spectra(xx, np.zeros(1, int), setup, plain=True) for xx in x]
    return np.concatenate([c for c, _ in cs]), np.concatenate([p for _, p in cs]), setup, np.array(starts)


def test_weak_direct_path_before_a_strong_reflection_is_timed():
    # direct path 18 dB below a reflection 0.5 ms (1.75 pulse widths) later, from another direction
    rng = np.random.default_rng(1)
    c, c_plain, setup, starts = _session([(0.0, 10 ** (-18 / 20), 0.0), (0.5e-3, 1.0, 3e-5)], rng)
    res = locate(c, setup, **KW, c_onset=c_plain)
    first = res["tau"] - starts
    assert np.all(np.median(first, axis=1) > 3e-4)   # the onset search timed the reflection (the defect)
    res, again = retime_earlier(res, c, c_plain, setup, KW)
    assert again is not None and sorted(again["events"]) == list(range(len(starts)))
    assert np.abs(again["tau"] - starts[again["events"]]).max() < 20e-6   # every mic now times the direct path
    assert np.all(again["ratio"] < 0.35) and np.all(res["ratio"] < 0.35)  # ... reported weak (flagged weak_direct)


@pytest.mark.parametrize("paths, tilt", [
    ([(0.0, 1.0, 0.0)], 1.0),                                  # one path whose spectrum the template misses
    ([(0.0, 1.0, 0.0), (0.4e-3, 0.8, 3e-5)], 0.5),             # a clear array 5 cm from a wall: a merged pair
    ([(0.0, 1.0, 0.0), (0.3e-3, 0.3, 3e-5), (4e-3, 0.7, 1e-4)], 0.0),  # early reflections after it
])
def test_nothing_earlier_where_the_timed_path_is_the_direct_one(paths, tilt):
    rng = np.random.default_rng(2)
    c, c_plain, setup, starts = _session(paths, rng, tilt=tilt)
    res = locate(c, setup, **KW, c_onset=c_plain)
    assert np.abs(res["tau"] - starts).max() < 20e-6
    found, _, _ = earlier_paths(c_plain, setup, res["dp"], KW["lo"], KW["hi"], KW["half_width"], 6.0, 0.05, 2.0)
    assert not found.any()
    out, again = retime_earlier(res, c, c_plain, setup, KW)
    assert again is None and np.array_equal(out["dp"], res["dp"])
