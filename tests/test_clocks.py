"""Clocks as they really are (issue 28): the clock function and its inverse, the fault simulator, and the
estimator's per-array clock models (steps, drift terms, wrong nominal rates) against simulated truth."""
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib.clock import Clock, Step, Term, header_ratio
from calib.estimator import calibrate
from calib.estimator.clockmodel import Component, correct_features, extra
from calib.pipeline.formats.results import to_calibration
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate import clocks as ck
from calib.pipeline.simulate.featsim import simulate_features

from .sessions import NO_TARGET

SIGMA = 1e-5   # TDOA noise of the step tests (s): a good frontend's


# ----------------------------------------------------------------------------------------------- the clock
def test_linear_clock_and_inverse_by_hand():
    c = Clock(offset=0.5, drift=1e-3, t0=10.0)
    assert c.local(12.0) == pytest.approx(0.5 + 1.001 * 2.0, abs=1e-15)
    assert c.emitter(0.5 + 1.001 * 2.0) == pytest.approx(12.0, abs=1e-12)
    assert c.sample(12.0, 48000) == pytest.approx(48000 * 2.502, abs=1e-9)


def test_inserted_block_jumps_forward_and_its_gap_maps_to_the_step():
    c = Clock(offset=0.0, drift=0.0, t0=0.0, steps=(Step(5.0, 0.010),))
    np.testing.assert_allclose(c.local([4.0, 6.0]), [4.0, 6.010], atol=1e-15)
    assert c.emitter(5.005) == pytest.approx(5.0, abs=1e-12)     # inside the inserted samples: the step's time
    assert c.emitter(6.010) == pytest.approx(6.0, abs=1e-12)


def test_dropped_block_stands_still_then_goes_on_behind():
    c = Clock(offset=1.0, drift=0.0, t0=0.0, steps=(Step(5.0, -0.020),))
    # the reading stands at 6.0 until the clock has run 20 ms on, then goes on 20 ms behind
    np.testing.assert_allclose(c.local([4.0, 5.0, 5.01, 5.02, 6.0]), [5.0, 6.0, 6.0, 6.0, 6.98], atol=1e-12)
    assert c.emitter(6.0) == pytest.approx(5.0, abs=1e-12)       # the flat's start
    assert c.emitter(6.98) == pytest.approx(6.0, abs=1e-12)
    assert np.all(np.diff(c.local(np.linspace(0, 10, 10001))) >= 0)


def test_drift_terms_by_hand():
    A, T = 3e-6, 60.0
    warm = Clock(drift=1e-5, terms=(Term("exp", {"amplitude": A, "time_constant": T}),))
    u = 120.0
    assert warm.local(u) == pytest.approx((1 + 1e-5) * u + A * T * (1 - np.exp(-u / T)), abs=1e-13)
    assert warm.rate(u) == pytest.approx(1 + 1e-5 + A * np.exp(-u / T), abs=1e-9)
    quad = Clock(terms=(Term("quadratic", {"slope": 2e-8}),))
    assert quad.extra(100.0) == pytest.approx(0.5 * 2e-8 * 100.0 ** 2, abs=1e-12)   # (extra: L − linear part, rounding ~1e-14)
    hinge = Clock(terms=(Term("hinge", {"time": 30.0, "change": 4e-6}),))
    np.testing.assert_allclose(hinge.extra([10.0, 50.0]), [0.0, 4e-6 * 20.0], atol=1e-12)
    table = Clock(terms=(Term("table", {"knots": [0.0, 1.0, 2.0], "values": [0.0, 1e-6, 4e-6]}),))
    assert table.extra(1.5) == pytest.approx(2.5e-6, abs=1e-12)
    for c in (warm, quad, hinge, table):
        t = np.array([3.0, 77.0, 140.0])
        np.testing.assert_allclose(c.emitter(c.local(t)), t, atol=1e-9)
        assert Clock.from_dict(c.to_dict()).local(t) == pytest.approx(c.local(t), abs=1e-15)


def test_common_rate_ratios_are_named():
    assert header_ratio(44100 / 48000 * (1 + 3e-5), 1e-4) == (48000, 44100)
    assert header_ratio(48000 / 16000, 1e-4) == (16000, 48000)
    assert header_ratio(1.01, 1e-4) is None


def test_fault_clock_draws_steps_between_events_and_keeps_the_scene():
    t = np.array([0.0, 5.0, 11.0, 20.0])
    c = ck.fault_clock(0.01, 2e-5, {"steps": [{"size": -0.005}], "rate": {"header": 48000, "actual": 44100}},
                       event_times=t, rng=np.random.default_rng(1))
    assert c.drift == pytest.approx(44100 / 48000 * (1 + 2e-5) - 1, abs=1e-15)
    (s,) = c.steps
    assert s.size == -0.005 and any(s.time == 0.5 * (a + b) for a, b in zip(t[:-1], t[1:]))
    with pytest.raises(ValueError, match="unknown clock"):
        ck.resolve({"stepz": []})
    f0, t0 = simulate_features(3, seed=4)
    f1, t1 = simulate_features(3, seed=4, clocks={"A2": "insert"})
    np.testing.assert_array_equal(t0["sources"].to_numpy(), t1["sources"].to_numpy())
    assert "clocks" in t1 and t1["clocks"]["A2"]["steps"][0]["size"] == 0.005


# ----------------------------------------------------------------------------------------------- estimator
def _steps(cal, name):
    return cal["report"]["clock"]["arrays"][name]["steps"]


def _interval(truth_clock, features):
    """(event before, event after) of a true step."""
    t = features["events"]["t_emit"].to_numpy() - features["events"]["t_emit"].iloc[0]
    e = features["events"]["event"].to_numpy()
    s = truth_clock["steps"][0]["time"]
    return int(e[t < s].max()), int(e[t > s].min())


@pytest.mark.parametrize("seed,size", [(1, -0.020), (2, 0.0005)])
def test_a_step_is_found_in_its_interval_with_its_size(seed, size):
    f, truth = simulate_features(3, SIGMA, seed=seed, clocks={"A3": {"steps": [{"size": size}]}})
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, "A3")
    assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"]["A3"], f)
    assert abs(s["size"] - size) < 3 * s["std"]
    assert s["kind"] == ("dropped" if size < 0 else "inserted")
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A4", "A5"))
    assert cal["report"]["unreliable_arrays"] == []
    clean = evaluate(calibrate(simulate_features(3, SIGMA, seed=seed)[0], clock_model="auto"), simulate_features(3, SIGMA, seed=seed)[1])
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean["position_rmse_m"]
    # the calibration's clock follows the model: local times at the events against the true clock
    f["meta"]["reference_detections_s"] = {str(e): 0.0 for e in f["events"]["event"]}
    c = to_calibration(cal, f)
    tt = f["events"]["t_emit"].to_numpy()
    true = Clock.from_dict(truth["clocks"]["A3"])
    got = c.to_local_time("A3", tt)
    err = (got - got[0]) - (true.local(tt - tt[0]) - true.local(0.0))
    assert np.max(np.abs(err)) < 1e-4
    np.testing.assert_allclose(c.to_emitter_time("A3", got), tt, atol=1e-9)


def _session(seed, n=24):
    """Stops of a random walk in a room-sized box (the robot stops for each chirp)."""
    rng = np.random.default_rng([seed, 28])
    walk = np.cumsum(rng.normal(0, 0.8, (n, 3)) * [1, 1, 0.2], axis=0) + [3.0, 2.5, 1.0]
    return np.clip(walk, [0.2, 0.2, 0.3], [5.8, 4.8, 1.7])


def test_a_chirp_lost_in_a_dropped_block_leaves_the_step_and_the_others_alone():
    # a 50 ms block dropped between two events 80 ms apart: the later chirp falls into the lost samples (its
    # arrival is the block's start), rows hundreds of σ off that the solve screens out; they must neither make
    # steps of the other arrays nor fail the true step (a 36-stop walk of the clock benchmark's kind)
    rng = np.random.default_rng([9, 2800])
    stops = np.clip(np.cumsum(rng.normal(0, 0.8, (36, 3)) * [1, 1, 0.2], axis=0) + [3.0, 2.5, 1.0],
                    [0.2, 0.2, 0.3], [5.8, 4.8, 1.7])
    f0, _ = simulate_features(stops, SIGMA, seed=9, max_interval=10.0)
    f, truth = simulate_features(stops, SIGMA, seed=9, max_interval=10.0, clocks={"A3": {"steps": [{"size": -0.05}]}})
    t = f["events"]["t_emit"].to_numpy() - f["events"]["t_emit"].iloc[0]
    k = _interval(truth["clocks"]["A3"], f)[0]
    assert t[k + 1] - t[k] < 0.1   # (the scene has the property under test)
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, "A3")
    assert (s["after_event"], s["before_event"]) == (k, k + 1) and abs(s["size"] + 0.05) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A4", "A5"))
    assert not cal["report"]["clock"]["emitter"]["steps"]
    # the lost chirp's arrival is modelled as that one arrival's error (not a drift term), at event k + 1, off by
    # its recorded arrival against the clock after the step (truth: its TDOA-M against the fault-free one's)
    a3 = cal["report"]["clock"]["arrays"]["A3"]
    assert not a3["drift_terms"]
    (arr,) = a3["arrivals"]
    m = f["tdoa_m"][(f["tdoa_m"]["array"] == "A3") & (f["tdoa_m"]["event"] == k + 1)]["tdoa"].iloc[0]
    m0 = f0["tdoa_m"][(f0["tdoa_m"]["array"] == "A3") & (f0["tdoa_m"]["event"] == k + 1)]["tdoa"].iloc[0]
    assert arr["event"] == k + 1 and abs(arr["size"] - (m - m0 + 0.05)) < 1e-4
    clean = evaluate(calibrate(f0), truth)["position_rmse_m"]
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002


def _walk36(seed):
    """The clock benchmark's 3-minute session: 36 stops of a random walk (benchmarks/bench_clocks.py ``session``)."""
    rng = np.random.default_rng([seed, 2800])
    return np.clip(np.cumsum(rng.normal(0, 0.8, (36, 3)) * [1, 1, 0.2], axis=0) + [3.0, 2.5, 1.0],
                   [0.2, 0.2, 0.3], [5.8, 4.8, 1.7])



