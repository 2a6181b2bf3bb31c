"""The frontend's range track (frontend/nlos.py): its 5-parameter fit against scipy's, and the direct paths'
track when the line of sight comes and goes in short runs."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from calib.frontend import nlos

C = 343.0   # m/s


def _track(rng, n=16):
    """(t, s, direct, reflected): emission times, a trajectory 3-6 m from an array at (3, 5, 1.2) on a clock
    (τ 0.7 s, δ 2e-5), and its arrivals by the direct path and by a wall's reflection (the array's image
    across the plane y = 6 m), each with 20 µs of noise."""
    t = np.sort(rng.uniform(0.0, 200.0, n))
    s = np.column_stack([np.linspace(0.0, 6.0, n), 2.0 + np.sin(np.linspace(0.0, 3.0, n)), np.full(n, 0.3)])
    x, image = np.array([3.0, 5.0, 1.2]), np.array([3.0, 7.0, 1.2])
    clock = 0.7 + (1.0 + 2e-5) * t
    return (t, s, *(clock + np.linalg.norm(s - p, axis=1) / C + rng.normal(0.0, 2e-5, n) for p in (x, image)))


def _scipy_refine(q0, arrival, t, s, c, loss):
    """The track fit as scipy's least_squares does it (the previous implementation)."""
    prior = np.zeros((1, 5))
    prior[0, 4] = 1.0 / nlos.DRIFT_PRIOR
    return least_squares(
        lambda q: np.r_[(arrival - nlos.range_model(q, t, s, c)) / nlos.ROBUST_SCALE_S, q[4] / nlos.DRIFT_PRIOR],
        q0, jac=lambda q: np.vstack([-nlos._jacobian(q, t, s, c) / nlos.ROBUST_SCALE_S, prior]), loss=loss,
        f_scale=1.0, x_scale=np.r_[1, 1, 1, 1e-3, 1e-5], max_nfev=500, ftol=1e-12, xtol=1e-12, gtol=1e-12).x


@pytest.mark.parametrize("loss", ["cauchy", "linear"])
def test_track_fit_reaches_scipys_minimum(loss):
    """On direct paths with noise (and a quarter of them reflections for the robust loss), from a start
    30 cm and 1 ms off the truth, the closed 5 × 5 Levenberg–Marquardt reaches the minimum scipy's
    least_squares reaches when run to convergence: the same arrival model to 10 ns, the same horizontal
    position to 0.1 mm. (From a far start a planar trajectory's range track has several minima — the array's mirror
    image across the trajectory's plane among them — and either method may end in any of them.)"""
    for seed in range(4):
        rng = np.random.default_rng(seed)
        t, s, direct, reflected = _track(rng, n=20)
        a = np.where(rng.random(20) < (0.25 if loss == "cauchy" else 0.0), reflected, direct)
        q0 = np.r_[np.array([3.0, 5.0, 1.2]) + rng.normal(0.0, 0.3, 3), 0.7 + 1e-3, 0.0]
        ours = nlos._refine(q0.copy(), np.arange(20), a, t, s, C, None, None, loss=loss)
        ref = _scipy_refine(q0.copy(), a, t, s, C, loss)
        assert np.max(np.abs(nlos.range_model(ours, t, s, C) - nlos.range_model(ref, t, s, C))) < 1e-8
        # the height above a planar trajectory is barely determined (the range is flat in it near the plane)
        assert np.linalg.norm(ours[:2] - ref[:2]) < 1e-4 and abs(ours[2] - ref[2]) < 1e-2


def test_reflections_in_doorway_runs_are_flagged():
    """Half the arrivals reflections, the direct paths in runs of 2-4 events (an office's doorways, as the
    L-shaped office's): no window of SUBSET consecutive events holds direct paths only, yet the track must be
    theirs and exactly the reflections flagged (the latest arrivals are peeled off first)."""
    los = np.array([int(x) for x in "1100001111000011"], bool)
    for seed in range(8):
        t, s, direct, reflected = _track(np.random.default_rng(seed), n=16)
        ev = nlos.late_arrivals(np.where(los, direct, reflected), t, s, C)
        assert np.array_equal(ev["nlos"], ~los), seed
        assert ev["early"] == 0


