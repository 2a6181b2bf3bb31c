"""Any array geometry (issue 10 item 4): what each geometry measures (frontend), the simulator's per-array
mic geometries, the calibration of mic pairs from simulated recordings, and per-parameter observability."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from calib.estimator import calibrate
from calib.frontend.doa import cone_vectors, fibonacci_sphere, mic_geometry, srp_cone
from calib.pipeline.simulate import roomsim as rs
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import write_calibration
from calib.pipeline.simulate.scenes import named_mics

C = 343.0


# ----------------------------------------------------------------------------------------------- frontend
@pytest.mark.parametrize("mics, kind", [
    ([[0, 0, 0]], "single"),
    ([[-0.05, 0, 0], [0.05, 0, 0]], "linear"),
    ([[0, -0.03, 0.01], [0, 0.0, 0.01], [0, 0.06, 0.01]], "linear"),
    (named_mics("circle", None, 6, 0.0354, 0), "planar"),
    (named_mics("octahedron", None, 6, 0, 0), "volume"),
])
def test_mic_geometry_kinds(mics, kind):
    k, vec = mic_geometry(mics)
    assert k == kind
    m = np.asarray(mics, float)
    if kind == "linear":   # the axis: unit, along the mics' line, largest component positive
        d = m - m.mean(0)
        assert np.isclose(np.linalg.norm(vec), 1) and np.allclose(np.cross(d, vec), 0, atol=1e-12)
        assert vec[np.argmax(np.abs(vec))] > 0
    if kind == "planar":
        assert np.allclose((m - m.mean(0)) @ vec, 0, atol=1e-12)


@pytest.mark.parametrize("mics", [[[-0.05, 0, 0], [0.05, 0, 0]],                      # 2-mic pair on x
                                  [[0.01, -0.045, 0.02], [0.01, 0.0, 0.02], [0.01, 0.045, 0.02]]])  # off-origin line
def test_srp_cone_measures_the_angle_to_the_axis(mics):
    # ideal gated spectra of a plane wave from u (mic m leads the origin by u·m / c), with noise: the cone
    # angle is measured, whatever the direction's azimuth about the axis
    mics = np.asarray(mics, float)
    _, axis = mic_geometry(mics)
    freqs = np.linspace(500, 4000, 57)
    u_true = fibonacci_sphere(60)
    rng = np.random.default_rng(1)
    g = np.exp(2j * np.pi * freqs[None, None, :] * (u_true @ mics.T)[:, :, None] / C)
    g *= np.exp(1j * rng.normal(0, 0.05, g.shape))
    cos_t, power = srp_cone(g, mics, axis, freqs, C)
    err = np.degrees(np.abs(np.arccos(cos_t) - np.arccos(u_true @ axis)))
    assert np.median(err) < 0.5 and err.max() < 3.0
    assert np.all(power > 0.9)
    u = cone_vectors(axis, cos_t)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0)
    np.testing.assert_allclose(u @ axis, cos_t, atol=1e-12)


# ----------------------------------------------------------------------------------------------- simulator
def test_scenario_geometries_per_array():
    sc = rs.make_scenario("paper-traj3", seed=2, n_arrays=5, mic_spacing=0.08,
                          geometries=["octahedron", "pair", "linear", "single"])
    mics = [np.asarray(a["mics"]) for a in sc["arrays"]]
    assert [len(m) for m in mics] == [6, 2, 6, 1, 6]
    assert mic_geometry(mics[0])[0] == "volume" and mic_geometry(mics[4])[0] == "planar"   # A5: default
    for m in mics[1:3]:
        assert mic_geometry(m) == ("linear", pytest.approx(np.array([1.0, 0, 0])))
        assert np.allclose(np.diff(m[:, 0]), 0.08) and np.allclose(m.mean(0), 0)
    rs.validate_scenario(sc)
    # the arrays' poses do not depend on their mic geometry
    base = rs.make_scenario("paper-traj3", seed=2, n_arrays=5)
    assert [a["position"] for a in base["arrays"]] == [a["position"] for a in sc["arrays"]]
    with pytest.raises(InputError, match="unknown geometry 'triangle'"):
        rs.make_scenario("paper-traj3", geometries=["triangle"])
    with pytest.raises(InputError, match="at most n_arrays"):
        rs.make_scenario("paper-traj3", n_arrays=2, geometries=["pair"] * 3)


# ----------------------------------------------------------------------------------------------- estimator
def _cones(feats, axes):
    """The DOAs of the arrays in ``axes`` ({name: axis in the array frame}) reduced to what a linear array
    measures: one unit vector on the cone of the true angle to the axis (the frontend's choice)."""
    d = feats["doa"].copy()
    for name, ax in axes.items():
        m = (d.array == name).to_numpy()
        a = np.asarray(ax, float) / np.linalg.norm(ax)
        u = d.loc[m, ["ux", "uy", "uz"]].to_numpy()
        d.loc[m, ["ux", "uy", "uz"]] = cone_vectors(a, u @ a)
    return {**feats, "doa": d, "meta": {**feats["meta"], "doa_axes": {k: list(v) for k, v in axes.items()}}}


def test_pairs_along_any_axis_of_their_frame():
    """A pair whose axis is not a coordinate axis of its frame: the axis direction is recovered exactly from
    noise-free data, and the evaluation scores it by the axis (the roll is not scored)."""
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=4, noise=False)
    axes = {"A2": [0.6, 0.0, 0.8], "A3": [0.0, -1.0, 0.0], "A4": [0.5, 0.5, -0.7071]}
    cal = calibrate(_cones(feats, axes))
    m = evaluate(cal, truth)
    per = {r["array"]: r for r in m["per_array"]}
    for name in axes:
        assert per[name]["position_m"] < 1e-5 and per[name]["axis_deg"] < 1e-3, per[name]
        assert np.isnan(per[name]["geodesic_deg"])
    assert per["A5"]["geodesic_deg"] < 1e-3 and np.isnan(per["A5"]["axis_deg"])
    assert {u["array"] for u in cal["report"]["undetermined"] if u["parameter"] == "roll"} == set(axes)