def _lost_chirp_seeded(size):
    """(features, the seeded models, their solve) of the clock benchmark's session whose
    A3 has its arrival at event k mis-detected 5 ms early and, if ``size``, a step of that size just before k;
    seeded as the jumps seed a lost chirp (:func:`clockmodel._lost_arrivals`): a step next to k (size 0) and
    the arrival at k."""
    from calib.estimator.calibrate import calibrate_features

    seed, k, name = 3104, 12, "A3"
    sim = dict(seed=seed, max_interval=10.0)
    f, _ = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, **sim)
    t = f["events"]["t_emit"].to_numpy() - f["events"]["t_emit"].iloc[0]
    if size:
        f = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, **sim,
                              clocks={name: {"steps": [{"size": size, "time": 0.5 * (t[k - 1] + t[k])}]}})[0]
    g = ck.delay_arrivals(f, name, {int(f["events"]["event"].iloc[k]): -5e-3})
    models = {name: [Component("step", 0.5 * (t[k - 1] + t[k]), 0.0), Component("arrival", float(t[k]), -5e-3)]}
    return g, models, calibrate_features(correct_features(g, models))


def test_a_lost_arrival_goes_with_its_step():
    """An "arrival" term (a chirp lost in a dropped block, stamped at its edge) stands only beside its step. On a
    session whose clocks are clean and whose one arrival at k is mis-detected, seeded with a step next to k and
    that arrival: the step has no evidence and is removed, and the arrival with it (alone it takes A3's rows at k
    out of the fit unjudged; the robust solve screens that one outlier: featsim seed 6 of test_motion_noise)."""
    from calib.estimator import clockmodel as cm
    from calib.estimator.calibrate import calibrate_features

    g, models, res = _lost_chirp_seeded(0.0)
    _, kept, _, _ = cm._refine_and_resolve(calibrate_features, g, res, models, {})
    assert kept == {}


@pytest.mark.slow
def test_a_lost_arrival_beside_a_true_step_stays_and_only_widens_the_stds():
    """The contrast: the same lost arrival beside a true 20 ms drop just before it: the step is kept, sized within
    3σ, the arrival too (5 ms early), and the components widen the solve's own (honest) σ, never narrow them."""
    from calib.estimator import clockmodel as cm
    from calib.estimator.calibrate import calibrate_features

    g, models, res = _lost_chirp_seeded(-0.02)
    out, kept, _, _ = cm._refine_and_resolve(calibrate_features, g, res, models, {}, calibrate_features(g))
    assert sorted(c.kind for c in kept["A3"]) == ["arrival", "step"] and list(kept) == ["A3"]
    (st,) = [c for c in kept["A3"] if c.kind == "step"]
    assert abs(st.value + 0.02) < 3 * st.std
    (a,) = [c for c in kept["A3"] if c.kind == "arrival"]
    assert abs(a.value + 5e-3) < 3 * a.std + 1e-4
    cols = ["x_std", "y_std", "z_std"]
    own = calibrate_features(correct_features(g, kept))["arrays"][cols].to_numpy(float)   # (the components held)
    widened = out["arrays"][cols].to_numpy(float)
    assert np.all(widened[np.isfinite(own)] >= own[np.isfinite(own)] * (1 - 1e-9))


def test_a_small_insert_whose_evidence_is_mostly_its_interval_s_tdoa_s_is_found_not_a_hinge():
    """A 0.1 ms insert (10 σ) whose later arrivals' level the sources and the linear clock mostly absorb: its
    evidence is mostly the TDOA-S of its interval, which its persistence's leave-out takes (χ² 61, 11 left), while
    a hinge's is spread (35, 15 left). Ranked by what the leave-out leaves, the hinge was taken and the step then
    fitted half; ranked by the evidence once both pass, the step is found in its interval, sized within 3σ, and
    nothing else is modelled."""
    seed, name = 3103, "A4"
    f, truth = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, seed=seed, max_interval=10.0,
                                 clocks={name: {"steps": [{"size": 1e-4}]}})
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, name)
    assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"][name], f)
    assert abs(s["size"] - 1e-4) < 3 * s["std"]
    rep = cal["report"]["clock"]
    assert all(not e["steps"] and not e["drift_terms"] for a, e in rep["arrays"].items() if a != name)
    assert not rep["arrays"][name]["drift_terms"] and not rep["emitter"]["steps"] and not rep["emitter"]["drift_terms"]
    assert cal["report"]["unreliable_arrays"] == []


def test_a_step_whose_neighbouring_interval_fits_as_well_names_both():
    """The reference's 0.1 ms drop between events 6 and 7 of bench_clocks' seed 517: the scan's χ² is 31.0 there
    and 32.8 between 7 and 8 (the arrivals of event 7 are all that differ, and its source's position absorbs part
    of them), so the step is modelled one interval late. The report says that the data cannot place it: a finding
    names the true interval as the modelled step's equal (before: the late interval alone, as if certain)."""
    seed, name = 517, "A1"
    f, truth = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, seed=seed, max_interval=10.0,
                                 clocks={name: {"steps": [{"size": -1e-4}]}})
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, name)
    after, before = _interval(truth["clocks"][name], f)
    where = f"between events {after} and {before}"
    if (s["after_event"], s["before_event"]) != (after, before):
        assert any(where in x and "cannot tell in which interval" in x for x in cal["report"]["clock"]["findings"])
    assert abs(s["size"] + 1e-4) < 3 * s["std"]


def test_two_late_arrivals_of_one_array_make_no_clock_term_on_it_or_through_the_sources():
    """The contrast: one array's arrivals at two consecutive stops late by 80 and 60 µs (8 and 6 σ: a reflector
    near those stops; its step at their edge scores χ² 44, well above the penalty) are no clock term, neither its
    nor another array's whose arrivals those two pull through the shared sources (a test of the persistence: free
    late-only arrivals of the array under test kept the pulled array's 0.065 ms false step)."""
    seed, k = 3101, 8
    f, _ = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, seed=seed, max_interval=10.0)
    ev = f["events"]["event"].to_numpy()
    g = ck.delay_arrivals(f, "A3", {int(ev[k]): 8e-5, int(ev[k + 1]): 6e-5})
    assert not calibrate(g, clock_model="auto")["report"]["clock"]["findings"]


@pytest.mark.parametrize("seed,name,interval,size", [(11, "A3", 0, -0.002), (12, "A3", 1, 0.0004),
                                                     (13, "A3", -1, 0.003), (14, "A2", -2, -0.0003),
                                                     (15, "A1", 0, 0.001)])
def test_a_step_next_to_a_session_s_start_or_end_is_found(seed, name, interval, size):
    """A step with one or two events on one side (the first or second interval, the last or the one before it;
    the reference's too) shows in those events' arrivals alone, shifted alike, their DOAs still on the direct
    path: found in its interval, sized within 3σ, nothing else modelled."""
    stops = _session(seed)
    f0, _ = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0)
    t = f0["events"]["t_emit"].to_numpy() - f0["events"]["t_emit"].iloc[0]
    k = interval % (len(t) - 1)
    f, truth = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0,
                                 clocks={name: {"steps": [{"size": size, "time": 0.5 * (t[k] + t[k + 1])}]}})
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, name)
    assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"][name], f) == (k, k + 1)
    assert abs(s["size"] - size) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A3", "A4", "A5") if a != name)
    assert not cal["report"]["clock"]["emitter"]["steps"] and not cal["report"]["clock"]["emitter"]["drift_terms"]


def _turned(features, array, event, angle):
    """A copy of ``features`` with ``array``'s DOA at ``event`` turned by ``angle`` (rad): an echo's direction."""
    doa = features["doa"].copy()
    at = ((doa["array"] == array) & (doa["event"] == event)).to_numpy()
    u = doa.loc[at, ["ux", "uy", "uz"]].to_numpy(float)
    w = np.cross(u, [0.0, 0.0, 1.0])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    doa.loc[at, ["ux", "uy", "uz"]] = np.cos(angle) * u + np.sin(angle) * w
    return {**features, "doa": doa}


@pytest.mark.parametrize("seed,first", [(16, True), (17, False)])
def test_an_end_event_s_echo_is_no_clock_step_but_the_same_shift_on_the_direct_path_is(seed, first):
    """The first (or last) event's arrival at A3 late by 0.6 ms: in the TDOAs exactly a step next to that end.
    With its DOA turned 40° (the chirp detected on an echo, from an image source) no clock term is modelled;
    with its DOA on the direct path (every mic shifted alike: a clock) it is the step there."""
    f, truth = simulate_features(_session(seed), SIGMA, seed=seed, max_interval=10.0)
    ev = f["events"]["event"].to_numpy()
    j = int(ev[0] if first else ev[-1])
    late = ck.delay_arrivals(f, "A3", {j: 6e-4})
    echo = calibrate(_turned(late, "A3", j, np.radians(40.0)), clock_model="auto")
    assert not echo["report"]["clock"]["findings"]
    assert evaluate(echo, truth)["position_rmse_m"] < 1.5 * evaluate(calibrate(f), truth)["position_rmse_m"] + 0.002
    (s,) = _steps(calibrate(late, clock_model="auto"), "A3")
    assert (s["after_event"], s["before_event"]) == ((ev[0], ev[1]) if first else (ev[-2], ev[-1]))
    assert abs(s["size"] - (-6e-4 if first else 6e-4)) < 3 * s["std"]


def _one_arrival_noted(cal, array, event):
    """Whether the detection rounds say ``array``'s doubted arrival at ``event`` alone was not modelled."""
    return any(f"{array}: event {event} alone" in r.get("rejected", "") for rnd in cal["report"]["clock"]["detection"]
               for r in rnd)