def test_peel_finds_the_direct_track_from_a_compromise():
    """From the track fitted to all arrivals (a compromise between direct paths and reflections), peeling
    the latest arrivals ends on the direct paths: they lie on it within INLIER_S, the reflections late."""
    los = np.array([int(x) for x in "1100001111000011"], bool)
    t, s, direct, reflected = _track(np.random.default_rng(4), n=16)
    a = np.where(los, direct, reflected)
    q0 = nlos.linear_start(a, t, s, C)
    q0[4] = 0.0
    compromise = nlos._refine(q0, np.arange(16), a, t, s, C, None, None)
    track = nlos.Track(a, t, s)
    q, score = nlos.run_searches([nlos._peel(compromise, track, C, None)], [track], C)[0]
    res = a - nlos.range_model(q, t, s, C)
    assert np.all(np.abs(res[los]) < nlos.INLIER_S)
    assert np.all(res[~los] > nlos.NLOS_MIN_S)
    assert score == int(los.sum())


def test_setup_check_leaves_out_reflection_only_arrivals():
    """The set-up check's channel and geometry tests take the frontend's detections less the events whose
    arrival there is flagged nlos (diagnostics.json), the flag matched as a whole word of the '+' list."""
    from calib.pipeline.setupcheck import nlos_events
    diag = {"arrays": {"A1": {"arrivals": [{"event": 0, "flag": "track"}, {"event": 3, "flag": "weak_direct+nlos"},
                                           {"event": 5, "flag": "nlos"}, {"event": 7, "flag": ""}]},
                       "A2": {"arrivals": [{"event": 3, "flag": "doa_reflection"}]}}}
    assert nlos_events(diag, "A1") == [3, 5]
    assert nlos_events(diag, "A2") == [] and nlos_events(diag, "A9") == [] and nlos_events(None, "A1") == []


def test_arrivals_on_no_track_judge_nothing():
    """Arrivals that follow no range track along the odometry (scattered by 5 ms about the true one: odometry
    not of this session, or in other units on a rendered room) leave a track whose own arrivals scatter by
    more than TRACK_SCALE_MAX: no arrival is called a reflection; with 20 µs of scatter the same reflections
    are flagged."""
    los = np.array([int(x) for x in "1111001111110011"], bool)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        t, s, direct, reflected = _track(rng, n=16)
        a = np.where(los, direct, reflected)
        assert np.array_equal(nlos.late_arrivals(a, t, s, C)["nlos"], ~los)
        ev = nlos.late_arrivals(a + rng.normal(0.0, 5e-3, 16), t, s, C)
        assert ev["scale"] > nlos.TRACK_SCALE_MAX and not ev["nlos"].any() and np.all(np.isnan(ev["late"]))


# ushape seed 71 (calib simulate, rendered by the independent room model), array A1: emission times (s from the
# first), the frontend's arrivals (local s), the odometry (m) and the truth's line of sight per event
U71_T = [0.0, 1.765478, 3.278713, 5.617924, 7.939709, 10.088275, 11.982606, 14.418113, 16.719571, 18.739315, 20.724658,
         22.70372, 24.704837, 27.013012, 28.774984, 30.313892]
U71_A = [0.4269954, 2.2219178, 3.7223723, 6.0482478, 8.3552647, 10.4922557, 12.3840903, 14.8210941, 17.1440021,
         19.1946511, 21.1699421, 23.1342247, 25.1134055, 27.4179475, 29.1791064, 30.7167541]
U71_S = [[0.0, 0.0, 0.0], [-2.7133, -1.4798, -2.4066], [-1.1595, -2.1833, -1.9081], [1.0531, -0.5905, 0.304],
         [0.2221, 2.2859, 1.512], [-3.2085, 4.1511, 0.6072], [-5.2384, 2.7736, -1.3845], [-2.1499, 3.1731, 0.6318],
         [-0.3171, 1.0654, 0.8666], [-2.7992, -1.5464, -2.0959], [-1.8861, -2.3597, -2.0357], [0.9394, -0.5194, 0.6926],
         [-0.0619, 2.3275, 1.7395], [-3.2992, 4.1093, 0.9316], [-5.9513, 3.0826, -1.2096], [-2.9245, 3.2024, 0.614]]
U71_LOS = "0000011100001111"


