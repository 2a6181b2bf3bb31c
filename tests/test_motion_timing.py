"""Issue 27: the frontend's arrival time of a sweep from a source that moves (and accelerates) during it.

Truth is analytic: a single path whose delay grows as ``δ(t) = ε t + ½ a t²`` over the sweep (ε = ṙ/c at the
start, a = r̈/c); a linear sweep's matched filter sees about the mean stretch, the range rate near half-way
through (t*, :func:`timing.sweep_time`, measured on the template alone), so the arrival is the sweep start's
plus ``β (ε + a t*)`` (β the drift coupling, :func:`timing.drift_bias`).
"""
import numpy as np
import pytest

from calib.frontend import extract as X
from calib.frontend import timing as T
from calib.frontend.signals import chirp_band, chirp_template, sweep

FS, C = 16000, 343.0
CHIRP = {"f0": 500.0, "f1": 4000.0, "duration": 0.5, "fade": 0.0, "kind": "linear"}
# range rates (m/s) at the sweep start and range accelerations (m/s²) of six events: 0.2-0.6 m/s either way
RDOT = np.array([0.55, -0.45, 0.3, -0.2, 0.6, -0.6])
RDDOT = np.array([0.3, -0.25, -0.3, 0.2, 0.0, 0.15])


def _recording(gap=2.0):
    """(1, n) recording of the six events, each a sweep received with the delay ε t + ½ a t² after its start
    (solved for the emission time by fixed point), and the true start sample of each."""
    n_ev = len(RDOT)
    starts = (0.3 + gap * np.arange(n_ev)) * FS + 0.37   # sub-sample starts
    y = np.zeros(int((0.3 + gap * n_ev) * FS))
    n = np.arange(len(y)) / FS
    for t0, eps, acc in zip(starts / FS, RDOT / C, RDDOT / C):
        u = n - t0                                      # receive time since the start's arrival
        te = u.copy()
        for _ in range(6):
            tp = np.clip(te, 0, None)
            te = u - (eps * tp + 0.5 * acc * tp * tp)
        y += sweep(te, CHIRP["f0"], CHIRP["f1"], CHIRP["duration"])
    rng = np.random.default_rng(0)
    return (y + rng.normal(0, 1e-3, len(y)))[None, :], starts


def _arrivals(bank):
    x, starts = _recording()
    tpl = chirp_template(CHIRP, FS)
    band = chirp_band(CHIRP, tpl, FS)
    g = X._timing_layout(np.zeros((1, 3)), band, FS, C, len(tpl), X.DEFAULTS)
    setup = T.spectra_setup(tpl, FS, band, g["seg_len"], X.DEFAULTS["whiten_hz"])
    seg0 = np.round(starts).astype(int) - g["pre"]
    b = X._doppler_bank(tpl, setup, band, np.max(np.abs(RDOT)), C) if bank else None
    loc = X.locate_events(x, seg0, setup, {**g["locate_kw"], "own_phase": bank}, bank=b)
    beta = T.drift_bias(tpl, FS, band, g["locate_kw"], g["pre"], g["seg_len"], X.DEFAULTS["whiten_hz"])
    t_mid = T.sweep_time(tpl, FS, band, g["locate_kw"], g["pre"], g["seg_len"], X.DEFAULTS["whiten_hz"], beta)
    assert 0.4 * CHIRP["duration"] < t_mid < 0.5 * CHIRP["duration"]   # the band's middle weighs more than T/2
    arrival = seg0 / FS + loc["tau"][:, 0] + beta * loc["stretch"]
    expected = starts / FS + beta * (RDOT + RDDOT * t_mid) / C
    return arrival - expected, loc["stretch"], t_mid