@pytest.mark.parametrize("seed,first,lag", [(18, True, 2e-3), (19, False, 2e-3), (19, False, 0.0235)])
def test_a_doubted_end_event_alone_is_no_clock_step_whatever_its_bearing(seed, first, lag):
    """The first (or last) event's arrival at A3 late by ``lag`` and doubted by the frontend (flag nlos: the solve
    takes it out, so no scan sees it). A clock step next to that end and a reflection-only arrival that late
    (the warehouse check session's false 23.5 ms step: its last event, its DOA passing the direct-path test)
    give these same features: every row of the one arrival shifted by one amount, its DOA on the direct path or
    near it. One arrival cannot tell them apart, and a step there changes nothing else: no clock term is
    modelled (main readmitted a step whenever the DOA was the direct path's), the arrival stays out and the
    detection rounds say why; with its DOA turned 40° (an image source's) the same. The session calibrates
    within 1.5× of the same session without the late arrival."""
    f, truth = simulate_features(_session(seed), SIGMA, seed=seed, max_interval=10.0)
    ev = f["events"]["event"].to_numpy()
    j = int(ev[0] if first else ev[-1])
    late = ck.doubt_arrivals(ck.delay_arrivals(f, "A3", {j: lag}), "A3", [j])
    clean = evaluate(calibrate(f), truth)["position_rmse_m"]
    for g in (late, _turned(late, "A3", j, np.radians(40.0))):
        cal = calibrate(g, clock_model="auto")
        assert all(not a["steps"] and not a["drift_terms"] for a in cal["report"]["clock"]["arrays"].values())
        assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002
    assert _one_arrival_noted(calibrate(late, clock_model="auto"), "A3", j)


def test_a_warm_up_component_is_the_clock_s_exponential_term():
    """The warm-up candidate (drift excess c relaxing as exp(−u/T)) adds c T (1 − exp(−u/T)) to the local time,
    as the simulator's warm-up (calib.clock's ``exp`` term), by hand at u = T and in the limit u ≫ T."""
    from calib.estimator.clockmodel import as_clock

    c = Component("warmup", 50.0, 3e-6)
    assert c.basis(50.0) * c.value == pytest.approx(3e-6 * 50.0 * (1 - np.exp(-1.0)), rel=1e-12)
    assert c.basis(5000.0) == pytest.approx(50.0, rel=1e-12)
    u = np.linspace(0.0, 300.0, 7)
    clk = as_clock([c], offset=0.1, drift=2e-5)
    np.testing.assert_allclose(clk.extra(u), extra([c], u), atol=1e-15)
    assert c.plausible(180.0) and not c.with_value(3e-5).plausible(180.0)


@pytest.mark.parametrize("seed", [2, 3])
def test_a_warm_up_drift_is_modelled_and_calibrates_as_the_constant_drift_session(seed):
    """One array's drift 3 ppm fast at the start, relaxing over a minute (a board warming up), on a 16-stop walk
    with a good frontend's 1 µs TDOAs: a drift term on that array and nothing else; the session calibrates
    within 1.5× of the same session without the warm-up (the linear clock is several times worse)."""
    stops = _session(seed, 16)
    f0, truth0 = simulate_features(stops, 1e-6, seed=seed, max_interval=12.0)
    f, truth = simulate_features(stops, 1e-6, seed=seed, max_interval=12.0,
                                 clocks={"A3": {"warmup": {"amplitude": 3e-6, "time_constant": 60.0}}})
    cal = calibrate(f, clock_model="auto")
    arrays = cal["report"]["clock"]["arrays"]
    assert arrays["A3"]["drift_terms"] and not arrays["A3"]["steps"]
    assert all(not a["steps"] and not a["drift_terms"] for n, a in arrays.items() if n != "A3")
    clean = evaluate(calibrate(f0), truth0)["position_rmse_m"]
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002
    # calibration.json's clock follows the model (its drift term read back through calib.clock)
    f["meta"]["reference_detections_s"] = {str(e): 0.0 for e in f["events"]["event"]}
    c = to_calibration(cal, f)
    tt = f["events"]["t_emit"].to_numpy()
    got = c.to_local_time("A3", tt)
    true = Clock.from_dict(truth["clocks"]["A3"])
    assert np.max(np.abs((got - got[0]) - (true.local(tt - tt[0]) - true.local(0.0)))) < 2e-5
    np.testing.assert_allclose(c.to_emitter_time("A3", got), tt, atol=1e-9)


@pytest.mark.parametrize("seed,k", [(2, 0), (3, 4), (4, 9)])
def test_a_drop_whose_earlier_arrivals_are_doubted_beside_a_warm_up_is_modelled(seed, k):
    """A2 drops 20 ms between events k and k + 1 while A3 warms up (3 ppm relaxing over a minute), 16 stops with
    1 µs TDOAs; the frontend's range track reads A2's arrivals before the drop as late (flag nlos: rendered lab
    sessions, ``clocks.doubt_arrivals``). One doubted event (k = 0, rendered lab seed 28): its rows, 20 ms off,
    must not fail A3's warm-up; one arrival cannot tell the step from a reflection (its DOA on the direct path
    or not), so no step is modelled and its rows stay out, said in the detection rounds; a doubted block of 5 or
    of 10 of the 16 events (most of A2's: it is then refitted alone to them) is one clock step, readmitted. The
    session calibrates within 1.5× of the same one without faults."""
    stops = _session(seed, 16)
    f0, truth0 = simulate_features(stops, 1e-6, seed=seed, max_interval=12.0)
    t = f0["events"]["t_emit"].to_numpy() - f0["events"]["t_emit"].iloc[0]
    clocks = {"A2": {"steps": [{"time": 0.5 * (t[k] + t[k + 1]), "size": -0.02}]},
              "A3": {"warmup": {"amplitude": 3e-6, "time_constant": 60.0}}}
    f, truth = simulate_features(stops, 1e-6, seed=seed, max_interval=12.0, clocks=clocks)
    f = ck.doubt_arrivals(f, "A2", range(k + 1))
    cal = calibrate(f, clock_model="auto")
    arrays = cal["report"]["clock"]["arrays"]
    assert arrays["A3"]["drift_terms"] and not arrays["A3"]["steps"]
    if k == 0:
        assert not arrays["A2"]["steps"] and not arrays["A2"]["drift_terms"] and _one_arrival_noted(cal, "A2", 0)
    else:
        (s,) = arrays["A2"]["steps"]
        assert (s["after_event"], s["before_event"]) == (k, k + 1) and abs(s["size"] + 0.02) < 3 * s["std"]
    clean = evaluate(calibrate(f0), truth0)["position_rmse_m"]
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002


@pytest.mark.parametrize("seed", [530, 534])
def test_a_step_at_the_end_of_a_doubted_run_inside_the_session_is_placed_by_the_doubted_rows(seed):
    """A3 drops 508 µs (an ESP board) between events 14 and 15 of 30, and the frontend doubts its six arrivals
    before the drop (flag nlos: its range track reads them as late), a run inside the session (no readmitted
    block). The screen takes them out, so the undoubted rows fit a step anywhere in events 8-15 alike; the
    doubted rows, on the old level, say where. Without them the per-array scan proposed the run's first
    intervals, each failed its structure test on those rows, and A3 ended unreliable (refitted alone)."""
    stops = _session(seed, 30)
    f0, truth0 = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0)
    t = f0["events"]["t_emit"].to_numpy() - f0["events"]["t_emit"].iloc[0]
    clocks = {"A3": {"steps": [{"time": 0.5 * (t[14] + t[15]), "size": -5.08e-4}]}}
    f, truth = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0, clocks=clocks)
    cal = calibrate(ck.doubt_arrivals(f, "A3", range(9, 15)), clock_model="auto")
    (s,) = cal["report"]["clock"]["arrays"]["A3"]["steps"]
    assert (s["after_event"], s["before_event"]) == (14, 15) and abs(s["size"] + 5.08e-4) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A4", "A5"))
    assert cal["report"]["unreliable_arrays"] == []
    clean = evaluate(calibrate(f0), truth0)["position_rmse_m"]
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002


@pytest.mark.parametrize("seed", [531, 532])
def test_a_step_beside_reflection_only_arrivals_is_found_and_the_array_kept(seed):
    """A3 inserts 5 ms between events 10 and 11 of 24, and at 8 events (2-5, 15-18) its line of sight is blocked:
    its arrivals are reflections 15-20 ms late, a different excess path at each (the frontend doubts them, flag
    nlos), as an occluded office array's. Under Huber's weight those rows read as 100-200σ misfits of every row
    group of the step's structure test, pulled the per-array scan's pose and scale (0.3-2 ms) and a DOA test
    bent to their image sources: the step was never modelled and A3 ended unreliable (refitted alone), 9-62 cm.
    The reflections testify nothing about the clock: found in its interval within 3σ, the array as without
    the step."""
    stops = _session(seed, 24)
    f0, truth0 = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0)
    t = f0["events"]["t_emit"].to_numpy() - f0["events"]["t_emit"].iloc[0]
    late = [2, 3, 4, 5, 15, 16, 17, 18]
    delays = dict(zip(late, np.random.default_rng([seed, 53]).uniform(0.015, 0.020, len(late))))
    clocks = {"A3": {"steps": [{"time": 0.5 * (t[10] + t[11]), "size": 0.005}]}}
    f, truth = simulate_features(stops, SIGMA, seed=seed, max_interval=10.0, clocks=clocks)
    cal = calibrate(ck.doubt_arrivals(ck.delay_arrivals(f, "A3", delays), "A3", late), clock_model="auto")
    (s,) = _steps(cal, "A3")
    assert (s["after_event"], s["before_event"]) == (10, 11) and abs(s["size"] - 0.005) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A4", "A5"))
    assert cal["report"]["unreliable_arrays"] == []
    twin = calibrate(ck.doubt_arrivals(ck.delay_arrivals(f0, "A3", delays), "A3", late))
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * evaluate(twin, truth0)["position_rmse_m"] + 0.002


def test_a_large_reference_step_beside_another_arrays_step_is_the_references():
    # a 7 ms reference step bends the fit: its scanned size is off by tens of σ, and the other array's
    # unmodelled step shows in its structure test's row groups; it is resized and set aside, not banned
    f, truth = simulate_features(_session(5), SIGMA, seed=5, max_interval=10.0,
                                 clocks={"A1": {"steps": [{"size": -0.007}]}, "A3": {"steps": [{"size": 0.0004}]}})
    cal = calibrate(f, clock_model="auto")
    for name in ("A1", "A3"):
        (s,) = _steps(cal, name)
        true = truth["clocks"][name]["steps"][0]["size"]
        assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"][name], f)
        assert abs(s["size"] - true) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A2", "A4", "A5"))
    assert not cal["report"]["clock"]["emitter"]["steps"]