def _keep_events(feats, name, events):
    """``feats`` with array ``name``'s measurements restricted to ``events``."""
    f = dict(feats)
    for k in ("tdoa_m", "doa"):
        d = feats[k]
        f[k] = d[(d.array != name) | d.event.isin(events)].reset_index(drop=True)
    d = feats["tdoa_s"]
    f["tdoa_s"] = d[(d.array != name) | (d.from_event.isin(events) & d.to_event.isin(events))].reset_index(drop=True)
    return f


@pytest.mark.parametrize("seed", [5, 6])
def test_undetermined_parameters_are_reported_and_the_rest_calibrated(seed, tmp_path):
    """One array with too few measurements no longer stops the calibration: what it leaves undetermined is
    named per parameter (NaN std, not scored), every other array is calibrated as well as without it."""
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=seed)
    clean = {r["array"]: r for r in evaluate(calibrate(feats), truth)["per_array"]}
    # A4 without TDOA-M: its clock offset alone is undetermined (its position follows from TDOA-S and DOAs)
    f = dict(feats)
    f["tdoa_m"] = feats["tdoa_m"][feats["tdoa_m"].array != "A4"].reset_index(drop=True)
    # A4 seen in 2 events only: 7 measurements for its 8 parameters
    two = _keep_events(feats, "A4", sorted(feats["events"].event)[:2])
    for f, expect in ((f, {"offset"}), (two, {"position"})):
        cal = calibrate(f)
        und = {u["parameter"] for u in cal["report"]["undetermined"] if u["array"] == "A4"}
        assert expect <= und and all(u["array"] == "A4" for u in cal["report"]["undetermined"]), und
        a = cal["arrays"].set_index("array")
        cols = {"offset": ["offset_std"], "position": ["x_std", "y_std", "z_std"], "drift": ["drift_std"],
                "orientation": ["rx_std", "ry_std", "rz_std"]}
        for u in und:
            assert a.loc["A4", cols[u]].isna().all()
        per = {r["array"]: r for r in evaluate(cal, truth)["per_array"]}
        if "position" in und:
            assert np.isnan(per["A4"]["position_m"])
        else:
            assert per["A4"]["position_m"] < 1.5 * clean["A4"]["position_m"] + 0.02
        for name in ("A2", "A3", "A5"):
            assert per[name]["position_m"] < 1.5 * clean[name]["position_m"] + 0.01, (name, per[name])
            assert np.all(np.isfinite(a.loc[name, ["x_std", "rx_std", "offset_std", "drift_std"]].to_numpy(float)))
        # calibration.json marks them too, and its covariance (rebuilt from disk) leaves them out
        out = tmp_path / "_".join(sorted(expect))
        write_calibration(out, cal, features=f)
        doc = json.loads((out / "calibration.json").read_text())
        entry = {e["name"]: e for e in doc["arrays"]}
        assert set(entry["A4"]["undetermined"]) == und and entry["A2"]["undetermined"] == []
        labels = doc["covariance"]["parameters"]
        key = {"offset": "offset", "position": "x", "drift": "drift", "orientation": "rx"}
        assert "A2.offset" in labels and not any(f"A4.{key[u]}" in labels for u in und)
        assert np.all(np.isfinite(doc["covariance"]["matrix"]))


