"""An array taken at a measured (or declared) sample rate (issue 28): its calibrated clock is on that rate's time
base; composed with the header's rate (calibration.json ``header_sample_rate``) it is the simulator's true clock,
and `calib evaluate` scores it so. Files without the header rate load and score as before."""
import json
import subprocess
import sys

import numpy as np
import pytest

from calib.clock import Clock, Step, Term, header_time_base
from calib.pipeline.simulate import clocks as ck

HEADER = 16000


def test_a_clock_read_at_another_rate_composes_back_to_the_true_one():
    """The simulator's clocks (a +1000 ppm board with a 20 ms drop and a warm-up, a -1 % board, a crystal
    reference) read at the rates calib would take them at: the local times × header / used. What a perfect
    calibration on those time bases holds (offsets relative to the reference's local time at t0) composes with
    r = used / header back to the truth's offset (τ_i − τ_ref) and drift, and Clock.scaled(r) back to the true
    local times, steps and terms included."""
    t = np.array([0.0, 2.0, 5.5, 9.0, 14.0, 20.0])
    rng = np.random.default_rng(500)
    ref = Clock(offset=0.39, drift=-4.7e-5)
    truth = {"A2": (ck.fault_clock(0.30, 1.3e-5, {"rate": {"error": 1e-3}, "steps": [{"time": 7.0, "size": -0.02}],
                                                  "warmup": {"amplitude": 3e-6, "time_constant": 60.0}},
                                   event_times=t, rng=rng), 16016),
             "A3": (ck.fault_clock(0.37, -2.4e-5, {"rate": {"error": -0.01}}, event_times=t, rng=rng), 15840)}
    for name, (true, used) in truth.items():
        r = used / HEADER
        taken = true.scaled(1.0 / r)    # its local time as WAV sample / used
        np.testing.assert_allclose(taken.local(t), true.local(t) * HEADER / used, rtol=1e-13, atol=1e-13)
        offset, drift = header_time_base(taken.offset - ref.offset, taken.drift, r, 1.0, ref.offset)
        assert offset == pytest.approx(true.offset - ref.offset, abs=1e-13)
        assert drift == pytest.approx(true.drift, abs=1e-13)
        np.testing.assert_allclose(taken.scaled(r).local(t), true.local(t), atol=1e-12)
    # the reference itself taken at another rate: every offset composes with (r − r_ref)
    r_ref = 16001 / HEADER
    ref_taken = ref.scaled(1.0 / r_ref)
    true, used = truth["A3"]
    taken = true.scaled(HEADER / used)
    offset, _ = header_time_base(taken.offset - ref_taken.offset, taken.drift, used / HEADER, r_ref, ref_taken.offset)
    assert offset == pytest.approx(true.offset - ref.offset, abs=1e-13)
    # every term kind scales (its parameters that are time)
    for term in (Term("quadratic", {"slope": 2e-8}), Term("hinge", {"time": 3.0, "change": 4e-6}),
                 Term("table", {"knots": [0.0, 10.0], "values": [0.0, 1e-6]})):
        c = Clock(0.1, 1e-4, 0.0, (Step(4.0, 0.005),), (term,))
        np.testing.assert_allclose(c.scaled(0.99).local(t), 0.99 * c.local(t), atol=1e-13)


