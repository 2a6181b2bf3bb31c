"""`pipeline.report.summary`: residuals in natural units against the injected noise, outlier masks and
covariances rebuilt from files, the report folder (atomic), and a real data set with a known outlier."""
import json
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from calib.pipeline.report import summary as report
from calib.estimator import calibrate
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import read_calibration, read_features, read_truth, write_calibration

from .sessions import REAL_WORLD as REAL


def _truth_calib(truth):
    return {"arrays": truth["arrays"], "sources": truth["sources"], "report": {}}


def test_residuals_at_truth_are_the_injected_noise():
    noisy, truth = simulate_features(trajectory=3, seed=11, sigma_tdoa=1e-4, sigma_doa_deg=5.0, sigma_odo=0.02)
    clean, _ = simulate_features(trajectory=3, seed=11, sigma_tdoa=1e-4, sigma_doa_deg=5.0, sigma_odo=0.02,
                                 noise=False)
    res = report.residuals(report.rebuild(noisy, _truth_calib(truth)))
    assert set(res) == {"tdoa_s", "tdoa_m", "doa", "odometry"}
    for kind in ("tdoa_s", "tdoa_m"):  # residual = model − measured = clean − noisy, in µs
        want = (clean[kind]["tdoa"].to_numpy() - noisy[kind]["tdoa"].to_numpy()) * 1e6
        np.testing.assert_allclose(res[kind]["values"], want, atol=1e-6)
        assert res[kind]["unit"] == "µs" and res[kind]["sigma"] == pytest.approx(100.0)
        assert not res[kind]["outlier"].any()
    u0 = clean["doa"][["ux", "uy", "uz"]].to_numpy()
    u1 = noisy["doa"][["ux", "uy", "uz"]].to_numpy()
    ang = np.degrees(np.arccos(np.clip(np.sum(u0 * u1, axis=1), -1, 1)))
    np.testing.assert_allclose(res["doa"]["values"], ang, atol=1e-5)
    steps = lambda f: np.diff(f["events"][["odom_x", "odom_y", "odom_z"]].to_numpy(), axis=0)  # noqa: E731
    np.testing.assert_allclose(res["odometry"]["values"], ((steps(clean) - steps(noisy)) * 100).ravel(), atol=1e-9)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A feature-level scene with one gross TDOA-M error, calibrated and written to disk."""
    feats, truth = simulate_features(trajectory=3, seed=4, sigma_tdoa=5e-5, sigma_doa_deg=3.0)
    feats["meta"].update(sigma_tdoa=2e-4, sigma_doa_deg=6.0)  # stated 4x and 2x too large
    tm = feats["tdoa_m"]
    row = int(np.flatnonzero((tm["event"] == 3).to_numpy() & (tm["array"] == "A3").to_numpy())[0])
    tm.loc[row, "tdoa"] += 5e-3
    calib = calibrate(feats, noise="estimate")  # weights differ from meta.json: the report must use them
    d = tmp_path_factory.mktemp("cal") / "calibration"
    write_calibration(d, calib)
    return feats, truth, calib, read_calibration(d), row


def test_rebuilt_model_matches_the_estimator(calibrated):
    feats, _, calib, from_disk, row = calibrated
    model = report.rebuild(feats, from_disk)
    res = report.residuals(model)
    assert np.flatnonzero(res["tdoa_m"]["outlier"]).tolist() == [row]
    assert res["tdoa_m"]["values"][row] == pytest.approx(-5000, abs=300)  # the typed-in 5 ms, in µs
    assert not res["tdoa_s"]["outlier"].any()
    # covariance blocks rebuilt from the files = the estimator's own 1-σ columns
    cov_a, cov_s = report.position_covariances(model)
    a = calib["arrays"]
    np.testing.assert_allclose(np.sqrt(np.diagonal(cov_a[1:], axis1=1, axis2=2)),
                               a[["x_std", "y_std", "z_std"]].to_numpy()[1:], rtol=1e-4)
    assert np.isnan(cov_a[0]).all()  # the reference array is fixed
    np.testing.assert_allclose(np.sqrt(np.diagonal(cov_s, axis1=1, axis2=2)),
                               calib["sources"][["x_std", "y_std", "z_std"]].to_numpy(), rtol=1e-4)
    # RMS of the inliers as in the estimator's report
    for kind in ("tdoa_s", "tdoa_m"):
        v = res[kind]["values"][~res[kind]["outlier"]]
        assert np.sqrt(np.mean(v ** 2)) == pytest.approx(calib["report"]["residuals"][kind]["rms_us"], rel=1e-4)


@pytest.mark.slow
def test_report_folder(calibrated, tmp_path):
    feats, truth, _, from_disk, row = calibrated
    out = tmp_path / "report"
    metrics = report.make_report(out, feats, from_disk, truth=truth)
    assert metrics["position_rmse_m"] == pytest.approx(evaluate(from_disk, truth)["position_rmse_m"])
    assert json.loads((out / "metrics.json").read_text())["position_rmse_m"] == pytest.approx(
        metrics["position_rmse_m"])
    for png in ("scene_3d.png", "residuals.png"):
        img = matplotlib.image.imread(out / png)
        assert img.shape[0] > 300 and img.shape[1] > 600
    md = (out / "summary.md").read_text()
    for name in feats["meta"]["arrays"]:
        assert f"| {name} |" in md
    ev = feats["tdoa_m"].loc[row]
    assert f"tdoa_m (event {ev['event']}, array {ev['array']}), features/tdoa_m.csv line {row + 2}:" in md
    assert "](scene_3d.png)" in md and "](residuals.png)" in md and "Evaluation against ground truth" in md
    # without truth: no metrics
    assert report.make_report(tmp_path / "r2", feats, from_disk) is None
    assert not (tmp_path / "r2" / "metrics.json").exists()
    assert "Evaluation" not in (tmp_path / "r2" / "summary.md").read_text()


@pytest.mark.slow
def test_failed_report_leaves_previous_one(calibrated, tmp_path, monkeypatch):
    feats, _, _, from_disk, _ = calibrated
    out = tmp_path / "report"
    report.make_report(out, feats, from_disk)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def boom(*a, **k):
        raise RuntimeError("plot failed (injected)")

    monkeypatch.setattr(report, "plot_residuals", boom)
    with pytest.raises(RuntimeError, match="injected"):
        report.make_report(out, feats, from_disk)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["report"]


def test_nice_scale():
    assert [report._nice_scale(x) for x in (0.3, 1.0, 1.5, 3.0, 7.0, 11.0, 4000.0)] == [1, 1, 2, 5, 10, 20, 5000]


@pytest.mark.skipif(not (REAL / "zhang_real_07").is_dir(), reason="shared real-world data not available")
def test_real_set_07_reports_its_known_outlier(tmp_path):
    """Set 07 has a TDOA-M of array A3 off by about 40 ms (shared/real_world/README.md)."""
    feats = read_features(REAL / "zhang_real_07" / "features")
    truth = read_truth(REAL / "zhang_real_07" / "truth")
    d = tmp_path / "calibration"
    write_calibration(d, calibrate(feats))
    m = report.make_report(tmp_path / "report", feats, read_calibration(d), truth=truth)
    md = (tmp_path / "report" / "summary.md").read_text()
    line = [s for s in md.splitlines() if s.startswith("- tdoa_m (") and "array A3" in s]
    assert len(line) == 1 and 30000 < abs(float(line[0].split("residual ")[1].split(" µs")[0])) < 50000
    assert m["position_rmse_m"] < 0.15


@pytest.mark.parametrize("dist", ["normal", "rayleigh"])
def test_expected_density_is_the_rows_mixture(dist):
    from scipy import stats

    law = stats.norm if dist == "normal" else stats.rayleigh
    x = np.linspace(-8.0 if dist == "normal" else 0.0, 8.0, 4001)
    one = report.expected_density(x, np.full(7, 1.3), dist)
    np.testing.assert_allclose(one, law.pdf(x, scale=1.3), rtol=1e-12, atol=1e-15)
    rows = np.array([0.5, 0.5, 0.5, 2.0])  # three rows at 0.5, one at 2: weights 3/4 and 1/4
    mix = report.expected_density(x, rows, dist)
    np.testing.assert_allclose(mix, 0.75 * law.pdf(x, scale=0.5) + 0.25 * law.pdf(x, scale=2.0), rtol=1e-12,
                               atol=1e-15)
    assert np.sum(mix) * (x[1] - x[0]) == pytest.approx(1.0, abs=2e-3)  # a density (Riemann sum)


def test_doa_rows_with_their_own_sigmas_in_residuals_and_summary(calibrated, tmp_path):
    feats, truth, _, _, _ = calibrated
    feats = {**feats, "doa": feats["doa"].copy()}
    own = np.where(np.arange(len(feats["doa"])) % 3 == 0, 12.0, 3.0)  # deg per axis; the type's is 6
    feats["doa"]["sigma_deg"] = own
    calib = calibrate(feats)  # sigmas as stated (meta), so the type's DOA sigma stays 6°
    res = report.residuals(report.rebuild(feats, calib))["doa"]
    # the row's sigma: √(½ m² + ½ own²), m = 3° the median row's (docs/method.md), whatever rows the estimator kept
    np.testing.assert_allclose(res["row_sigma"], np.sqrt(0.5 * 3.0**2 + 0.5 * own**2), rtol=1e-9)
    assert res["sigma"] == pytest.approx(6.0)
    md = report.summary_markdown(feats, calib, {"doa": res}, None, None, {"scene": "s.png", "residuals": "r.png"})
    lo, hi = np.sqrt(0.5 * 9.0 + 0.5 * 9.0), np.sqrt(0.5 * 9.0 + 0.5 * 144.0)
    assert f"per row: median {lo:.3g}, {lo:.3g}–{hi:.3g} deg/axis" in md  # two thirds of the rows at 3°
    assert f"{len(own)} rows at {lo / 6:.2f}–{hi / 6:.2f}× the type's σ" in md
    report.plot_residuals(tmp_path / "r.png", {"doa": res})
    assert matplotlib.image.imread(tmp_path / "r.png").shape[0] > 100


def _calibration_with_an_array_component():
    """A scene whose noisiest array (5x the DOA noise) got a sigma of its own, calibrated (the first of a
    few seeds where the array tests did not drop it instead)."""
    from .test_arraynoise import _noisy_doas

    for seed in range(6):
        feats, _ = simulate_features(3, 1e-4, 5.0, 0.03, seed=2000 + seed)
        feats = _noisy_doas(feats, feats["meta"]["arrays"][1 + seed % 4], 5.0, np.random.default_rng(seed))
        calib = calibrate(feats, noise="estimate", array_noise=True)
        if any(calib["report"]["sigmas"]["per_array_factor"].values()):
            return feats, calib
    pytest.fail("no array got a component of its own in 6 scenes with one array at 5x the DOA noise")


def test_rebuilt_model_leaves_out_the_rows_the_estimator_screened(tmp_path):
    """Reflection-only rows (flag ``nlos``, 3 ms late) are screened before the solve: a calibration read back from
    disk must leave them out too, or the report's residual table shows them as fitted and the covariance counts
    them as information."""
    stops = np.cumsum(np.random.default_rng(11).normal(0, 0.4, (12, 3)), axis=0) * [1, 1, 0.2] + [0, 0, 1.2]
    feats, _ = simulate_features(trajectory=stops, seed=11, n_arrays=5)
    for name in ("tdoa_m", "tdoa_s", "doa"):
        df = feats[name]
        ev = df["event"] if "event" in df else df["to_event"]
        late = (df["array"] == "A3").to_numpy() & ev.isin([4, 5]).to_numpy()
        df["flag"] = np.where(late, "nlos", "")
        if name != "doa":
            df.loc[late, "tdoa"] += 3e-3
    calib = calibrate(feats)
    assert len(calib["report"]["screened"]["rows"]) == 6
    write_calibration(tmp_path / "c", calib, features=feats)
    model = report.rebuild(feats, read_calibration(tmp_path / "c"))
    res = report.residuals(model)
    for kind in ("tdoa_s", "tdoa_m"):
        assert len(res[kind]["values"]) == calib["report"]["residuals"][kind]["n"]
        assert np.sqrt(np.mean(res[kind]["values"] ** 2)) == pytest.approx(
            calib["report"]["residuals"][kind]["rms_us"], rel=1e-4)
    cov_a, _ = report.position_covariances(model)
    np.testing.assert_allclose(np.sqrt(np.diagonal(cov_a[1:], axis1=1, axis2=2)),
                               calib["arrays"][["x_std", "y_std", "z_std"]].to_numpy()[1:], rtol=1e-4)


def test_rebuilt_model_keeps_the_arrays_own_sigmas(tmp_path):
    """With per-array components (array_noise=True), the report's covariances and row sigmas are the
    estimator's."""
    feats, calib = _calibration_with_an_array_component()
    d = tmp_path / "calibration"
    write_calibration(d, calib)
    model = report.rebuild(feats, read_calibration(d))
    cov_a, _ = report.position_covariances(model)
    np.testing.assert_allclose(np.sqrt(np.diagonal(cov_a[1:], axis1=1, axis2=2)),
                               calib["arrays"][["x_std", "y_std", "z_std"]].to_numpy()[1:], rtol=1e-4)
    res = report.residuals(model)
    sig = calib["report"]["sigmas"]
    for kind, own in sig["per_array_factor"].items():
        typ = np.rad2deg(sig["doa_rad_per_axis"]) if kind == "doa" else sig[kind] * 1e6
        want = typ * np.array([own.get(a, 1.0) for a in feats[kind]["array"]])
        arrival = sig.get("arrival_scale") or {}   # each array's arrival scale (variance.estimate_arrival_scales)
        ref = feats["meta"]["reference_array"]
        if kind == "tdoa_s":
            want = want * np.array([arrival.get(a, 1.0) for a in feats[kind]["array"]])
        elif kind == "tdoa_m":
            want = want * np.array([np.sqrt((arrival.get(a, 1.0) ** 2 + arrival.get(ref, 1.0) ** 2) / 2)
                                    for a in feats[kind]["array"]])
        np.testing.assert_allclose(res[kind]["row_sigma"], want, rtol=1e-9)


def test_a_fast_clock_s_note_is_in_the_summary_s_clock_section():
    """The set-up check's note on an array taken at its measured rate (report.json ``setup``, status note,
    check "sample rate") is a line of summary.md's Clocks section, with the clock's own findings; other notes
    and the verdict's set-up reasons are not repeated there."""
    fast = {"status": "note", "what": "A2.wav", "check": "sample rate", "array": "A2",
            "text": "A2.wav (array A2): its clock runs +938 ppm against the emission times"}
    other = {"status": "note", "what": "events.csv", "check": "trajectory", "text": "a mirror refitted"}
    wrong = {"status": "suspect", "what": "A3.wav", "check": "sample rate", "text": "A3.wav: the header's rate"}
    lines = report.clock_lines({"findings": ["A4: a step of -20 ms"]}, [fast, other, wrong])
    assert lines[0] == "## Clocks" and f"- {fast['text']}" in lines and "- A4: a step of -20 ms" in lines
    assert not any(other["text"] in x or wrong["text"] in x for x in lines)
    assert report.clock_lines({}, [other]) == []