# ----------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_mic_pairs_from_simulated_recordings_cli(tmp_path):
    """Issue 10's acceptance session: 3 two-mic pairs + a 6-mic reference array simulated as recordings
    (`calib simulate --set`), calibrated by `calib run`: the frontend writes cone DOAs for the pairs, pair
    positions within 5 cm, axes within 3°, the roll about each axis reported undetermined (NaN std)."""
    from typer.testing import CliRunner

    from calib.cli.main import app
    from calib.pipeline.report.evaluate import feature_errors
    from calib.pipeline.formats.io import read_calibration, read_features

    rec, out = tmp_path / "rec", tmp_path / "out"
    runner = CliRunner()
    r = runner.invoke(app, ["simulate", "-o", str(rec), "--preset", "paper-traj3", "--seed", "3", "--set", "n_arrays=4",
                            "--set", 'geometries=["octahedron", "pair", "pair", "pair"]'])
    assert r.exit_code == 0, r.stderr
    r = runner.invoke(app, ["run", str(rec), "-o", str(out)])
    assert r.exit_code == 0, r.stderr
    feats = read_features(out / "features")
    assert feats["meta"]["doa_axes"] == {n: [1.0, 0.0, 0.0] for n in ("A2", "A3", "A4")}
    sc = rs.load_scenario(rec / "truth" / "manifest.json")
    cone = feature_errors(feats, sc)["cone"]
    pairs = feats["doa"].array.isin(["A2", "A3", "A4"]).to_numpy()
    assert np.all(np.isfinite(cone[pairs])) and np.all(np.isnan(cone[~pairs]))
    assert np.median(cone[pairs]) < 0.5
    metrics = json.loads((out / "report" / "metrics.json").read_text())
    per = {m["array"]: m for m in metrics["per_array"]}
    for name in ("A2", "A3", "A4"):
        assert per[name]["position_m"] <= 0.05 and per[name]["axis_deg"] <= 3.0, per[name]
    cal = read_calibration(out / "calibration")
    assert {u["array"] for u in cal["report"]["undetermined"] if u["parameter"] == "roll"} == {"A2", "A3", "A4"}
    a = cal["arrays"].set_index("array")
    assert a.loc[["A2", "A3", "A4"], "rx_std"].isna().all() and np.isfinite(a.loc[["A2", "A3", "A4"], "ry_std"]).all()