def _bench_steps(seed, steps):
    """The clock benchmark's session (seed) with a step of each array {name: (k, size)} between events k and k+1."""
    sim = dict(seed=seed, max_interval=10.0)
    f, _ = simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, **sim)
    t = f["events"]["t_emit"].to_numpy() - f["events"]["t_emit"].iloc[0]
    clocks = {n: {"steps": [{"size": size, "time": 0.5 * (t[k] + t[k + 1])}]} for n, (k, size) in steps.items()}
    return simulate_features(_walk36(seed), SIGMA, 5.0, 0.03, **sim, clocks=clocks)


@pytest.mark.parametrize("seed,steps", [
    # a 6.1 ms reference step fails its structure test alone while A5's 2.6 ms step is unmodelled (and A5's the
    # reference's): taken together (clockmodel._paired); one at a time, the reference's was taken an interval off
    (509, {"A5": (26, -0.0026), "A1": (29, 0.0061)}),
    # a 0.38 ms reference step three events before the end, next to A4's 2.2 ms: the emitter's step at its
    # interval has as much evidence and a larger margin after its leave-out (by arrays, not events); solved,
    # the reference's fits better (clockmodel._contenders)
    (531, {"A4": (33, -0.0022), "A1": (32, 0.00038)})])
def test_two_steps_on_two_arrays_are_each_found_in_their_interval(seed, steps):
    f, truth = _bench_steps(seed, steps)
    cal = calibrate(f, clock_model="auto")
    for name, (k, size) in steps.items():
        (s,) = _steps(cal, name)
        assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"][name], f) == (k, k + 1)
        assert abs(s["size"] - size) < 3 * s["std"]
    assert all(not _steps(cal, a) for a in ("A1", "A2", "A3", "A4", "A5") if a not in steps)
    assert not cal["report"]["clock"]["emitter"]["steps"]


def test_an_array_isolated_for_its_unmodelled_step_is_readmitted_with_it():
    """bench_clocks seed 529: A5's 0.91 ms drop bends the linear fit (A5 14.5 cm off) and hides from both scans
    (the per-array fit holds the sources where they absorbed it; A5, named for its outliers, is out of the joint
    scan). The leave-one-array-out test isolates A5; without its rows its step shows (492 χ²), and A5 comes back
    with it (before: the step was rejected because the isolated A5 was unreliable, and A5 was refitted alone)."""
    from calib.pipeline.report.evaluate import array_errors, array_table

    f, truth = _bench_steps(529, {"A5": (21, -0.00091)})
    cal = calibrate(f, clock_model="auto", **NO_TARGET)
    (s,) = _steps(cal, "A5")
    assert (s["after_event"], s["before_event"]) == (21, 22) and abs(s["size"] + 0.00091) < 3 * s["std"]
    assert cal["report"]["unreliable_arrays"] == [] and cal["report"]["verdict"]["status"] == "ok"
    f0, truth0 = _bench_steps(529, {})
    errors = [array_errors(array_table(c["arrays"]), array_table(t["arrays"]))["position_m"]
              for c, t in ((cal, truth), (calibrate(f0, clock_model="linear"), truth0))]
    assert np.all(np.asarray(errors[0]) < 1.5 * np.asarray(errors[1]) + 0.002)   # every array, A5 too


def test_an_array_isolated_by_request_keeps_its_step_in_its_own_fit():
    """An array solved without (``isolate``) is unreliable by construction, which says nothing of its clock terms:
    its step stays, and its pose refitted alone is as good as without the fault (before: the step was removed for
    the array being unreliable, and A3 refitted alone without it was 37 cm off)."""
    from calib.pipeline.report.evaluate import array_errors, array_table

    f, truth = _bench_steps(512, {"A3": (15, -0.005)})
    cal = calibrate(f, clock_model="auto", isolate=["A3"], **NO_TARGET)
    (s,) = _steps(cal, "A3")
    assert (s["after_event"], s["before_event"]) == (15, 16) and abs(s["size"] + 0.005) < 3 * s["std"]
    assert cal["report"]["unreliable_arrays"] == ["A3"]
    f0, truth0 = _bench_steps(512, {})

    def a3(c, t):
        e = array_errors(array_table(c["arrays"]), array_table(t["arrays"]))
        return dict(zip(e["array"], e["position_m"]))["A3"]
    assert a3(cal, truth) < 1.5 * a3(calibrate(f0, clock_model="linear", isolate=["A3"]), truth0) + 0.002


@pytest.mark.parametrize("seed,name,k,size,seen", [(525, "A4", 21, 1e-4, True), (525, "A4", 21, -1e-4, True),
                                                    (550, "A5", 27, 1e-4, False)])
def test_a_0_1_ms_step_is_found_where_the_data_hold_it_and_costs_little_where_they_do_not(seed, name, k, size, seen):
    # the clock benchmark's noise (10 µs TDOA, 3 cm odometry, 5°): a 0.1 ms step is 10 σ on its interval's TDOA-S
    # and on each later TDOA-M, but sources and poses can absorb it; its information λ = |P_J b|² (b its column,
    # J the fault-free fit's Jacobian, bench_clocks ``attainable``) is 202 at seed 525's A4 (21, 22), 3.1 at seed
    # 550's A5 (27, 28), below the scan's 22.3 (9 of 100 draws of bench_clocks drop_0.1ms, seeds 500-599, are)
    f, truth = _bench_steps(seed, {name: (k, size)})
    cal = calibrate(f, clock_model="auto")
    if seen:
        (s,) = _steps(cal, name)
        assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"][name], f) == (k, k + 1)
        assert abs(s["size"] - size) < 3 * s["std"]
    assert not cal["report"]["clock"]["findings"] if not seen else len(cal["report"]["clock"]["findings"]) == 1
    f0, truth0 = _bench_steps(seed, {})
    clean = evaluate(calibrate(f0, clock_model="linear"), truth0)["position_rmse_m"]
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean + 0.002


@pytest.mark.parametrize("seed", [0, 3, 5])
def test_clean_sessions_get_the_linear_clock(seed):
    f, _ = simulate_features(3, SIGMA, seed=seed)
    rep = calibrate(f, clock_model="auto")["report"]["clock"]
    assert rep["findings"] == []
    assert all(e["drift_model"] == "linear" and not e["steps"] for e in rep["arrays"].values())


@pytest.mark.parametrize("fault,header", [("rate44k", (48000, 44100)), ("rate1pct", None)])
def test_a_wrong_nominal_rate_is_named_and_the_others_unbent(fault, header):
    f, truth = simulate_features(3, SIGMA, seed=2, clocks={"A4": fault})
    cal = calibrate(f, clock_model="auto")
    nr = cal["report"]["clock"]["arrays"]["A4"]["nominal_rate"]
    assert nr is not None and nr["ratio"] == pytest.approx(1 + truth["arrays"].set_index("array").loc["A4", "drift"]
                                                           - truth["arrays"]["drift"].iloc[0], abs=2e-4)
    assert (nr["header_hz"], nr["actual_hz"]) == (header or (None, None))
    assert any("A4: wrong nominal sample rate" in r for r in cal["report"]["verdict"]["reasons"])
    assert all(e["nominal_rate"] is None for n, e in cal["report"]["clock"]["arrays"].items() if n != "A4")
    clean = evaluate(calibrate(simulate_features(3, SIGMA, seed=2)[0], clock_model="auto"), truth)
    assert evaluate(cal, truth)["position_rmse_m"] < 1.5 * clean["position_rmse_m"]


def test_the_reference_s_wrong_rate_is_its_own_and_a_scaled_schedule_is_the_time_base():
    f, _ = simulate_features(3, SIGMA, seed=2, clocks={"A1": "rate1pct"})
    rep = calibrate(f, clock_model="auto")["report"]["clock"]
    assert [n for n, e in rep["arrays"].items() if e["nominal_rate"]] == ["A1"]
    f, _ = simulate_features(3, SIGMA, seed=2)
    ev = f["events"].copy()
    ev["t_emit"] *= 1.02                       # the schedule, not the boards: every array 1/1.02 against it
    rep = calibrate({**f, "events": ev}, clock_model="auto")["report"]["clock"]
    assert not any(e["nominal_rate"] for e in rep["arrays"].values())
    assert any(x.startswith("time base") for x in rep["findings"])


def test_a_common_emission_step_is_the_emitters_not_every_arrays():
    f, _ = simulate_features(3, SIGMA, seed=6)
    ev = f["events"].copy()
    ev.loc[ev["event"] >= 5, "t_emit"] -= 0.001   # events.csv 1 ms early from event 5 on (as real set 01)
    cal = calibrate({**f, "events": ev}, clock_model="auto")
    rep = cal["report"]["clock"]
    assert all(not e["steps"] for e in rep["arrays"].values())
    (s,) = rep["emitter"]["steps"]
    assert (s["after_event"], s["before_event"]) == (4, 5) and abs(s["size"] - 0.001) < 3 * s["std"]


def test_delayed_arrivals_of_one_size_are_a_clock_step():
    """delay_arrivals (the NLOS contrast) with one delay from an event on is exactly a clock step there."""
    f, truth = simulate_features(3, SIGMA, seed=1, noise=False, clocks={"A3": {"steps": [{"size": 4e-4}]}})
    clean, _ = simulate_features(3, SIGMA, seed=1, noise=False)
    k = _interval(truth["clocks"]["A3"], f)[1]
    late = ck.delay_arrivals(clean, "A3", {j: 4e-4 for j in f["events"]["event"] if j >= k})
    for kind in ("tdoa_m", "tdoa_s"):
        np.testing.assert_allclose(late[kind]["tdoa"].to_numpy(), f[kind]["tdoa"].to_numpy(), atol=1e-12)