def test_a_u_shaped_room_s_arm_visited_twice():
    """ushape seed 71's A1: the direct path only while the robot is in one arm, visited twice (runs of 3 and 4
    events), reflections 7-51 ms late elsewhere. No window of SUBSET consecutive events holds direct paths, the
    peel from the compromise track and the random subsets missed them, and no track was judged (9 reflections
    unflagged; the array 2.3 m off). The events nearest each other in space hold them: exactly the
    reflections are flagged."""
    los = np.array([int(x) for x in U71_LOS], bool)
    ev = nlos.late_arrivals(np.array(U71_A), np.array(U71_T), np.array(U71_S), C)
    assert np.array_equal(ev["nlos"], ~los)


def test_tracks_fitted_together_equal_each_fitted_alone():
    """Several arrays' range tracks searched in step, every round's fits stacked into one (fit_range_tracks,
    subsets of different lengths padded, robust and plain losses side by side), give each array the track its
    own search gives it alone: the same residuals to 1e-9 s and the same NLOS calls."""
    tracks, alone = [], []
    for seed, los in enumerate(["1100001111000011", "1111111111111111", "0000011100001111", "1111001111110011"]):
        t, s, direct, reflected = _track(np.random.default_rng(seed), n=16)
        a = np.where(np.array([int(x) for x in los], bool), direct, reflected)
        tracks.append(nlos.Track(a, t, s))
        alone.append(nlos.fit_range_track(a, t, s, C))
    together = nlos.fit_range_tracks(tracks, C)
    for (_, r1), (_, r2) in zip(alone, together):
        assert np.max(np.abs(r1 - r2)) < 1e-9
    many = nlos.late_arrivals_many([(tr.arrival, tr.t, tr.s, None) for tr in tracks], C)
    for tr, ev in zip(tracks, many):
        assert np.array_equal(ev["nlos"], nlos.late_arrivals(tr.arrival, tr.t, tr.s, C)["nlos"])


def test_an_arrival_with_a_weak_onset_and_no_plane_wave_is_flagged_reflection_only():
    """A reflection-only arrival whose detour is short stays on its range track (lshape seed 50, A4: 0.18 ms
    late, its DOA 103° off); its own waveform shows no direct path: a weak onset ("weak_direct") and mics that
    agree with no one plane wave ("doa_spread"). Both doubts make it "nlos" (quality halved, a warning); either
    alone, common in line of sight, does not; an arrival already "nlos" is not flagged twice."""
    from calib.frontend.extract import DOUBT_PENALTY, flag_no_direct

    flags = [["weak_direct"], ["doa_spread"], ["weak_direct", "mic_spread", "doa_spread"], [],
             ["doa_spread", "weak_direct", "nlos"]]
    results = {"A1": {"flags": [list(f) for f in flags], "quality": np.full(5, 0.8), "warnings": []}}
    flag_no_direct(results)
    r = results["A1"]
    assert [k for k, f in enumerate(r["flags"]) if "nlos" in f] == [2, 4]
    assert [f.count("nlos") for f in r["flags"]] == [0, 0, 1, 0, 1]
    np.testing.assert_allclose(r["quality"], [0.8, 0.8, 0.8 * DOUBT_PENALTY, 0.8, 0.8])
    assert len(r["warnings"]) == 1 and "1 of 5" in r["warnings"][0]