def _calib(*args):
    return subprocess.run([sys.executable, "-m", "calib", *args], capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_evaluate_scores_an_array_taken_at_its_measured_rate_on_its_total_clock(tmp_path):
    """A rendered session with one board 1000 ppm fast and one whose clock runs 1 % slow against its header
    (both taken at a measured rate by `calib run`): calibration.json and report.json give both rates, and
    `calib evaluate` scores their total drift and offset against the simulator's truth — within a few ppm and
    µs, as the crystal arrays (before: 1000 and 10000 ppm, 0.3 and 3.8 ms off); the local times
    ``to_local_time(header=True)`` gives follow the true clocks. A calibration.json / report.json without the
    header's rate (older files) still loads and scores as before, on the rate used."""
    from calib.pipeline.formats.io import read_calibration, read_truth
    from calib.pipeline.formats.results import load_calibration
    from calib.pipeline.report.evaluate import evaluate

    sim = _calib("simulate", "-o", str(tmp_path / "s"), "--preset", "paper-traj3", "--seed", "510", "--n-events",
                 "12", "-q", "--clock", "A2=rate1000ppm", "--clock", "A3={rate={error=-0.01}}")
    assert sim.returncode == 0, sim.stderr
    run = _calib("run", str(tmp_path / "s"), "-o", str(tmp_path / "o"), "-q")
    assert run.returncode == 0, run.stderr
    cdir = tmp_path / "o" / "calibration"
    truth = read_truth(tmp_path / "s" / "truth")
    cal = load_calibration(cdir)
    rates = {a.name: (a.sample_rate, a.header_sample_rate) for a in cal.arrays if a.sample_rate is not None}
    assert set(rates) == {"A2", "A3"} and all(h == HEADER for _, h in rates.values())
    rep = json.loads((cdir / "report.json").read_text())
    assert {n: (e["sample_rate"], e["header_sample_rate"]) for n, e in rep["clock"]["arrays"].items()
            if e["sample_rate"]} == rates
    m = evaluate(read_calibration(cdir), truth)
    for a in m["per_array"]:
        assert abs(a["drift"]) < 3e-6 and abs(a["offset_s"]) < 2e-5, a
    assert m["clock"]["local_time_max_error_s"] < 2e-5
    # the calibration's local times on each header's time base against the true clocks (relative to A1's)
    t0, recs = cal.clock.t0, truth["clocks"]
    t = t0 + np.asarray(recs["A2"]["event_times"])
    true_ref = recs["A2"]["offset"] - float(truth["arrays"].set_index("array").loc["A2", "offset"])
    ref_drift = float(truth["arrays"].set_index("array").loc["A1", "drift"])
    for name in ("A2", "A3"):
        got = cal.to_local_time(name, t, header=True) - cal.to_local_time("A1", t, header=True)
        want = Clock.from_dict(recs[name]).local(t) - (true_ref + (1 + ref_drift) * (t - t0))
        assert np.abs(got - want).max() < 2e-5
        np.testing.assert_allclose(cal.to_emitter_time(name, cal.to_local_time(name, t, header=True), header=True),
                                   t, atol=1e-9)
    # older files: no header rate → loaded, on the rate used (A2's drift error its 1000 ppm, as before)
    doc = json.loads((cdir / "calibration.json").read_text())
    for a in doc["arrays"]:
        a["clock"].pop("header_sample_rate")
    (cdir / "calibration.json").write_text(json.dumps(doc))
    for e in rep["clock"]["arrays"].values():
        e.pop("sample_rate"), e.pop("header_sample_rate")
    (cdir / "report.json").write_text(json.dumps(rep))
    old = load_calibration(cdir)
    assert all(a.rate_scale == 1.0 and a.header_sample_rate is None for a in old.arrays)
    assert old.header_clock("A2") == pytest.approx((old.array("A2").offset, old.array("A2").drift), abs=1e-15)
    by = {a["array"]: a["drift"] for a in evaluate(read_calibration(cdir), truth)["per_array"]}
    assert by["A2"] == pytest.approx(HEADER / rates["A2"][0] - 1, abs=1e-4)   # ≈ −1000 ppm
    assert by["A3"] == pytest.approx(HEADER / rates["A3"][0] - 1, abs=1e-3)   # ≈ +1 %


def test_evaluate_composes_a_perfect_calibration_on_the_rate_used_back_to_the_truth():
    """A perfect calibration of a simulated +1000 ppm board (roomsim-like truth: its clock record holds its
    absolute offset τ, arrays.csv τ − τ_ref) taken at 16016 Hz: `evaluate` scores it 0 on the header's time base
    (drift, offset, the clock's local time), and as 1000 ppm off when the report lacks the header's rate (files
    before it), as it always did."""
    import pandas as pd

    from calib.pipeline.report.evaluate import evaluate

    t = np.array([0.0, 2.1, 4.0, 6.3, 8.2])
    tau_ref, drift_ref, used = 0.39, -4.7e-5, 16016
    true = ck.fault_clock(0.30, 1.3e-5, {"rate": {"error": 1e-3}}, event_times=t, rng=np.random.default_rng(0),
                          t0=10.0)
    r = used / HEADER

    def frame(offset, drift):
        return pd.DataFrame({"array": ["A1", "A2"], "x": [0.0, 1.0], "y": [0.0, 2.0], "z": [0.0, 0.5],
                             "qw": [1.0, 1.0], "qx": 0.0, "qy": 0.0, "qz": 0.0, "offset": [0.0, offset],
                             "drift": [drift_ref, drift]})

    truth = {"arrays": frame(true.offset - tau_ref, true.drift), "sources": None,
             "clocks": {"A2": ck.clock_record(true, {"rate": {"error": 1e-3}}, t)}}
    taken = true.scaled(1.0 / r)
    entry = {"sample_rate": used, "header_sample_rate": HEADER}
    calib = {"arrays": frame(taken.offset - tau_ref, taken.drift), "sources": None, "reference_offset": tau_ref,
             "report": {"clock": {"arrays": {"A1": {}, "A2": {**entry, "components": []}}}}}
    m = evaluate(calib, truth)
    (a2,) = m["per_array"]
    assert abs(a2["drift"]) < 1e-12 and abs(a2["offset_s"]) < 1e-12
    (c2,) = m["clock"]["per_array"]
    assert c2["local_time_max_error_s"] < 1e-12 and c2["rate_ratio"] == pytest.approx(1 + true.drift, abs=1e-12)
    # no reference offset (a calibration without calibration.json): the drift composed, the offset not scored
    (a2,) = evaluate({**calib, "reference_offset": None}, truth)["per_array"]
    assert abs(a2["drift"]) < 1e-12 and np.isnan(a2["offset_s"])
    # older files: the header's rate unknown, scored on the rate used
    calib["report"]["clock"]["arrays"]["A2"] = {"components": []}
    (a2,) = evaluate(calib, truth)["per_array"]
    assert a2["drift"] == pytest.approx((1 + true.drift) / r - 1 - true.drift, abs=1e-12)   # ≈ −1000 ppm
