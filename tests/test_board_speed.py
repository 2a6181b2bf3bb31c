"""A 3-D board's own speed of sound (issue 27): a plane wave's per-mic delays against the declared mic geometry
give its slowness ``|w| = 1 / c``, no odometry involved — the absolute scale that tells a wrong declared speed of
sound from a mis-scaled odometry (the arrivals against the odometry fix only their ratio).

Truth: chirps rendered analytically on a tetrahedron (exact fractional delays of plane or spherical waves, a
little white noise), the true c 343 m/s whatever is declared.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.frontend.consistency import board_speed, fit_geometry, measure_delays
from calib.pipeline.setupcheck import Finding, settled_by_estimate, sound_cause
from calib.pipeline.simulate.deploy import BOARDS

C_TRUE = 343.0
TETRA = BOARDS["tetra"][0]     # 3.5 cm tetrahedron
CIRCLE = BOARDS["circle6"][0]


def _chirp(fs, f0, f1, dur=0.3):
    t = np.arange(int(dur * fs)) / fs
    x = np.sin(2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / dur * t**2))
    n = int(0.005 * fs)
    x[:n] *= np.hanning(2 * n)[:n]
    x[-n:] *= np.hanning(2 * n)[n:]
    return x


def _recording(mics, fs, band, seed, r_src=None, n=10, seg_s=0.6):
    """(recording (M, N), chirp, chirp times s): ``n`` chirps from random directions, plane waves (``r_src``
    None) or from ``r_src`` metres, delays exact (a phase ramp), 40 dB SNR."""
    rng = np.random.default_rng(seed)
    tpl = _chirp(fs, *band)
    L = int(seg_s * fs)
    f = np.fft.rfftfreq(L, 1 / fs)
    pad = np.zeros(L)
    pad[: len(tpl)] = tpl
    spec = np.fft.rfft(pad)
    x, times = np.zeros((len(mics), n * L)), []
    for k in range(n):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        t0 = 0.1
        tm = t0 + ((np.linalg.norm(r_src * u - mics, axis=1) - r_src) if r_src else -mics @ u) / C_TRUE
        x[:, k * L : (k + 1) * L] = np.fft.irfft(spec * np.exp(-2j * np.pi * f * tm[:, None]), L)
        times.append(k * L / fs + t0)
    x += rng.normal(size=x.shape) * 0.01 * np.std(x)
    return x, tpl, np.array(times)


@pytest.mark.parametrize("fs, band", [(44100, (500.0, 4000.0)), (16000, (500.0, 4000.0)), (48000, (500.0, 10000.0))])
def test_the_board_measures_the_true_speed_whatever_is_declared(fs, band):
    x, tpl, times = _recording(TETRA, fs, band, seed=1)
    d = measure_delays(x, TETRA, tpl, fs, band, times, 349.0)
    b = board_speed(d, TETRA, 349.0)
    assert b is not None and b.n == len(times)
    assert abs(b.c - C_TRUE) < 1e-3 * C_TRUE, b          # the flat-topped gate: ≤ 0.07 % (a Hann gate: 0.5-0.9 %)
    assert abs(b.c - C_TRUE) < b.std
    # the mechanism: the Hann-gated delays (the geometry checks') read every delay short, the board fast
    hann = 349.0 * fit_geometry(d, TETRA, 349.0).scale
    assert hann > C_TRUE * (1.004 if band[1] > 5000 else 1.007), hann


@pytest.mark.parametrize("seed", range(3))
def test_a_near_source_stays_within_the_stated_std(seed):
    """A source 1.5 m away: the wave's curvature across 3.5 cm bends each event's |w| (~0.3 %), not the median."""
    x, tpl, times = _recording(TETRA, 44100, (500.0, 4000.0), seed=10 + seed, r_src=1.5, n=12)
    b = board_speed(measure_delays(x, TETRA, tpl, 44100, (500.0, 4000.0), times, C_TRUE), TETRA, C_TRUE)
    assert b is not None and abs(b.c - C_TRUE) < 2 * b.std, b
    assert b.std < 0.01 * C_TRUE   # precise enough to tell a 3 % error


def test_a_planar_board_measures_no_speed():
    """A circle's delays see only cos(el) / c: no speed of its own."""
    x, tpl, times = _recording(CIRCLE, 16000, (500.0, 4000.0), seed=3)
    assert board_speed(measure_delays(x, CIRCLE, tpl, 16000, (500.0, 4000.0), times, C_TRUE), CIRCLE, C_TRUE) is None


def test_the_board_names_the_odometry_or_the_declared_speed():
    board = (343.5, 1.7, ("A4",))
    assert sound_cause(350.0, 0.5, 343.0, board) == "odometry"       # odometry 2 % long, c right
    assert sound_cause(343.2, 0.5, 349.0, board) == "sound"          # c declared 1.7 % high, odometry right
    assert sound_cause(346.0, 0.5, 347.0, board) is None             # the board within 3σ of both: no blame
    assert sound_cause(350.0, 0.5, 343.0, None) is None


def test_an_odometry_blamed_unnames_the_arrays_only_where_c_stayed_declared():
    f = Finding("suspect", "events.csv", "odometry scale", "events.csv: ...", arrays=("A2", "A3")).as_dict()
    kept = settled_by_estimate([f], {"speed_of_sound": {"estimated": False}})[0]
    assert kept["arrays"] == [] and kept["status"] == "suspect"
    solved = settled_by_estimate([f], {"speed_of_sound": {"estimated": True, "value_m_s": 349.0, "std_m_s": 0.5}})[0]
    assert tuple(solved["arrays"]) == ("A2", "A3")   # c solved against a mis-scaled odometry: every array scaled


def test_the_board_alone_names_a_declared_speed_the_odometry_did_not():
    """A moving source (no odometry test below 3 %): the board's own c beyond 3σ and 1 % of the declared is named,
    every non-reference array with it; within them, nothing (clean rendered sessions: |error| ≤ 1.0 σ)."""
    from calib.pipeline.setupcheck import board_findings

    feats = {"meta": {"arrays": ["A1", "A2", "A3"], "reference_array": "A1"}}
    f = board_findings((343.6, 1.7, ("A2",)), 352.0, feats)
    assert len(f) == 1 and f[0].status == "suspect" and f[0].arrays == ("A2", "A3") and "-2.4 %" in f[0].text
    assert board_findings((343.6, 1.7, ("A2",)), 346.0, feats) == []       # 1.4σ
    assert board_findings((343.0, 0.1, ("A2",)), 345.0, feats) == []       # 0.6 %: below SOUND_NEAR_TOL
    assert board_findings(None, 352.0, feats) == []


def test_the_board_alone_speaks_only_where_the_odometry_does_not_test_the_speed():
    """A static source with arrays whose arrivals fit the odometry: its (far more precise) test of c stands and the
    boards' own c does not name the arrays alone; a source moving during its sweeps, or no array to fit: it does."""
    from calib.frontend import extract_features
    from calib.pipeline.formats.session import read_session
    from calib.pipeline.setupcheck import _odometry_tested, speed_of_sound_fit

    feats = extract_features(read_session(Path(__file__).resolve().parents[1] / "sample_data" / "lab3"))[0]
    fits = speed_of_sound_fit(feats)
    assert _odometry_tested(feats, fits)
    assert not _odometry_tested({**feats, "meta": {**feats["meta"], "doa_time_s": 0.25}}, fits)
    assert not _odometry_tested(feats, {})