@pytest.mark.slow
def test_single_mic_and_linear_array_from_simulated_recordings(tmp_path):
    """A single microphone gets no DOA rows (position and clock from the TDOAs, orientation reported
    undetermined); a 4-mic linear array gets cone rows; the 3-D reference full DOAs."""
    from calib.pipeline.report.evaluate import feature_errors
    from calib.pipeline.formats.io import read_features
    from calib.pipeline.run import run

    sc = rs.make_scenario("paper-traj1", seed=1, n_arrays=4, geometries=["octahedron", "single", "linear", "pair"],
                          n_mics=4, mic_spacing=0.04)
    rs.simulate(sc, tmp_path / "rec")
    res = run(tmp_path / "rec", tmp_path / "out")
    feats = read_features(tmp_path / "out" / "features")
    assert "A2" not in set(feats["doa"].array) and "A2" in set(feats["tdoa_m"].array)
    assert set(feats["meta"]["doa_axes"]) == {"A3", "A4"}
    e = feature_errors(feats, sc)
    ref = (feats["doa"].array == "A1").to_numpy()
    assert np.median(e["doa"][ref]) < 1.0 and np.median(e["cone"][~ref]) < 0.5
    per = {m["array"]: m for m in res["metrics"]["per_array"]}
    assert all(per[n]["position_m"] < 0.05 for n in ("A2", "A3", "A4")), per
    und = {(u["array"], u["parameter"]) for u in res["calibration"]["report"]["undetermined"]}
    assert {("A2", "orientation"), ("A3", "roll"), ("A4", "roll")} <= und


def test_reflection_flagged_cone_rows_share_their_axis_rotation():
    """A wall board's reflection pulls all its cones the same way (measured against truth on development seeds: an
    axis rotation of RMS 0.82 × the median row sigma per axis for cone arrays with most rows flagged
    ``doa_reflection``, 0.27 for the others): every cone row of a pair measured about an axis turned by 3 of its
    row sigma. Flagged, the pair's axis error against the true axis stays within 3 of its stated std
    (``uncertainty.shared_cone_rows``: 2.0); the same rows without the flag (SHARED_CONE_FRACTION's smaller share)
    leave it beyond 3σ (3.6), as did the flagged ones before the term (3.9)."""
    from calib.estimator import uncertainty as U

    feats, truth = simulate_features(3, 1e-5, 1.0, 0.03, seed=7)
    feats = dict(feats)
    sd = np.radians(feats["meta"]["sigma_doa_deg"])
    m = (feats["doa"].array == "A2").to_numpy()
    doa = feats["doa"].copy()
    bias = Rotation.from_rotvec(3.0 * sd * np.array([0.0, 0.6, 0.8]))   # about an axis ⟂ the pair's x axis
    doa.loc[m, ["ux", "uy", "uz"]] = bias.inv().apply(doa.loc[m, ["ux", "uy", "uz"]].to_numpy(float, copy=True))   # cos = (B a)ᵀ u
    feats["doa"] = doa
    feats = _cones(feats, {"A2": [1.0, 0.0, 0.0]})
    R_true = Rotation.from_quat(truth["arrays"].set_index("array").loc["A2", ["qw", "qx", "qy", "qz"]].to_numpy(float, copy=True),
                                scalar_first=True)

    def axis_error_over_std(flag):
        d = feats["doa"].copy()
        d["flag"] = np.where(d["array"] == "A2", flag, "")
        a = calibrate({**feats, "doa": d}, noise="meta")["arrays"].set_index("array").loc["A2"]
        R = Rotation.from_quat(a[["qw", "qx", "qy", "qz"]].to_numpy(float, copy=True), scalar_first=True)
        err = np.arccos(np.clip(R.apply([1.0, 0, 0]) @ R_true.apply([1.0, 0, 0]), -1, 1))
        return err / np.linalg.norm(a[["ry_std", "rz_std"]].to_numpy(float))   # the components that turn the axis

    assert axis_error_over_std("doa_reflection") < 3.0
    assert axis_error_over_std("") > 3.0