@pytest.mark.parametrize("seed,form", [(2, "tail"), (4, "block")])
def test_reflections_are_not_modelled_as_clock_steps(seed, form):
    """One array's arrivals late by a detour that changes from stop to stop (a blocked line of sight, from an
    event on to the end, or for a stretch): no clock term anywhere, and the array named as with the linear
    clock. The same array with one clock step of the delays' mean size is found (the contrast)."""
    f, truth = simulate_features(3, SIGMA, seed=seed)
    ev = f["events"]["event"].to_numpy()
    rng = np.random.default_rng(seed)
    k = len(ev) // 3
    span = ev[k:] if form == "tail" else ev[k:k + 6]
    late = {int(j): rng.uniform(3e-4, 1.2e-3) for j in span}
    g = ck.delay_arrivals(f, "A3", late)
    auto, linear = calibrate(g, clock_model="auto")["report"], calibrate(g, clock_model="linear")["report"]
    assert not auto["clock"]["findings"]
    assert "A3" in auto["verdict"]["flagged_arrays"] and auto["verdict"]["flagged_arrays"] == linear["verdict"]["flagged_arrays"]
    size = float(np.mean(list(late.values())))
    t = f["events"]["t_emit"].to_numpy()
    f, truth = simulate_features(3, SIGMA, seed=seed, clocks={"A3": {"steps": [{"size": size, "time": 0.5 * (t[k - 1] + t[k])}]}})
    (s,) = _steps(calibrate(f, clock_model="auto"), "A3")
    assert (s["after_event"], s["before_event"]) == (k - 1, k) and abs(s["size"] - size) < 3 * s["std"]


def test_rivals_the_data_cannot_tell_apart_are_named_while_the_chosen_one_is_kept():
    from calib.estimator.clockmodel import _ambiguities

    events, u = np.arange(4), np.array([0.0, 10.0, 20.0, 30.0])
    rounds = [[{"array": "A4", "margin_chi2": 30.0}], [{"ambiguous": [("A5", "step", 15.0, -9.3e-5),
                                                                      ("A4", "step", 15.0, 1.01e-4)]}]]
    (text,) = _ambiguities(rounds, {"A5": [Component("step", 15.0, -9.3e-5)]}, events, u)
    assert text.startswith("A5's step of -0.093 ms between events 1 and 2") and "A4's step of +0.101 ms" in text
    assert _ambiguities(rounds, {}, events, u) == []      # the chosen one was eliminated later: nothing to name


def test_one_component_proposed_by_both_scans_is_not_its_own_rival():
    """bench_clocks drop_and_warmup seed 502: A4 drops 0.72 ms between events 6 and 7 (A1, the reference, warms up
    2.3 ppm over a minute: too little of it outside the linear clock and the sources to be modelled). A4's scan
    and the joint scan both propose that step, sized 0.5 µs apart; solved, they fit alike — one model, which no
    finding may name as the data's ambiguity with itself."""
    clocks = {"A4": {"steps": [{"size": -0.0007227616346524744}]},
              "A1": {"warmup": {"amplitude": 2.3219592908953057e-06, "time_constant": 59.02129591716124}}}
    f, truth = simulate_features(_walk36(502), SIGMA, 5.0, 0.03, seed=502, max_interval=10.0, clocks=clocks)
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, "A4")
    assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"]["A4"], f) == (6, 7)
    assert abs(s["size"] - truth["clocks"]["A4"]["steps"][0]["size"]) < 3 * s["std"]
    for text in cal["report"]["clock"]["findings"]:   # (the clauses without their sizes: which component)
        if "the data cannot tell" in text:
            clauses = re.sub(r" of [+-]\d+\.\d+ ms", "", text.split(": the data cannot tell")[0])
            chosen, rivals = clauses.split(" (modelled) explains the data as well as ")
            assert chosen not in rivals.split(" or ")


def test_correct_features_takes_a_model_out_of_the_tdoas():
    f, truth = simulate_features(3, SIGMA, seed=1, noise=False, clocks={"A3": {"steps": [{"size": 0.004}]},
                                                                         "A1": {"steps": [{"size": -0.002}]}})
    clean, _ = simulate_features(3, SIGMA, seed=1, noise=False)
    models = {n: [Component("step", c["steps"][0]["time"], c["steps"][0]["size"])] for n, c in truth["clocks"].items()}
    g = correct_features(f, models)
    for kind in ("tdoa_m", "tdoa_s"):
        np.testing.assert_allclose(g[kind]["tdoa"].to_numpy(), clean[kind]["tdoa"].to_numpy(), atol=1e-12)
    assert extra(models["A3"], np.array([0.0, 1e3])).tolist() == [0.0, 0.004]


@pytest.mark.parametrize("noise, first_after", [(1.0, 6), (0.0, 6), (1.0, 10)])
def test_the_persistent_drop_is_the_step_s_chi2_refitted_without_each_run_of_events(noise, first_after):
    """persistent_drop's deletion formula against explicit refits: a linear model (5 columns, 12 events of 3
    rows) with a step from event ``first_after`` on, the step's χ² drop refitted with the rows of every one or
    two consecutive events removed; the smallest is what it returns. noise 0: the leave-out noncentrality
    (bench_clocks.attainable). A step two events from the end: the run of both its late events is not left out."""
    from calib.estimator.clockmodel import end_side, persistent_drop

    rng = np.random.default_rng(7)
    K, m = 12, 3
    A = rng.normal(size=(K * m, 5))
    ev = np.repeat(np.arange(K), m)
    b = (ev >= first_after).astype(float)
    y = A @ rng.normal(size=5) + 2.0 * b + noise * rng.normal(size=K * m)
    G = np.linalg.inv(A.T @ A)
    P = np.eye(K * m) - A @ G @ A.T
    groups = [np.flatnonzero(ev == e) for e in range(K)]
    side = end_side(np.arange(K, dtype=float), first_after - 0.5)

    def drop(keep):   # the χ² drop of the step refitted on the rows ``keep``
        rss = [float(np.sum((y[keep] - X @ np.linalg.lstsq(X, y[keep], rcond=None)[0]) ** 2))
               for X in (A[keep], np.column_stack([A[keep], b[keep]]))]
        return rss[0] - rss[1]

    runs = [range(k, k + w) for w in (1, 2) for k in range(K - w + 1)
            if side is None or not set(side) <= set(range(k, k + w))]
    want = min([drop(np.ones(K * m, bool))] + [drop(~np.isin(ev, list(run))) for run in runs])
    got = persistent_drop(lambda R: A[R] @ G @ A[R].T, P @ y, P @ b, groups, side=side)
    assert (side is not None) == (first_after == 10)
    assert got == pytest.approx(max(want, 0.0), rel=1e-8, abs=1e-9)


# ----------------------------------------------------------------------------------------------- the user's path
def test_estimate_clock_model_flag_and_evaluate_scores_the_clock(tmp_path):
    """`calib estimate` (its default clock model, auto) models A3's dropped block, `calib evaluate` scores it against
    truth/clocks.json (found, in its interval, size within 3σ; the local time right to a few σ), and the
    linear clock's calibration of the same features is scored as missing it."""
    import json

    from typer.testing import CliRunner

    from calib.cli.main import app
    from calib.pipeline.formats.io import write_features, write_truth

    f, truth = simulate_features(3, SIGMA, seed=1, clocks={"A3": {"steps": [{"size": -0.020}]}})
    write_features(tmp_path / "features", f)
    write_truth(tmp_path / "truth", truth, extra_files={"clocks.json": json.dumps(truth["clocks"])})
    scored = {}
    for model in ("auto", "linear"):   # (auto: the default, no flag)
        r = CliRunner().invoke(app, ["estimate", str(tmp_path / "features"), "-o", str(tmp_path / model), "-q"]
                               + (["--clock-model", model] if model != "auto" else []))
        assert r.exit_code in (0, 3), r.output
        r = CliRunner().invoke(app, ["evaluate", str(tmp_path / model), str(tmp_path / "truth"), "--json"])
        assert r.exit_code == 0, r.output
        scored[model] = json.loads(r.output)["clock"]
    got = scored["auto"]
    (a3,) = [a for a in got["per_array"] if a["array"] == "A3"]
    (s,) = a3["steps"]
    assert s["found"] and s["placed"] and s["size_error_sigma"] <= 3
    assert (s["after_event"], s["before_event"]) == _interval(truth["clocks"]["A3"], f)
    assert (got["steps_found"], got["false_steps"], got["false_drift_models"]) == (1, 0, 0)
    assert a3["local_time_max_error_s"] < 1e-4
    miss = scored["linear"]
    assert (miss["steps_found"], miss["steps_placed"]) == (0, 0)
    # unmodelled, the 20 ms step leaves about half of it in A3's local time after a linear fit
    assert miss["local_time_max_error_s"] > 5e-3
    r = CliRunner().invoke(app, ["evaluate", str(tmp_path / "auto"), str(tmp_path / "truth")], terminal_width=200)
    assert "1/1 true steps found" in r.output
    # a clocks.json without the emission times (older folders): found and sized, the interval not judged
    old = {n: {k: v for k, v in c.items() if k != "event_times"} for n, c in truth["clocks"].items()}
    (tmp_path / "truth" / "clocks.json").write_text(json.dumps(old))
    r = CliRunner().invoke(app, ["evaluate", str(tmp_path / "auto"), str(tmp_path / "truth"), "--json"])
    (s,) = [a for a in json.loads(r.output)["clock"]["per_array"] if a["array"] == "A3"][0]["steps"]
    assert s["found"] and s["placed"] is None and s["size_error_sigma"] <= 3
    r = CliRunner().invoke(app, ["estimate", str(tmp_path / "features"), "-o", str(tmp_path / "x"), "--clock-model", "steps"])
    assert r.exit_code == 2 and "clock_model" in r.output