def test_doppler_bank_times_a_moving_source_to_its_mid_sweep_range_rate():
    err, stretch, t_mid = _arrivals(bank=True)
    assert np.max(np.abs(err)) < 8e-6, err           # 8 µs = 3 mm of path, against shifts of up to 1 ms
    # the chosen stretch is the mean one, within the bank's step (a quarter pulse of smear)
    step = X.STRETCH_STEP_PULSES / (3500.0 * CHIRP["duration"])
    assert np.all(np.abs(stretch - (RDOT + RDDOT * t_mid) / C) < 2.5 * step)   # (the arrival does not depend on it)


def test_doppler_search_hands_locate_the_chosen_rows_envelope():
    """matched_stretch's rows are the argmax of every row's direct-path peak, and the envelope it returns is the
    one locate computes on the spectra stretched by those rows (the same values, bit for bit), so locate given
    it times every event exactly as without it."""
    x, starts = _recording()
    tpl = chirp_template(CHIRP, FS)
    band = chirp_band(CHIRP, tpl, FS)
    g = X._timing_layout(np.zeros((1, 3)), band, FS, C, len(tpl), X.DEFAULTS)
    setup = T.spectra_setup(tpl, FS, band, g["seg_len"], X.DEFAULTS["whiten_hz"])
    c, c_plain = T.segment_spectra(x, np.round(starts).astype(int) - g["pre"], setup, plain=True)
    bank = X._doppler_bank(tpl, setup, band, np.max(np.abs(RDOT)), C)
    kw = {**g["locate_kw"], "own_phase": True}
    rows, env = T.matched_stretch(c_plain, setup, bank[0], kw["lo"], kw["hi"], stretches=bank[1])
    peaks = []
    for i in range(len(bank[0])):   # every row's direct-path peak, exhaustively
        e = np.abs(T.lag_grid(c_plain * bank[0][i], setup, kw["lo"], kw["hi"])).mean(axis=1)
        d = T.direct_path_lag(e, T.pulse_envelope(setup, kw["hi"] - kw["lo"], plain=True),
                              near=T.pulse_near(setup, kw["hi"] - kw["lo"], 2, plain=True))[0]
        peaks.append(e[np.arange(len(d)), d])
    assert np.array_equal(rows, np.argmax(peaks, axis=0))
    rows3, env3 = T.matched_stretch(c_plain, setup, bank[0], kw["lo"], kw["hi"], stretches=bank[1], coarse=3)
    np.testing.assert_array_equal(env3, np.abs(T.lag_grid(c_plain * bank[0][rows3][:, None, :], setup, kw["lo"],
                                                          kw["hi"])).mean(axis=1))   # (the coarse-to-fine search)
    c, c_plain = c * bank[0][rows][:, None, :], c_plain * bank[0][rows][:, None, :]
    np.testing.assert_array_equal(env, np.abs(T.lag_grid(c_plain, setup, kw["lo"], kw["hi"])).mean(axis=1))
    given, own = (T.locate(c, setup, **kw, c_onset=c_plain, onset_env=e) for e in (env, None))
    np.testing.assert_array_equal(given["tau"], own["tau"])


def test_shared_phase_template_timing_slips_for_a_moving_source():
    """Control: one carrier phase for all events and the unstretched template (a robot that stops) misses
    the same arrivals by a good part of a carrier period (the stretch rotates the phase ~0.4 rad per 1e-4)."""
    err = _arrivals(bank=False)[0]
    assert np.max(np.abs(err)) > 60e-6


def test_sweep_middle_is_exact_for_a_constant_acceleration():
    """The estimator's source state ``t*`` into each sweep: a cubic Hermite through the odometry positions and
    velocities at the sweep starts reproduces a quadratic path exactly (displacement and velocity)."""
    from calib.estimator.motion import sweep_middle

    rng = np.random.default_rng(1)
    s0, v0, acc = rng.normal(0, 1, 3), rng.normal(0, 0.4, 3), rng.normal(0, 0.2, 3)
    t = np.cumsum(rng.uniform(2.0, 4.0, 8))
    pos = s0 + np.outer(t, v0) + 0.5 * np.outer(t**2, acc)
    vel = v0 + np.outer(t, acc)
    disp, v_mid = sweep_middle(t, pos, vel, 0.22)
    tm = t + 0.22
    assert np.allclose(disp, s0 + np.outer(tm, v0) + 0.5 * np.outer(tm**2, acc) - pos, atol=1e-12)
    assert np.allclose(v_mid, v0 + np.outer(tm, acc), atol=1e-12)
    # without a time: the start's velocity, no displacement
    d0, v_0 = sweep_middle(t, pos, vel, 0.0)
    assert np.all(d0 == 0) and np.all(v_0 == vel)