def _receding(drift, n, duration):
    """(arrival, t, s): a source receding from an array at the origin along x (2 → 38 m over ``duration`` s,
    weaving in y), the array's clock drifting by ``drift``, a quarter of the arrivals reflections 3–8 ms late,
    20 µs timing noise (seeded)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, duration, n)
    s = np.column_stack([np.linspace(2.0, 38.0, n), 1.0 + np.sin(np.linspace(0.0, 4.0, n)), np.full(n, 1.5)])
    rng_m = np.linalg.norm(s - np.array([0.0, 0.0, 0.2]), axis=1)
    late = np.where(rng.random(n) < 0.25, rng.uniform(3e-3, 8e-3, n), 0.0)
    return 0.4 + (1.0 + drift) * t + rng_m / C + late + rng.normal(0.0, 2e-5, n), t, s


@pytest.mark.parametrize("drift", [5e-5, -5e-5, 1.2e-3])
def test_a_range_trend_is_no_fast_clock(drift, monkeypatch):
    """A source crossing a 40 m hall away from an array (0.9 m/s of range rate): a straight line through the
    arrivals (the association's) slopes by δ + ṙ/c ≈ 2.7e-3, at the association's bound (1e-3) even for a
    crystal. The range track along the odometry (``late_arrivals_many``, the NLOS check's, a quarter of the
    arrivals reflections) recovers the simulated drift (within 2e-5; 5 % of a fast clock's), so ``fast_clocks`` drops a crystal (its
    |δ| ≤ CRYSTAL_DRIFT) without the estimator's look (``arrival_drift``: not called), while a true fast clock
    (1.2e-3) is named by its track alone (``TRACK_FAST``; no look either)."""
    from calib.estimator import clockmodel, screen
    from calib.pipeline import headerrate, setupcheck

    arrival, t, s = _receding(drift, 24, 40.0)
    assert np.polyfit(t, arrival, 1)[0] - 1.0 > 2e-3   # the association's line: clamped at its bound
    ev = nlos.late_arrivals_many([(arrival, t, s, None)], C)[0]
    assert abs(ev["drift"] - drift) < max(2e-5, 0.05 * abs(drift))   # (its weak drift prior pulls 1.2e-3 by 2 %)
    asked = []
    monkeypatch.setattr(setupcheck, "arrival_drift", lambda los, name: asked.append(name) or drift)
    monkeypatch.setattr(clockmodel, "impossible_jumps", lambda feats: [])
    monkeypatch.setattr(screen, "screen_rows", lambda feats: (None, {}))
    diag = {"arrays": {"A1": {"fs": 16000, "association": {"scale": 1.0 + 1e-3}, "track_drift": ev["drift"]}}}
    got = headerrate.fast_clocks({"arrays": [{"name": "A1"}]}, None, diag, 1e-3)
    fast = abs(drift) > headerrate.FAST_CLOCK
    assert list(got) == (["A1"] if fast else []) and asked == []   # (its track alone names a fast clock)


@pytest.mark.parametrize("drift", [-1e-3, 1.2e-3, 5e-5, -5e-5])
def test_a_fast_clock_the_association_hides_is_a_candidate(drift, monkeypatch):
    """A source receding 36 m over 100 s (ṙ/c ≈ 1e-3): a straight line through the arrivals (the association's)
    slopes by δ + ṙ/c, inside its bound for a clock 1e-3 slow (as paper-traj3 500 A2 at -1e-3: association
    -8.9e-4) and at it for one 1.2e-3 fast, and the arrivals give ``arrival_drift`` no chain (None: ushape 500
    A2 at +1e-3). The range track along the odometry (``late_arrivals_many``, a quarter of the arrivals
    reflections) recovers the simulated drift within 2e-5 (1e-5 for a crystal), and that alone makes
    ``fast_clocks`` name the fast ones for the first solve to decide; a crystal (±5e-5) is named nowhere, nor
    a clock that steps."""
    from calib.estimator import clockmodel, screen
    from calib.pipeline import headerrate, setupcheck

    arrival, t, s = _receding(drift, 40, 100.0)
    slope = np.polyfit(t, arrival, 1)[0] - 1.0   # the association's line: the range's trend, not the clock
    assert abs(slope - drift) > 9e-4 and (abs(slope) < headerrate.CLAMPED * 1e-3) == (drift == -1e-3)
    ev = nlos.late_arrivals_many([(arrival, t, s, None)], C)[0]
    assert abs(ev["drift"] - drift) < 2e-5
    monkeypatch.setattr(setupcheck, "arrival_drift", lambda los, name: None)
    monkeypatch.setattr(clockmodel, "impossible_jumps", lambda feats: [])
    monkeypatch.setattr(screen, "screen_rows", lambda feats: (None, {}))
    diag = {"arrays": {"A1": {"fs": 16000, "association": {"scale": 1.0 + np.clip(slope, -1e-3, 1e-3)},
                              "track_drift": ev["drift"]}}}
    got = headerrate.fast_clocks({"arrays": [{"name": "A1"}]}, None, diag, 1e-3)
    assert list(got) == (["A1"] if abs(drift) > headerrate.FAST_CLOCK else [])
    monkeypatch.setattr(clockmodel, "impossible_jumps", lambda feats: [{"array": "A1"}])   # a step is no rate
    assert headerrate.fast_clocks({"arrays": [{"name": "A1"}]}, None, diag, 1e-3) == {}