@pytest.mark.slow
def test_calib_run_on_a_rendered_session_with_a_dropped_block(tmp_path):
    """`calib simulate --clock` renders the drop into A3's WAV; `calib run` finds it in its interval and the
    calibration matches the fault-free session's."""
    import json
    import subprocess
    import sys

    from calib.pipeline.formats.io import read_truth

    def calib(*args):
        return subprocess.run([sys.executable, "-m", "calib", *args], capture_output=True, text=True, timeout=900)

    errs = {}
    for name, extra in (("clean", []), ("drop", ["--clock", "A3={steps=[{size=-0.02}]}"])):
        sim = calib("simulate", "-o", str(tmp_path / name), "--preset", "paper-traj3", "--seed", "3", "--n-events", "10",
                    "-q", *extra)
        assert sim.returncode == 0, sim.stderr
        run = calib("run", str(tmp_path / name), "-o", str(tmp_path / f"out_{name}"), "-q")
        assert run.returncode == 0, run.stderr
        cal = tmp_path / f"out_{name}" / "calibration"
        truth = read_truth(tmp_path / name / "truth")
        from calib.pipeline.formats.io import read_features
        from calib.pipeline.formats.calibration_json import calibration_document
        from calib.pipeline.report.evaluate import evaluate

        # the features of `calib run`, estimated with clock models (not yet the CLI's default)
        feats = read_features(tmp_path / f"out_{name}" / "features")
        result = calibrate(feats, clock_model="auto")
        rep = result["report"]
        errs[name] = evaluate(result, truth)["position_rmse_m"]
        steps = rep["clock"]["arrays"]["A3"]["steps"]
        if name == "clean":
            assert rep["clock"]["findings"] == []
            continue
        (s,) = steps
        t = truth["clocks"]["A3"]["steps"][0]["time"] + truth["clocks"]["A3"]["t0"]   # the true drop (emitter time)
        ev = pd.read_csv(tmp_path / name / "events.csv")
        assert (s["after_event"], s["before_event"]) == (int(ev.event[ev.t_emit < t].max()), int(ev.event[ev.t_emit > t].min()))
        assert s["kind"] == "dropped" and abs(s["size"] + 0.02) < max(3 * s["std"], 1e-5)
        doc = calibration_document(result, feats)
        assert next(a for a in doc["arrays"] if a["name"] == "A3")["clock"]["steps"][0]["after_event"] == s["after_event"]
    assert errs["drop"] < 1.5 * errs["clean"] + 0.002


# ----------------------------------------------------------------------------------------------- declared rates
def _declare_rate(session_dir, array, value):
    """session.toml with ``sample_rate = value`` (TOML text) in ``array``'s table."""
    p = session_dir / "session.toml"
    text = p.read_text()
    head = f'name = "{array}"\n'
    assert head in text
    p.write_text(text.replace(head, head + f"sample_rate = {value}\n"))


def test_a_declared_sample_rate_replaces_the_header_s_and_bad_values_are_named(tmp_path):
    """session.toml's per-array ``sample_rate`` (a board whose WAV header states a wrong rate) is the rate every
    stage reads its samples at; a bad value is one line naming the file and the key, exit 2."""
    import soundfile as sf
    from typer.testing import CliRunner

    from calib.cli.main import app
    from calib.errors import InputError
    from calib.frontend.signals import ArrayAudio, read_header
    from calib.pipeline.formats.session import read_session, session_toml

    from .sessions import small_lab3_session

    d = small_lab3_session(tmp_path / "s", seed=0, n_events=3, rt60=0.0)
    header = sf.info(str(d / "A2.wav")).samplerate
    declared = header - 160   # 1 % slow: what the board really runs at
    _declare_rate(d, "A2", declared)
    s = read_session(d)
    a2 = next(a for a in s["arrays"] if a["name"] == "A2")
    assert a2["sample_rate"] == declared and all(a["sample_rate"] is None for a in s["arrays"] if a["name"] != "A2")
    assert read_header(a2).samplerate == declared
    assert read_header(s["arrays"][0]).samplerate == header
    with ArrayAudio(a2) as audio:
        assert audio.fs == declared and audio.frames == sf.info(str(d / "A2.wav")).frames
    # the writer keeps it (a session written back reads the same)
    text = session_toml(343.0, "A1", {"f0": 500.0, "f1": 4000.0, "duration": 0.2},
                        [{"name": a["name"], "wav": a["wav"].name, "mics": a["mics"], "sample_rate": a["sample_rate"]}
                         for a in s["arrays"]])
    assert text.count("sample_rate") == 1 and f"sample_rate = {declared}\n" in text
    clean = (d / "session.toml").read_text().replace(f"sample_rate = {declared}\n", "")
    for bad, why in (('"fast"', "must be a number"), ("0", ""), ("44100.5", ""), ("true", "must be a number"),
                     ("1e9", "")):
        (d / "session.toml").write_text(clean)
        _declare_rate(d, "A2", bad)
        with pytest.raises(InputError, match=f"session.toml: array 'A2': 'sample_rate'.*{why}"):
            read_session(d)
        r = CliRunner().invoke(app, ["features", str(d), "-o", str(tmp_path / "f"), "-q"])
        assert r.exit_code == 2 and "'sample_rate'" in r.output and r.output.startswith("error: "), r.output
        assert not (tmp_path / "f").exists()


@pytest.mark.parametrize("seed,size", [(4, 0.040), (5, -0.040)])
def test_a_large_step_of_the_reference_is_named_and_modelled(seed, size):
    """A 40 ms step of the reference's clock shifts every TDOA-M: the linear solve may find no basin at all.
    Its TDOA-S jumps further than any source move allows (the triangle inequality, no fit needed): named
    there, and the step modelled from it in its interval, the session calibrated as without it."""
    from calib.estimator.clockmodel import impossible_jumps

    f, truth = simulate_features(3, SIGMA, seed=seed, clocks={"A1": {"steps": [{"size": size}]}})
    interval = _interval(truth["clocks"]["A1"], f)
    (j,) = impossible_jumps(f)
    assert (j["array"], j["after_event"], j["before_event"]) == ("A1", *interval)
    assert abs(j["size"] - size) <= j["allowed"]
    cal = calibrate(f, clock_model="auto")
    (s,) = _steps(cal, "A1")
    assert (s["after_event"], s["before_event"]) == interval and abs(s["size"] - size) < 3 * s["std"]
    clean = evaluate(calibrate(simulate_features(3, SIGMA, seed=seed)[0]), simulate_features(3, SIGMA, seed=seed)[1])
    assert evaluate(cal, truth)["position_rmse_m"] <= 1.5 * clean["position_rmse_m"] + 0.002


@pytest.mark.slow
def test_a_declared_rate_calibrates_a_wrong_header_as_if_right(tmp_path):
    """`calib simulate --clock A2={rate=...}` renders A2 1 % slow under its header's rate; `calib run` names the
    wrong header, and with A2's true rate declared in session.toml calibrates as the fault-free session."""
    import json
    import subprocess
    import sys

    import soundfile as sf

    from calib.pipeline.formats.io import read_calibration, read_truth

    def calib(*args):
        return subprocess.run([sys.executable, "-m", "calib", *args], capture_output=True, text=True, timeout=900)

    for name, extra in (("clean", []), ("slow", ["--clock", "A2={rate={error=-0.01}}"])):
        sim = calib("simulate", "-o", str(tmp_path / name), "--preset", "paper-traj3", "--seed", "3", "--n-events",
                    "10", "-q", *extra)
        assert sim.returncode == 0, sim.stderr
    import shutil

    shutil.copytree(tmp_path / "slow", tmp_path / "declared")
    fs = sf.info(str(tmp_path / "slow" / "A2.wav")).samplerate
    _declare_rate(tmp_path / "declared", "A2", round(fs * 0.99))
    out = {}
    for name in ("clean", "slow", "declared"):
        run = calib("run", str(tmp_path / name), "-o", str(tmp_path / f"out_{name}"), "-q")
        assert run.returncode in (0, 3), run.stderr
        rep = json.loads((tmp_path / f"out_{name}" / "calibration" / "report.json").read_text())
        err = evaluate(read_calibration(tmp_path / f"out_{name}" / "calibration"), read_truth(tmp_path / name / "truth"))
        out[name] = (rep, err["position_rmse_m"])
    # undeclared: the features stage measured A2's rate from the chirps and took its samples at it
    # (pipeline/headerrate.py): named as a wrong header (suspect), calibrated as the fault-free session
    rep, err = out["slow"]
    meta = json.loads((tmp_path / "out_slow" / "features" / "meta.json").read_text())
    assert list(meta["header_rates"]) == ["A2"] and abs(meta["header_rates"]["A2"]["used"] / (fs * 0.99) - 1) < 2e-4
    assert rep["verdict"]["status"] == "suspect" and "A2.wav (array A2): the header's sample rate" in \
        rep["verdict"]["reasons"][0]
    assert err <= 1.5 * out["clean"][1] + 0.002
    rep, err = out["declared"]
    assert rep["verdict"]["status"] == "ok" and all(a["nominal_rate"] is None for a in rep["clock"]["arrays"].values())
    assert err <= 1.5 * out["clean"][1] + 0.002


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_wrong_header_rate_is_measured_from_the_chirps_spacing(seed):
    """Detections of a board sampling at s x its header's rate lie at s (t_emit + d/c) + b (plus noise): the rate
    is measured to the range changes' share (the source moves metres: d/c varies by ms), the other arrays and
    a declared rate are left alone, and arrays all off by one scale are the emission times' fault."""
    import pandas as pd

    from calib.pipeline.headerrate import rate_corrections

    rng = np.random.default_rng(seed)
    t_emit = np.cumsum(rng.uniform(1.5, 2.5, 40))
    ranges = 3.0 + np.cumsum(rng.normal(0, 0.3, 40))            # m: the robot wanders
    session = {"events": pd.DataFrame({"event": np.arange(40), "t_emit": t_emit}),
               "arrays": [{"name": n, "sample_rate": None} for n in ("A1", "A2", "A3")]}

    def dets(scale, fs=16000, drop=()):   # (the association matches a clock within 1e-3 of the emitter's)
        t = scale * (t_emit + ranges / 343.0) + rng.uniform(0, 5) + rng.normal(0, 1e-4, 40)
        return {"fs": fs, "detections": [{"time": float(x), "event": k if abs(scale - 1) < 1e-3 else None}
                                         for k, x in enumerate(t) if k not in drop]}

    true = 44100 / 48000
    diag = {"arrays": {"A1": dets(1.00002), "A2": dets(true, drop=(3, 17)), "A3": dets(0.99995)}}
    fixes = rate_corrections(session, diag)
    assert list(fixes) == ["A2"]
    # the spacing's error: the range changes' slope over the session (the first solve's drift refines it)
    span = np.polyfit(t_emit, ranges / 343.0, 1)[0]
    assert abs(fixes["A2"]["scale"] / true - 1) <= abs(span) * 1.5 + 2e-5
    declared = {**session, "arrays": [{**a, "sample_rate": 14700 if a["name"] == "A2" else None}
                                      for a in session["arrays"]]}
    assert rate_corrections(declared, diag) == {}
    every = {"arrays": {n: dets(1.02) for n in ("A1", "A2", "A3")}}
    assert rate_corrections(session, every) == {}