def _true_directions(out, doa, t_rel):
    """(n, 3) unit vectors in each row's array frame from the array to the rendered source ``t_rel`` (s, (n,)
    or scalar) after the row's sweep start (truth/trajectory.csv, truth/arrays.csv, events.csv)."""
    import pandas as pd
    from scipy.spatial.transform import Rotation

    arr = pd.read_csv(out / "truth" / "arrays.csv").set_index("array")
    tr = pd.read_csv(out / "truth" / "trajectory.csv")
    t0 = pd.read_csv(out / "events.csv").set_index("event")["t_emit"]
    t = t0.loc[doa["event"]].to_numpy() + t_rel
    s = np.column_stack([np.interp(t, tr["t"], tr[k]) for k in "xyz"])
    a = arr.loc[doa["array"]]
    R = Rotation.from_quat(a[["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()
    w = np.einsum("kba,kb->ka", R, s - a[["x", "y", "z"]].to_numpy())   # R_iᵀ (s − x_i)
    return w / np.linalg.norm(w, axis=1, keepdims=True)


@pytest.mark.slow
def test_doa_of_a_moving_source_looks_at_the_stated_instant(tmp_path):
    """The instant a moving source's DOA represents (meta ``doa_time_s``, which the estimator turns the DOA
    from to the sweep start) against the rendered trajectory: free field, the robot at 0.3-0.6 m/s, so the
    direction from an array turns by ~1-4° over the sweep and each band of the sweep sees its own direction.
    The frontend's DOAs lie on the truth at ``doa_time_s`` (measured 0.07° median on seed 3, where the start
    is 1.1° off and T/2 0.3°), and fitting each row's direction along the sweep puts them 0.6-0.7 T in."""
    from calib.pipeline.features import session_features
    from calib.pipeline.simulate.roomsim import make_scenario, simulate

    sc = make_scenario("moving", 3, n_events=5, rt60=0.0, sigma_vel=0.0, sigma_odo=0.0)
    out = simulate(sc, tmp_path / "m")
    feats, _ = session_features(out)
    doa, t_doa, dur = feats["doa"], feats["meta"]["doa_time_s"], sc["chirp"]["duration"]
    assert 0.6 * dur < t_doa < 0.7 * dur
    u = doa[["ux", "uy", "uz"]].to_numpy(float)
    err = {f: np.degrees(np.arccos(np.clip(np.sum(u * _true_directions(out, doa, f * dur), axis=1), -1, 1)))
           for f in (0.0, 0.5, t_doa / dur, 1.0)}
    at_doa = np.median(err[t_doa / dur])
    assert at_doa < 0.15, err
    assert np.median(err[0.0]) > 5 * at_doa and np.median(err[0.5]) > 2 * at_doa and np.median(err[1.0]) > 3 * at_doa
    # the instant each row looks at: its direction's closest approach to the truth over the sweep
    f = np.linspace(0.0, 1.0, 41)
    best = f[np.argmax([np.sum(u * _true_directions(out, doa, x * dur), axis=1) for x in f], axis=0)]
    turns = np.degrees(np.arccos(np.sum(_true_directions(out, doa, 0.0) * _true_directions(out, doa, dur), axis=1)))
    assert np.sum(turns > 1.0) >= 5 and np.all(np.abs(best[turns > 1.0] - t_doa / dur) < 0.1), (best, turns)
