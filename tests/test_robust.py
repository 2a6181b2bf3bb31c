"""Robust estimation (issue 10): outliers of every type, inconsistent arrays, the verdict, bounded noise
re-estimation, the odometry frame's yaw and option validation — against simulated ground truth."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator import calibrate, validate_options
from calib.estimator.factors import FACTORS
from calib.estimator.problem import build_problem, make_layout, retract, state_from_dict
from calib.estimator.robust import measurement_stats
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features
from .sessions import NO_TARGET

_spec = importlib.util.spec_from_file_location("bench_faults", Path(__file__).parents[1] / "benchmarks" / "bench_faults.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


@pytest.mark.slow
def test_normalised_statistics_have_their_chi2_mean_on_clean_data():
    """q = rᵀ(I − H)⁻¹r is χ²(dof): its mean over clean scenes is the dof (hat-matrix correction included)."""
    q = {"tdoa_s": [], "tdoa_m": [], "doa": [], "odometry": []}
    for seed in range(8):
        feats, truth = simulate_features(3, 1e-4, 5.0, seed=40 + seed)
        cal = calibrate(feats, noise="meta")
        p, st = cal["problem"], cal["state"]
        stats = measurement_stats(p, st, make_layout(p), ["tdoa_s", "tdoa_m", "doa", "odometry"], {})
        for k in q:
            q[k].append(stats.q[stats.kind == k] / stats.dof[stats.kind == k])
    for k in q:   # 8 scenes: the mean of q/dof has a std of ~0.03 (TDOA, DOA) to ~0.07 (odometry)
        assert 0.75 < np.mean(np.concatenate(q[k])) < 1.3, k


def test_outliers_of_every_type_are_flagged_and_good_rows_kept():
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=11)
    clean = evaluate(calibrate(feats), truth)
    tm, ts, doa, ev = (feats[k].copy() for k in ("tdoa_m", "tdoa_s", "doa", "events"))
    tm.loc[[5, 20], "tdoa"] += [0.004, -0.0008]                 # 40 σ and 8 σ
    ts.loc[3, "tdoa"] += 0.02
    u = doa.loc[30, ["ux", "uy", "uz"]].to_numpy(float).copy()
    doa.loc[30, ["ux", "uy", "uz"]] = u2 = Rotation.from_rotvec([0, 0, np.deg2rad(60)]).apply(u)
    moved = np.rad2deg(np.arccos(np.clip(u @ u2, -1, 1)))
    doa.loc[44, ["ux", "uy", "uz"]] = -doa.loc[44, ["ux", "uy", "uz"]].to_numpy(float)
    ev.loc[7:, "odom_x"] += 0.6                                 # one slipped odometry step (20 σ)
    cal = calibrate({**feats, "tdoa_m": tm, "tdoa_s": ts, "doa": doa, "events": ev})
    rep = cal["report"]
    flagged = {(o["type"], o["line"]) for o in rep["outliers"]}
    injected = {("tdoa_m", 7), ("tdoa_m", 22), ("tdoa_s", 5), ("doa", 32), ("doa", 46), ("odometry", 7)}
    assert injected <= flagged
    assert len(flagged - injected) <= 1                         # good rows are not condemned
    rec = next(o for o in rep["outliers"] if o["type"] == "doa" and o["line"] == 32)
    assert rec["array"] == feats["doa"].loc[30, "array"] and rec["event"] == feats["doa"].loc[30, "event"]
    assert abs(rec["residual"] - moved) < 10 and rec["unit"] == "deg"   # its error, up to the noise
    m = evaluate(cal, truth)
    assert m["position_rmse_m"] < clean["position_rmse_m"] + 0.01
    assert rep["verdict"]["status"] in ("ok", "suspect")


@pytest.mark.parametrize("seed", [0, 4])
def test_an_array_biased_as_a_whole_is_named_and_dropped(seed):
    feats, truth = simulate_features(1 + seed % 3, 1e-4, 5.0, 0.03, seed=1000 + seed)
    f2, bad = bench.fault_array(feats, truth, np.random.default_rng(seed))
    clean = calibrate(feats, **NO_TARGET)
    cal = calibrate(f2, **NO_TARGET)
    v = cal["report"]["verdict"]
    assert v["flagged_arrays"] == [bad] and v["status"] != "ok"
    assert cal["report"]["unreliable_arrays"] == [bad]
    stds = cal["arrays"].set_index("array").filter(like="_std")
    assert stds.loc[bad].isna().all() and stds.drop(index=[bad, feats["meta"]["reference_array"]]).notna().all().all()
    loc, _ = bench.errors(cal, truth, skip=bad)
    loc0, _ = bench.errors(clean, truth, skip=bad)
    assert loc < 1.5 * loc0 + 0.01
    assert calibrate(feats, **NO_TARGET)["report"]["verdict"]["flagged_arrays"] == []


def test_concentrated_candidates_name_the_array_holding_most_rows_beyond_the_level():
    """The drop-test candidates by concentration (robust.concentrated_candidates), on hand-made statistics:
    4 arrays × 40 rows, array 0 the reference; rows beyond ``critical_z`` counted per array."""
    from types import SimpleNamespace

    from calib.estimator.robust import concentrated_candidates, critical_z

    arr = np.repeat(np.arange(4), 40)
    p = SimpleNamespace(N=4, ref=0)

    def cands(beyond, kept=None, n_rows=None):
        a = arr if n_rows is None else np.repeat(np.arange(4), n_rows)
        z = np.zeros(a.size)
        for i, k in beyond.items():
            z[np.flatnonzero(a == i)[:k]] = critical_z(5.0, a.size) + 1.0
        keep = np.ones(a.size, bool) if kept is None else kept
        return concentrated_candidates(p, SimpleNamespace(z=z, array=a, kept=keep), 5.0)

    assert cands({2: 6, 3: 1}) == {2: 6}          # most of the rows beyond the level, 15 % of its own
    assert cands({0: 6, 3: 1}) == {}              # the reference is never dropped
    assert cands({1: 3, 2: 3, 3: 3}) == {}        # spread over the arrays: single rows, not an array
    assert cands({2: 4}, n_rows=[40, 40, 100, 40]) == {}   # 4 of its 100 rows: below its own share
    hidden = np.ones(arr.size, bool)
    hidden[np.flatnonzero(arr == 2)[:3]] = False  # rows already removed do not count
    assert cands({2: 6}, kept=hidden) == {}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4])
def test_an_occluded_array_does_not_bend_the_arrays_it_is_named_beside(tmp_path, seed):
    """`hard` preset (an occluded array, issue 9): the occluded array is named, and the arrays the verdict
    does not name stay within the lab figures (≤ 6 cm). Seed 4 (found 24 Nov): the occluded A2's kept rows
    bent the solution (A4 16.8 cm off, unnamed) until an array holding most of the outlier rows got the
    drop test too."""
    import json

    from calib.pipeline.run import run
    from calib.pipeline.simulate.roomsim import make_scenario, simulate

    res = run(simulate(make_scenario("hard", seed), tmp_path / "s"), tmp_path / "out", force=True)
    rep = json.loads((tmp_path / "out" / "calibration" / "report.json").read_text())
    named = set(rep["verdict"]["flagged_arrays"])
    assert named, "the occluded array is named"
    rest = [a for a in res["metrics"]["per_array"] if a["array"] not in named]
    assert rest and max(a["position_m"] for a in rest) < 0.06, rest


@pytest.mark.slow
def test_an_occluded_arrays_doa_spreads_do_not_set_the_sessions_doa_sigma(tmp_path):
    """`hard` seed 9 (found 24 Nov): the occluded A2's DOAs had unflagged spreads of 77–151°, whose RMS made
    the session's DOA sigma 35° (the estimator's 12°: every DOA counted for nothing; A4 8.7 cm off). With the
    doubt "doa_spread" the sigmas are those of the other arrays' DOAs (~1°), A2 is named, and the others are
    within the first clause of the `hard` figures (10 cm)."""
    import json

    from calib.pipeline.run import run
    from calib.pipeline.simulate.roomsim import make_scenario, simulate

    res = run(simulate(make_scenario("hard", 9), tmp_path / "s"), tmp_path / "out", force=True)
    meta = json.loads((tmp_path / "out" / "features" / "meta.json").read_text())
    rep = json.loads((tmp_path / "out" / "calibration" / "report.json").read_text())
    assert meta["sigma_doa_deg"] < 3.0
    assert np.degrees(rep["sigmas"]["doa_rad_per_axis"]) < 3.0
    named = set(rep["verdict"]["flagged_arrays"])
    assert "A2" in named
    rest = [a for a in res["metrics"]["per_array"] if a["array"] not in named]
    assert rest and max(a["position_m"] for a in rest) < 0.10, rest


@pytest.mark.slow
def test_stated_position_errors_match_the_errors_on_the_lab_preset(tmp_path):
    """`lab` seeds 0-4 end to end: the arrays' position errors against truth, over their stated std (every
    coordinate of every non-reference array the verdict does not name), have an RMS within the 1.5 the
    frontend's sigmas are held to. With a frontend's own sigma lowered up to 3x by the residuals (until 24
    Nov) it was 1.98: error bars half the error."""
    import json

    import pandas as pd

    from calib.pipeline.run import run
    from calib.pipeline.simulate.roomsim import make_scenario, simulate

    z = []
    for seed in range(5):
        out = tmp_path / f"out{seed}"
        run(simulate(make_scenario("lab", seed), tmp_path / f"s{seed}"), out, force=True)
        named = set(json.loads((out / "calibration" / "report.json").read_text())["verdict"]["flagged_arrays"])
        est = pd.read_csv(out / "calibration" / "arrays.csv").set_index("array")
        tru = pd.read_csv(tmp_path / f"s{seed}" / "truth" / "arrays.csv").set_index("array")
        std = est[["x_std", "y_std", "z_std"]]
        keep = [a for a in est.index if a not in named and std.loc[a].notna().all()]
        err = est.loc[keep, ["x", "y", "z"]].to_numpy() - tru.loc[keep, ["x", "y", "z"]].to_numpy()
        z.append((err / std.loc[keep].to_numpy()).ravel())
    rms = float(np.sqrt(np.mean(np.concatenate(z) ** 2)))
    assert 1 / 1.5 < rms < 1.5, rms


def test_wrong_emission_times_end_failed():
    feats, truth = simulate_features(2, 1e-4, 5.0, 0.03, seed=1001)
    f2, _ = bench.fault_t_emit(feats, truth, None)
    v = calibrate(f2, **NO_TARGET)["report"]["verdict"]
    assert v["status"] == "failed" and v["reasons"]
    assert calibrate(feats, **NO_TARGET)["report"]["verdict"] == {"status": "ok", "reasons": [], "flagged_arrays": []}


def test_stated_odometry_prior_is_not_inflated_beyond_its_bound():
    """Odometry 10× worse than stated, TDOA sigma a frontend figure: the odometry σ moves ≤ 3×, verdict says so."""
    feats, truth = simulate_features(3, 1e-4, 5.0, sigma_odo=0.3, seed=3)
    feats["meta"].update(sigma_odo=0.03, sigmas_estimated=["sigma_tdoa"])
    rep = calibrate(feats)["report"]
    assert rep["sigmas"]["source"] == "estimate"
    assert rep["sigmas"]["odometry_m"] <= 3 * 0.03 + 1e-12
    assert rep["verdict"]["status"] != "ok"
    assert any("odometry" in r for r in rep["verdict"]["reasons"])


def test_stated_sigma_excess_is_a_chi2_test():
    """Flagged only beyond the 1.5x tolerance AND improbable under the stated sigma (χ² tail), and only for
    types judged against their stated sigma (bound < 10)."""
    from scipy.stats import chi2

    from calib.estimator.verdict import stated_sigma_excess

    bounds = {"odometry": 3.0, "doa": 100.0}
    assert "odometry" in stated_sigma_excess({"odometry": 2.05}, {"odometry": 37}, bounds)   # lab seed 3, old frontend
    assert not stated_sigma_excess({"odometry": 1.3}, {"odometry": 37}, bounds)              # within the tolerance
    assert chi2.sf(3 * 1.6 ** 2, 3) > 1e-3                                                   # 3 values: not significant
    assert not stated_sigma_excess({"odometry": 1.6}, {"odometry": 3}, bounds)
    assert not stated_sigma_excess({"doa": 2.0}, {"doa": 100}, bounds)                       # free type: own sigma


@pytest.mark.parametrize("seed", [0, 1])
def test_odometry_worse_than_stated_is_suspect(seed):
    """Odometry noise 2.5x its stated sigma (within the 3x bound the prior may grow): suspect, said why;
    as stated: no such reason."""
    for true_odo, expect in ((0.01, False), (0.025, True)):
        feats, truth = simulate_features(3, 1e-5, 1.0, sigma_odo=true_odo, seed=seed)
        feats["meta"].update(sigma_odo=0.01, sigmas_estimated=["sigma_tdoa", "sigma_doa_deg"])
        verdict = calibrate(feats)["report"]["verdict"]
        said = any("stated sigma" in r for r in verdict["reasons"])
        assert said == expect and (verdict["status"] != "ok") == expect, (true_odo, verdict)


def test_odometry_yaw_is_estimated():
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=1002)
    aligned = calibrate(feats)
    assert not aligned["report"]["odometry_frame"]["estimated"]      # insignificant: fixed at 0
    f2, _ = bench.fault_odo_rot(feats, truth, None)
    cal = calibrate(f2)
    fr = cal["report"]["odometry_frame"]
    assert fr["estimated"] and abs(fr["yaw_deg"] + bench.ODO_YAW_DEG) < max(3 * fr["yaw_std_deg"], 1.0)
    loc, _ = bench.errors(cal, truth)
    loc0, _ = bench.errors(aligned, truth)
    assert loc < 1.5 * loc0 + 0.01
    off = calibrate(f2, odometry_yaw=False)
    assert bench.errors(off, truth)[0] > 3 * loc0                    # without it the rotation is not absorbed


@pytest.mark.parametrize("yaw_deg", [20.0, 180.0])
def test_odometry_yaw_with_a_planar_reference_array(yaw_deg):
    """Mirror-ambiguous reference DOAs: the start yaw is found anyway (unfolded), so any rotation of the
    odometry gives the solve of the 20° one (the problem is equivariant in the yaw), within 3σ of the truth."""
    feats, truth = simulate_features(2, 1e-4, 5.0, 0.03, seed=1001, planar=(0.0, 0.0, 1.0))
    ev = feats["events"].copy()
    o = ev[["odom_x", "odom_y", "odom_z"]].to_numpy(float).copy()
    ev[["odom_x", "odom_y", "odom_z"]] = Rotation.from_euler("z", yaw_deg, degrees=True).apply(o)
    fr = calibrate({**feats, "events": ev})["report"]["odometry_frame"]
    err = (fr["yaw_deg"] + yaw_deg + 180.0) % 360.0 - 180.0
    assert fr["estimated"] and abs(err) < 3 * fr["yaw_std_deg"]


def test_odometry_frame_jacobian_with_yaw():
    feats, _ = simulate_features(3, seed=1)
    p = build_problem(feats, odometry_yaw=True)
    rng = np.random.default_rng(0)
    st = state_from_dict({"x": rng.normal(0, 2, (p.N, 3)), "R": Rotation.random(p.N, random_state=1).as_matrix(),
                          "offset": np.zeros(p.N), "drift": np.zeros(p.N), "s": rng.normal(0, 2, (p.K, 3)),
                          "e": np.zeros(p.K), "odo_yaw": np.array([0.7])})
    lay = make_layout(p)
    assert lay.odo_yaw[0] >= 0
    f = FACTORS["odometry"](p, st, lay)
    num = np.zeros_like(f.J)
    for k in range(lay.n):
        h = np.zeros(lay.n)
        h[k] = 1e-6
        num[:, k] = (FACTORS["odometry"](p, retract(st, lay, h), lay).r
                     - FACTORS["odometry"](p, retract(st, lay, -h), lay).r) / 2e-6
    np.testing.assert_allclose(f.J, num, atol=1e-4 * np.abs(num).max())


@pytest.mark.parametrize("opt,value", [("outlier_threshold", float("nan")), ("outlier_threshold", -1.0),
                                       ("emission_sigma", float("inf")), ("robust_k", 0.0), ("max_iter", 0),
                                       ("noise", "magic"), ("loss", "l1")])
def test_bad_options_are_refused(opt, value):
    with pytest.raises(ValueError, match=opt):
        validate_options(**{opt: value})
    feats, _ = simulate_features(1, seed=0)
    with pytest.raises(ValueError, match=opt):
        calibrate(feats, **{opt: value})


def _as_pairs(feats, names, axis=(1.0, 0.0, 0.0)):
    """The DOAs of ``names`` reduced to what a mic pair along ``axis`` (x) measures: a unit vector on the cone."""
    d = feats["doa"].copy()
    m = d.array.isin(names).to_numpy()
    ux = d.loc[m, "ux"].to_numpy()
    d.loc[m, "uy"], d.loc[m, "uz"] = np.sqrt(1 - ux ** 2), 0.0
    return {**feats, "doa": d, "meta": {**feats["meta"], "doa_axes": {n: list(axis) for n in names}}}


@pytest.mark.parametrize("noise", [False, True])
def test_mic_pairs_calibrated_from_cones(noise):
    """Three 2-mic pairs + two full arrays: pair positions and axes recovered, roll reported undetermined."""
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=2, noise=noise)
    cal = calibrate(_as_pairs(feats, ["A2", "A3", "A4"]))
    a, t = cal["arrays"].set_index("array"), truth["arrays"].set_index("array")
    pos = np.linalg.norm((a[["x", "y", "z"]] - t[["x", "y", "z"]]).to_numpy(float), axis=1)
    q = ["qw", "qx", "qy", "qz"]
    ea = Rotation.from_quat(a[q].to_numpy(float), scalar_first=True).apply([1, 0, 0])
    ta = Rotation.from_quat(t[q].to_numpy(float), scalar_first=True).apply([1, 0, 0])
    axis_deg = np.rad2deg(np.arccos(np.clip(np.sum(ea * ta, axis=1), -1, 1)))
    tol_pos, tol_ax = (1e-6, 1e-4) if not noise else (0.06, 4.0)
    assert np.all(pos < tol_pos) and np.all(axis_deg < tol_ax), (pos, axis_deg)
    assert np.isnan(a.loc["A2", "rx_std"]) and np.isfinite(a.loc["A2", "ry_std"])     # roll about x
    assert {u["array"] for u in cal["report"]["undetermined"] if u["parameter"] == "roll"} == {"A2", "A3", "A4"}


def test_cli_exit_codes_for_failed_verdict_and_bad_options(tmp_path):
    """`calib estimate`: verdict printed last, exit 3 on failed (calibration still written), 2 on NaN options."""
    from typer.testing import CliRunner

    from calib.cli.main import app
    from calib.pipeline.formats.io import write_features

    feats, truth = simulate_features(2, 1e-4, 5.0, 0.03, seed=1001)
    bad, _ = bench.fault_t_emit(feats, truth, None)
    write_features(tmp_path / "f", bad)
    runner = CliRunner()
    r = runner.invoke(app, ["estimate", str(tmp_path / "f"), "-o", str(tmp_path / "c")])
    assert r.exit_code == 3, (r.stdout, r.stderr)
    assert r.stderr.rfind("verdict: FAILED") > r.stderr.rfind("converged:") >= 0   # the verdict comes last
    assert (tmp_path / "c" / "report.json").is_file()
    r = runner.invoke(app, ["estimate", str(tmp_path / "f"), "-o", str(tmp_path / "c2"), "--outlier-threshold", "nan"])
    assert r.exit_code == 2 and "--outlier-threshold" in r.stderr and not (tmp_path / "c2").exists()


@pytest.mark.slow
def test_report_first_line_states_the_verdict(tmp_path):
    from calib.pipeline.formats.io import read_calibration, write_calibration
    from calib.pipeline.report.summary import make_report

    feats, truth = simulate_features(2, 1e-4, 5.0, 0.03, seed=1001)
    for f, status in ((feats, "OK"), (bench.fault_t_emit(feats, truth, None)[0], "FAILED")):
        write_calibration(tmp_path / status / "cal", calibrate(f, **NO_TARGET))
        make_report(tmp_path / status / "rep", f, read_calibration(tmp_path / status / "cal"))
        first = (tmp_path / status / "rep" / "summary.md").read_text().splitlines()[0]
        assert first.endswith(f"verdict: {status}"), first


@pytest.mark.parametrize("turns", [1, -2])
def test_yaw_test_wraps_full_turns(turns):
    """A yaw of a whole number of turns plus a small angle is that small angle: not significant, and reported
    in (−180°, 180°] (a solve that wandered round the circle once is no rotated odometry)."""
    from calib.estimator.odoframe import yaw_decision

    feats, _ = simulate_features(3, seed=1)
    p = build_problem(feats, odometry_yaw=True)
    lay = make_layout(p)
    k = int(lay.odo_yaw[0])
    Jw = np.zeros((lay.n + 1, lay.n))
    Jw[np.arange(lay.n), np.arange(lay.n)] = 1.0 / np.deg2rad(1.0)    # every parameter's 1-σ: 1° (rad)
    st = state_from_dict({"x": np.zeros((p.N, 3)), "R": np.tile(np.eye(3), (p.N, 1, 1)), "offset": np.zeros(p.N),
                          "drift": np.zeros(p.N), "s": np.zeros((p.K, 3)), "e": np.zeros(p.K),
                          "odo_yaw": np.array([2 * np.pi * turns + np.deg2rad(0.5)])})
    _, _, test = yaw_decision(p, st, Jw, k)
    assert test["yaw_deg"] == pytest.approx(0.5) and test["std_deg"] == pytest.approx(1.0) and not test["kept"]


def test_block_statistic_is_the_quadratic_form_and_never_negative():
    # rᵀ (I ∓ H)⁻¹ r of a DOA block: as the direct solve for a regular hat block; a block whose leverage came out
    # above 1 (an ill-conditioned pseudo-inverse: 1.006 on another session's emission times) is clipped there, so
    # the statistic is finite and ≥ 0 (it had been negative, the sigma NaN and calib run an internal error)
    from calib.estimator.robust import _block_quadratic

    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 3, 3))
    V = np.linalg.qr(A)[0]
    lam = np.array([[0.2, 0.5, 0.9], [0.0, 0.3, 0.6], [0.1, 0.1, 0.1], [0.4, 0.7, 1.006], [0.0, 0.0, 1.0]])
    H = np.einsum("gij,gj,gkj->gik", V, lam, V)
    r = rng.normal(size=(5, 3))
    kept = np.array([True, False, True, True, True])
    q = _block_quadratic(H, kept, r)
    for g in range(3):   # regular blocks: the direct formula
        M = np.eye(3) + (-1 if kept[g] else 1) * H[g]
        assert q[g] == pytest.approx(r[g] @ np.linalg.solve(M, r[g]), rel=1e-10)
    assert np.all(np.isfinite(q)) and np.all(q >= 0)
    # the exactly fitted direction (λ ≥ 1) is left untested: only the other two count
    proj = np.einsum("ij,i->j", V[3], r[3])
    assert q[3] == pytest.approx(proj[0] ** 2 / 0.6 + proj[1] ** 2 / 0.3, rel=1e-10)