@pytest.mark.parametrize("seed", [0, 1])
def test_an_array_that_missed_chirps_at_its_right_rate_is_not_searched_at_other_rates(monkeypatch, seed):
    """An array that matched fewer than 80 % of the events (chirps lost behind an obstacle, at low SNR) but whose
    detections' intervals agree with the emission intervals at its header's rate keeps that rate, without the
    search that reads its whole recording at 22 other rates; one whose few detections agree with too few
    intervals is still searched, and its wrong rate found."""
    import pandas as pd

    from calib.pipeline import headerrate

    rng = np.random.default_rng(seed)
    t_emit = np.cumsum(rng.uniform(2.0, 3.0, 16))
    session = {"events": pd.DataFrame({"event": np.arange(16), "t_emit": t_emit}),
               "arrays": [{"name": n, "sample_rate": None} for n in ("A1", "A2")]}
    t = t_emit + 0.02 * rng.standard_normal(16) / 343.0 + rng.uniform(0, 5)   # crystal-true clocks, a wandering range
    lost = rng.choice(16, 5, replace=False)                                     # 11 of 16 matched
    diag = {"arrays": {"A1": {"fs": 16000, "detections": [{"time": float(x), "event": k} for k, x in enumerate(t)]},
                       "A2": {"fs": 16000, "detections": [{"time": float(x), "event": k} for k, x in enumerate(t)
                                                          if k not in lost]}}}
    searched = []

    def search(array, session, threshold=8.0):   # the search: here a 44.1 kHz board written as 48
        searched.append(array["name"])
        return 44100 / 48000, 0.9, (44100 / 48000) * t
    monkeypatch.setattr(headerrate, "searched_scale", search)
    assert headerrate.rate_corrections(session, diag) == {} and searched == []
    few = {**diag["arrays"]["A2"], "detections": diag["arrays"]["A2"]["detections"][:2]}   # mostly missed
    fixes = headerrate.rate_corrections(session, {"arrays": {**diag["arrays"], "A2": few}})
    assert searched == ["A2"] and list(fixes) == ["A2"] and fixes["A2"]["used"] == round(16000 * 44100 / 48000)


def test_a_fast_clock_stands_only_if_the_array_is_trusted_at_its_measured_rate(monkeypatch):
    """A fast-clock candidate (its association at the search bound) is read at the rate a first solve's drift
    gives it, trusted or not (a true fast clock's sweep is off the template: its timing is biased until then).
    Read at that rate, it stands only if the next solve trusts the array: an untrusted one's drift followed its
    wrong arrivals (a U-shaped room's reflections gave -829 ppm to a -85 ppm clock), and it goes back to its
    header's rate (changed: read again)."""
    from types import SimpleNamespace

    from calib.pipeline import headerrate, retime

    def solve(drift, unreliable):
        sol = {"problem": SimpleNamespace(names=list(drift)), "unreliable_arrays": unreliable,
               "state": SimpleNamespace(drift=np.array(list(drift.values())))}
        monkeypatch.setattr(retime, "first_solve", lambda *a, **k: (sol, None))

    cand = {n: {"header": 16000, "used": 16000, "scale": 1.0, "fast_clock": True} for n in ("A2", "A3")}
    solve({"A1": 0.0, "A2": -8.3e-4, "A3": 5e-5}, ["A2"])
    out, changed = headerrate.refine_rates({}, None, cand)      # A3: a crystal's drift, no fast clock
    assert list(out) == ["A2"] and changed and out["A2"]["used"] == round(16000 * (1 - 8.3e-4))
    taken = {"A2": {**out["A2"]}}
    solve({"A1": 0.0, "A2": -7e-5, "A3": 5e-5}, ["A2"])          # still untrusted at that rate: dropped
    assert headerrate.refine_rates({}, None, taken) == ({}, True)
    solve({"A1": 0.0, "A2": -2e-5, "A3": 5e-5}, [])              # trusted: it stands (refined below RATE_REFINE)
    out, changed = headerrate.refine_rates({}, None, taken)
    assert not changed and out["A2"]["used"] == taken["A2"]["used"]


@pytest.mark.slow
@pytest.mark.parametrize("fault,note", [("rate1000ppm", "note"), ("{rate={error=0.1}}", "suspect")])
def test_a_clock_no_crystal_gives_is_measured_and_calibrated(tmp_path, fault, note):
    """A board 10 % fast (header 10 % slow: its sweep 10 % off the template, most chirps missed at its header's
    rate) or 1000 ppm fast (the association's bound; the template 7 Doppler-bank steps off): `calib run` measures
    the rate (a search over rates; a first solve's drift), takes A2's samples at it, names it (10 %: a wrong
    header, suspect; 1000 ppm: a note) and calibrates the session as the fault-free one."""
    import json
    import subprocess
    import sys

    from calib.pipeline.formats.io import read_calibration, read_truth

    def calib(*args):
        return subprocess.run([sys.executable, "-m", "calib", *args], capture_output=True, text=True, timeout=900)

    err = {}
    for name, extra in (("clean", []), ("fault", ["--clock", f"A2={fault}"])):
        sim = calib("simulate", "-o", str(tmp_path / name), "--preset", "paper-traj3", "--seed", "5", "--n-events",
                    "12", "-q", *extra)
        assert sim.returncode == 0, sim.stderr
        run = calib("run", str(tmp_path / name), "-o", str(tmp_path / f"out_{name}"), "-q")
        assert run.returncode == 0, run.stderr
        err[name] = evaluate(read_calibration(tmp_path / f"out_{name}" / "calibration"),
                             read_truth(tmp_path / name / "truth"))["position_rmse_m"]
    meta = json.loads((tmp_path / "out_fault" / "features" / "meta.json").read_text())
    scale = 1.001 if fault == "rate1000ppm" else 1.1
    a2 = meta["header_rates"]["A2"]
    assert list(meta["header_rates"]) == ["A2"] and abs(a2["used"] / a2["header"] / scale - 1) < 2e-4
    # calibration.json says at which rate A2's local times count its samples (the others: their headers')
    from calib.pipeline.formats.results import load_calibration

    cal = load_calibration(tmp_path / "out_fault" / "calibration" / "calibration.json")
    assert {a.name: a.sample_rate for a in cal.arrays if a.sample_rate is not None} == {"A2": a2["used"]}
    rep = json.loads((tmp_path / "out_fault" / "calibration" / "report.json").read_text())
    assert [(f["status"], f["array"]) for f in rep["setup"] if f["check"] == "sample rate"] == [(note, "A2")]
    assert err["fault"] <= 1.5 * err["clean"] + 0.002


def test_arrivals_doubted_for_a_reason_no_clock_gives_are_free_in_the_per_array_fit():
    """An "arrival" component is one event's arrival off: +1 on its TDOA-M and on the TDOA-S into it, −1 on the
    TDOA-S out of it (TDOA-S and TDOA-M are differences of arrival times). Two of A4's arrivals 0.14 ms early and
    flagged mic_spread (mics that disagree: no clock does that; rendered warehouse seed 30 modelled two false steps
    before them): the per-array fit with them free recovers each shift, within 3 µs of the truth."""
    from calib.estimator import clockmodel as cm
    from calib.estimator.calibrate import calibrate_features

    f, _ = simulate_features(_session(5, 16), 2e-6, seed=5, max_interval=4.0)
    bad = {5: -1.4e-4, 13: -1.4e-4}
    g = ck.doubt_arrivals(ck.delay_arrivals(f, "A4", bad), "A4", list(bad), flag="mic_spread")
    assert {e for a, e in cm.doubted_arrivals(g, cm.CLOCK_BLIND_DOUBTS) if a == "A4"} == set(bad)
    r = calibrate_features(g)
    p, st = r["problem"], r["state"]
    i = [str(n) for n in p.names].index("A4")
    D = cm.array_data(p, st, i)
    free = [Component("arrival", float(p.t[k]), 0.0) for k in range(len(p.t)) if int(p.events[k]) in bad]
    S, M = cm._design(D, free)
    k5 = int(np.flatnonzero(p.events == 5)[0])
    np.testing.assert_array_equal(S[:, 0], (D.b == k5).astype(float) - (D.a == k5))
    np.testing.assert_array_equal(M[:, 0], (D.j == k5).astype(float))
    _, _, _, coef, _ = cm.fit_array(D, free, st.x[i].copy(), 1.0 + st.drift[i], st.offset[i])
    np.testing.assert_allclose(coef, [-1.4e-4, -1.4e-4], atol=3e-6)
    got = cm.best_component(D, [], st.x[i].copy(), 1.0 + st.drift[i], st.offset[i], p.N + 1, free=free)
    assert got[0] is None or all(c.kind != "arrival" for c in got[0])


# ----------------------------------------------------------------------------------------------- moving source
def _moving_scene(seed, sigma_v, monkeypatch):
    """test_motion_noise's moving scene: a robot that keeps moving while it chirps, the velocity the correction
    uses off by σ_v per axis (stated as such), linear clocks."""
    import calib.estimator.motion as motion
    from .test_motion_nlos import _moving

    monkeypatch.setattr(motion, "velocity_sigma", lambda *a, **k: sigma_v)
    f, tr = simulate_features(2, 2e-6, 0.05, 0.01, seed=seed)
    vel_error = np.random.default_rng(100 + seed).normal(0.0, sigma_v, (len(f["events"]), 3))
    return _moving(f, tr, with_vel=True, vel_error=vel_error)[0], tr


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_a_moving_source_s_velocity_error_makes_no_clock_term(monkeypatch, seed):
    """A velocity error of 0.05 m/s per axis moves each event's corrected arrivals as 3 cm of source shift,
    which the odometry does not follow: the clocks are linear, so no clock term (unmodelled, the nuisance made
    an emitter step and steps of A1 on these seeds, and the selection solved the session dozens of times)."""
    g, _ = _moving_scene(seed, 0.05, monkeypatch)
    out = calibrate(g, noise="meta")
    assert out["report"]["stages"]["motion"]["velocity_sigma_m_s"] == 0.05
    clock = out["report"]["clock"]
    assert not any(a["components"] for a in clock["arrays"].values())
    assert not clock["emitter"]["components"]


@pytest.mark.parametrize("seed", [102, 105])
def test_a_fault_free_moving_session_names_no_array(monkeypatch, seed):
    """The velocity error of a moving source's correction (3 cm of source shift per event in its arrivals, 40×
    their σ) is in the joint solve itself (``State.dv`` with its prior) and its arrival shifts are taken at the
    solve's own geometry (in the factors): its array tests then see honest residuals. Before, with the error
    only in the error bars and the shifts fixed between passes, these fault-free sessions had two and three
    of their arrays named inconsistent (verdict failed, arrays 2.2 / 3.2 cm off); now none, every array within
    1 cm of the simulated truth, the verdict ok and no clock term."""
    from calib.pipeline.report.evaluate import array_errors, array_table

    g, tr = _moving_scene(seed, 0.05, monkeypatch)
    out = calibrate(g, noise="meta")
    rep = out["report"]
    assert rep["stages"]["motion"]["applied"] and not rep["unreliable_arrays"]
    assert rep["verdict"]["status"] == "ok"
    e = array_errors(array_table(out["arrays"]), array_table(tr["arrays"]))
    assert np.nanmax(np.asarray(e["position_m"], float)) < 0.01
    assert not any(a["components"] for a in rep["clock"]["arrays"].values())


def test_every_row_of_a_moving_session_is_motion_corrected(monkeypatch):
    """The selection's tests of every row (persistence, structure, robust costs) rebuild the problem from the
    features: in a moving session with the solve's motion correction, its rows the solve's own (uncorrected,
    a TDOA is off by the source's move during the sweep: hundreds of σ, which made a true 2 ms step
    unpersistent)."""
    import calib.estimator.clockmodel as cm
    from calib.estimator.problem import build_problem, make_layout
    from calib.estimator.solver import linearise

    g, _ = _moving_scene(7, 0.05, monkeypatch)
    out = calibrate(g, noise="meta", clock_model="linear")
    assert out["report"]["stages"]["motion"]["applied"]
    p, q = out["problem"], cm._every_row(out, g)
    for kind in ("tdoa_m", "tdoa_s"):
        solved, every = getattr(p, kind), getattr(q, kind)
        at = {int(r): k for k, r in enumerate(every.row)}
        np.testing.assert_array_equal(every.val[[at[int(r)] for r in solved.row]], solved.val)
    # at the solution its TDOA rows fit as the solve's do; uncorrected, tens of times worse
    raw = build_problem(g, use_tdoa_s=True, odometry_yaw=p.odo_yaw_free).replace(sigma=dict(p.sigma))
    r = [np.median(np.abs(linearise(x, out["state"], make_layout(x), ["tdoa_s", "tdoa_m"]).r)) for x in (p, q, raw)]
    assert r[1] < 1.5 * r[0] and r[2] > 10.0 * r[1]


@pytest.mark.slow
def test_a_step_in_a_moving_session_is_still_found(monkeypatch):
    """The velocity nuisance does not hide a clock fault well above it: 2 ms of samples inserted on A3 between
    two middle events (the nuisance's arrival error is ~0.1 ms) is found in its interval, its size within 3σ,
    and A3 stays calibrated (before: its tests of every row read the arrivals uncorrected for the motion and
    the step failed its persistence; the leave-one-out test, blind to the velocity error, then isolated A3)."""
    _moving_step(monkeypatch, 7, "A3", 0.5, 0.002)


@pytest.mark.slow
@pytest.mark.parametrize("seed,array,at,size", [(8, "A5", 0.5, 0.0005), (10, "A4", 0.5, -0.02),
                                                (101, "A2", 0.4, -0.002), (100, "A4", 0.6, -0.002)])
def test_a_step_in_a_moving_session_on_other_seeds(monkeypatch, seed, array, at, size):
    """As above on other seeds, arrays and places: 0.5 ms inserted, 20 ms dropped (the issue's sizes), 2 ms
    dropped (seeds 100, 101: sized 16 and 85 µs off, which the σ of an estimate that models the velocity
    nuisance stated as 2.3 and 5.6 µs; the fit did not model it then: its sandwich σ, 20 and 39 µs; now the solve
    models it, ``State.dv``). Still lost (benchmarks/bench_moving_clocks.py, docs/results.md): a 20 ms step whose
    unmodelled first solve sends its array hundreds of metres away."""
    _moving_step(monkeypatch, seed, array, at, size)


def _moving_step(monkeypatch, seed, array, at, size):
    """``size`` (s; > 0 inserted) of samples on ``array`` between events k − 1 and k (k at the share ``at`` of the
    moving scene's events): found there, its size within 3σ, no other clock term, the array calibrated."""
    g, tr = _moving_scene(seed, 0.05, monkeypatch)
    t = g["events"]["t_emit"].to_numpy(float)
    k = int(len(t) * at)
    g = correct_features(g, {array: [Component("step", 0.5 * (t[k - 1] + t[k]) - t[0], -size)]})
    out = calibrate(g, noise="meta")
    steps = out["report"]["clock"]["arrays"][array]["steps"]
    ev = g["events"]["event"].to_numpy()
    assert len(steps) == 1 and (steps[0]["after_event"], steps[0]["before_event"]) == (ev[k - 1], ev[k])
    assert abs(steps[0]["size"] - size) < 3.0 * steps[0]["std"]
    others = [n for n, a in out["report"]["clock"]["arrays"].items() if n != array and a["components"]]
    assert not others
    assert array not in out["report"]["unreliable_arrays"]


def test_a_reference_warm_up_is_taken_by_the_sources_and_bends_the_others_more():
    """Why a warm-up on the reference is modelled less often and bends the other arrays more than one on another
    array (issue 28; benchmarks/diag_ref_warmup.py). Exact measurements of bench_clocks' seed-500 session (its
    linear fit is the truth): the warm-up's column (3.77 ppm, τ 60 s) off the clocks' offsets and drifts, then off
    the sources too. The reference's shifts every array's TDOA-M of an event alike, which the sources reproduce:
    they take over 90 % of what the clocks leave (another array's: under 75 %), and what the fit absorbs moves the
    others several times more per unit of the scan's evidence (χ² λ: below the scan's penalty, 22.3, here)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from diag_ref_warmup import information

    f, _ = simulate_features(_walk36(500), SIGMA, 5.0, 0.03, seed=500, max_interval=10.0, noise=False)
    fit = calibrate(f, clock_model="linear")
    ref, other = (information(fit, i, 3.77e-6) for i in (0, 2))
    assert ref["lam_src"] < 0.1 * ref["lam_clk"] and other["lam_src"] > 0.25 * other["lam_clk"]
    assert ref["lam"] < 22.3
    assert ref["bias_cm"] / np.sqrt(ref["lam"]) > 2.5 * other["bias_cm"] / np.sqrt(other["lam"])


def _loop_with_shadows(seed, edge, sigma=2e-6):
    """A fault-free session whose robot drives one loop of 10 stops twice (rendered office's), where A3's line of
    sight is blocked at events 6-9 and 16-19 (reflection-only arrivals 12-20 ms late, doubted ``nlos``) and its
    arrivals at the shadow's edge, events 5 and 15, are ``edge`` s late, unflagged (a direct path grazing the
    obstacle, a reflection merged with it). Returns the features."""
    stops = _session(seed, 10)
    stops = np.vstack([stops, stops + np.random.default_rng([seed, 55]).normal(0, 0.02, stops.shape)])
    f, _ = simulate_features(stops, sigma, seed=seed, max_interval=10.0)
    rng = np.random.default_rng([seed, 54])
    runs = [6, 7, 8, 9, 16, 17, 18, 19]
    delays = dict(zip(runs, rng.uniform(0.012, 0.020, len(runs))))
    delays.update({5: edge * rng.uniform(0.8, 1.2), 15: edge * rng.uniform(0.8, 1.2)})
    return ck.doubt_arrivals(ck.delay_arrivals(f, "A3", delays), "A3", runs)


@pytest.mark.parametrize("seed", [548])
def test_late_arrivals_at_the_edge_of_a_blocked_line_of_sight_make_no_clock_step(seed):
    """No clock has a fault. A3's two undoubted arrivals beside its reflection-only runs are 40 µs late (20 σ):
    with the runs' rows out of the tests, a step in the interval before one of them (its only undoubted event
    until the run ends) or between them rests on those two arrivals, ten events apart, which no leave-out of
    PERSIST_EVENTS consecutive events removes (rendered office dev 501/503: 75 and 30 µs false steps so). Left
    out together (clockmodel.penumbra), nothing is left of the step: no clock term on any array. (Seed 540 still
    gets a 42 µs step in the interval before event 15, persistent χ² 56 with the edges out: its structure test's
    early and late halves split the events after it, doubted ones included, and the late half testifies nothing.)"""
    cal = calibrate(_loop_with_shadows(seed, 4e-5), clock_model="auto")
    clocks = cal["report"]["clock"]
    assert not [a for a, e in clocks["arrays"].items() if e["components"]]
    assert not clocks["emitter"]["components"]


def test_a_clock_term_the_solved_rows_say_nothing_of_is_removed():
    """No clock has a fault. A3's last four arrivals are reflection-only, doubted and screened out of the solve,
    late by 6.8-7.3 ms (σ 100 µs: their spread is a few σ, too wide to be readmitted as one lag, close enough to
    testify for a 7 ms step in the structure and persistence tests). A 7 ms step of A3 before them: no row the
    solve uses holds it and the joint step sizes it with a σ of 0 (rendered deploy dev 513: a 6.93 ms reference
    step from doubted rows alone, reported as σ 0.0 µs). The judgement skipped components without a σ; it
    removes it."""
    from calib.estimator.calibrate import calibrate_features
    from calib.estimator.clockmodel import _refine_and_resolve

    f, _ = simulate_features(_session(7), 1e-4, seed=7, max_interval=10.0)
    late = [20, 21, 22, 23]
    f = ck.doubt_arrivals(ck.delay_arrivals(f, "A3", dict(zip(late, [0.0068, 0.0072, 0.0069, 0.0073]))), "A3", late)
    t = f["events"]["t_emit"].to_numpy() - f["events"]["t_emit"].iloc[0]
    models = {"A3": [Component("step", 0.5 * (t[19] + t[20]), 0.007)]}
    result = calibrate_features(correct_features(f, models))
    _, kept, _, removed = _refine_and_resolve(calibrate_features, f, result, models, {})
    assert not kept.get("A3") and [r[0] for r in removed] == ["A3"]
