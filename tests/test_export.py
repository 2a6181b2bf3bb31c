"""calibration.json, the exports and the typed results, against independent maths (hand-written quaternion
matrices, the feature simulator's clock model, parsers of each output format)."""
import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from calib.cli.main import app
from calib.estimator import calibrate
from calib.pipeline.formats.calibration_json import calibration_document, reference_offset
from calib.pipeline.formats.export import FORMATS, export
from calib.pipeline.simulate.featsim import arrival_times, simulate_features
from calib.pipeline.formats.io import read_calibration, write_calibration
from calib.pipeline.formats.results import from_document, load_calibration

TOL = 1e-9  # m: the acceptance tolerance of mics_reference and the pyroomacoustics export


def quat_matrix(q):
    """Rotation matrix of a scalar-first unit quaternion, written out (independent of scipy)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rpy_matrix(r, p, y):
    """URDF's fixed-axis roll-pitch-yaw: Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A calibration of simulated features with random mic geometries (3 to 8 mics per array)."""
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=3)
    rng = np.random.default_rng(7)
    names = feats["meta"]["arrays"]
    feats["meta"]["mics"] = {n: rng.uniform(-0.1, 0.1, (rng.integers(3, 9), 3)).tolist() for n in names}
    cal = calibrate(feats)
    d = tmp_path_factory.mktemp("cal") / "calibration"
    write_calibration(d, cal, features=feats)
    return d, feats, truth


def test_mics_reference_and_pyroomacoustics_equal_R_m_plus_x(calibrated, tmp_path):
    d, feats, _ = calibrated
    arrays = read_calibration(d)["arrays"].set_index("array")
    doc = json.loads((d / "calibration.json").read_text())
    expect = []
    for entry in doc["arrays"]:
        row = arrays.loc[entry["name"]]
        m = np.asarray(feats["meta"]["mics"][entry["name"]])
        ref = m @ quat_matrix(row[["qw", "qx", "qy", "qz"]].to_numpy(float)).T + row[["x", "y", "z"]].to_numpy(float)
        assert np.abs(np.asarray(entry["mics_reference"]) - ref).max() < TOL
        assert np.allclose(entry["mics"], m, atol=0, rtol=0)
        expect.append(ref)
    assert [e["name"] for e in doc["arrays"]] == feats["meta"]["arrays"]  # calibration order
    npy = np.load(export(load_calibration(d), "pyroomacoustics", tmp_path / "R.npy"))
    assert npy.shape == (3, sum(len(e) for e in expect))
    assert np.abs(npy - np.vstack(expect).T).max() < TOL


def test_self_describing_header_and_covariance_match_the_std_columns(calibrated):
    d, feats, _ = calibrated
    doc = json.loads((d / "calibration.json").read_text())
    assert doc["format"] == "calib-calibration" and doc["format_version"] == 1
    assert doc["reference_array"] == feats["meta"]["reference_array"]
    assert "scalar-first" in doc["conventions"]["quaternion"] and doc["units"]["position"] == "m"
    cov = np.asarray(doc["covariance"]["matrix"])
    labels = doc["covariance"]["parameters"]
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > -1e-12 * np.abs(cov).max()
    arrays = read_calibration(d)["arrays"].set_index("array")
    col = {"x": "x_std", "y": "y_std", "z": "z_std", "rx": "rx_std", "ry": "ry_std", "rz": "rz_std",
           "offset": "offset_std", "drift": "drift_std"}
    for k, lab in enumerate(labels):
        name, par = lab.split(".")
        assert np.sqrt(cov[k, k]) == pytest.approx(arrays.loc[name, col[par]], rel=1e-6)
    ref = feats["meta"]["reference_array"]
    assert not any(lab.startswith(f"{ref}.x") or lab == f"{ref}.offset" for lab in labels)  # the gauge
    assert doc["odometry_frame"] is None  # not estimated here: stated as absent


def test_reference_offset_and_clock_conversions_follow_the_simulators_clock_model():
    feats, truth = simulate_features(2, seed=5, noise=False)
    tau_ref, beta, c = 0.4321, 0.23, feats["meta"]["speed_of_sound"]
    arr, src, ev = truth["arrays"], truth["sources"], feats["events"]
    t = ev["t_emit"].to_numpy() - ev["t_emit"].iloc[0]
    x, s = arr[["x", "y", "z"]].to_numpy(), src[["x", "y", "z"]].to_numpy()
    local = arrival_times(x, s, t, arr["offset"].to_numpy() + tau_ref, arr["drift"].to_numpy(), c, beta)  # (N, K)
    ref = list(arr["array"]).index(feats["meta"]["reference_array"])
    meta = {**feats["meta"], "chirp_drift_bias": beta,
            "reference_detections_s": {str(e): float(v) for e, v in zip(ev["event"], local[ref])}}
    tau, sd, n = reference_offset(meta, arr, src, ev)
    assert tau == pytest.approx(tau_ref, abs=1e-12) and n == len(ev)
    cal = from_document(calibration_document({"arrays": arr, "sources": src, "report": {}},
                                             {**feats, "meta": meta}))
    d = np.linalg.norm(s[None] - x[:, None], axis=2)
    for i, name in enumerate(arr["array"]):
        emit = cal.to_emitter_time(name, local[i], chirp=True)
        assert np.abs(emit - (ev["t_emit"].to_numpy() + d[i] / c)).max() < 1e-12
        assert np.abs(cal.to_local_time(name, emit, chirp=True) - local[i]).max() < 1e-12
        # the reference array's clock reading of the same instants
        assert np.abs(cal.to_reference_time(name, local[i], chirp=True) -
                      (1 + arr["drift"].iloc[ref]) * (emit - ev["t_emit"].iloc[0]) - tau_ref -
                      beta * arr["drift"].iloc[ref]).max() < 1e-12


def _parse_odas(folder):
    """{array: its configuration} of an odas export, each read by libconf (libconfig syntax, as ODAS reads it)."""
    import libconf

    return {p.stem: libconf.loads(p.read_text()) for p in sorted(folder.glob("*.cfg"))}


def _parse_urdf(text):
    root = ET.fromstring(text)
    joints = {j.find("child").get("link"): (j.find("parent").get("link"),
                                           np.array(j.find("origin").get("xyz").split(), float),
                                           np.array(j.find("origin").get("rpy").split(), float))
              for j in root.iter("joint")}

    def pose(link):
        if link not in joints:
            return np.eye(3), np.zeros(3)
        parent, xyz, rpy = joints[link]
        Rp, tp = pose(parent)
        return Rp @ rpy_matrix(*rpy), Rp @ xyz + tp

    return joints, pose


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_export_round_trips(calibrated, tmp_path, fmt):
    d, feats, _ = calibrated
    cal = load_calibration(d)
    path = export(cal, fmt, tmp_path / f"out.{fmt}")
    mics_ref = {a.name: cal.mics("reference", a.name) for a in cal.arrays}
    if fmt == "json":
        back = load_calibration(path)
        assert back.document == cal.document
    elif fmt == "yaml":
        y = yaml.safe_load(path.read_text())
        for name, m in mics_ref.items():
            T = np.asarray(y[name]["T_ref_array"])
            mm = np.asarray(y[name]["mics"])
            assert np.abs(mm @ T[:3, :3].T + T[:3, 3] - m).max() < TOL
            assert np.allclose(T[:3, :3], quat_matrix(np.asarray(y[name]["quaternion_wxyz"])), atol=1e-12)
        assert y["calib"]["reference_array"] == cal.reference_array
    elif fmt == "pyroomacoustics":
        assert np.abs(np.load(path) - np.vstack(list(mics_ref.values())).T).max() < TOL
    elif fmt == "odas":
        configs = _parse_odas(path)
        assert sorted(configs) == sorted(cal.names)  # one complete configuration per array
        for a in cal.arrays:  # array-centred, reference axes: mics_reference − position
            g = configs[a.name]["general"]
            mu = np.array([m["mu"] for m in g["mics"]])
            assert np.abs(mu - (mics_ref[a.name] - a.position)).max() < TOL
            z = a.rotation.as_matrix()[:, 2]  # the spatial filter: the half-space the array's mics face
            assert len(g["spatialfilters"]) == 1 and np.allclose(g["spatialfilters"][0]["direction"], z)
            assert configs[a.name]["raw"]["nChannels"] == len(mu) == len(configs[a.name]["mapping"]["map"])
            assert {"sne", "ssl", "sst", "sss", "classify"} <= set(configs[a.name])
    elif fmt == "urdf":
        joints, pose = _parse_urdf(path.read_text())
        for a in cal.arrays:
            for k, m in enumerate(mics_ref[a.name]):
                R, t = pose(f"{a.name}_mic{k}")
                assert np.abs(t - m).max() < TOL
    elif fmt == "tf":
        lines = [ln for ln in path.read_text().splitlines() if ln.startswith("ros2 run")]
        assert len(lines) == len(cal.arrays) - 1
        for ln in lines:
            args = dict(re.findall(r"--(\S+) (\S+)", ln))
            a = cal.array(args["child-frame-id"])
            assert args["frame-id"] == cal.reference_array
            q = np.array([float(args[k]) for k in ("qw", "qx", "qy", "qz")])
            assert np.allclose(quat_matrix(q), a.rotation.as_matrix(), atol=1e-12)
            assert np.abs(np.array([float(args[k]) for k in "xyz"]) - a.position).max() < TOL


def test_typed_views_have_public_columns_only(calibrated):
    d, _, _ = calibrated
    cal = load_calibration(d)
    df = cal.arrays_frame()
    assert list(df.columns[:10]) == ["array", "x", "y", "z", "qw", "qx", "qy", "qz", "offset", "drift"]
    assert not any(str(c).startswith("_") for c in df.columns)
    assert not any(str(c).startswith("_") for c in read_calibration(d)["arrays"].columns)
    # mics in an array's own frame round-trip through the reference frame
    a = cal.arrays[1]
    assert np.abs(cal.mics(a.name, array=a.name) - a.mics).max() < 1e-12
    # the same typed object straight from the estimator's in-memory result
    from calib.pipeline.formats.results import to_calibration

    feats = calibrated[1]
    mem = to_calibration(calibrate(feats), feats)
    assert np.allclose(mem.arrays_frame()[["x", "y", "z"]], df[["x", "y", "z"]], atol=1e-9)


def test_export_cli_and_bad_input(calibrated, tmp_path):
    d, _, _ = calibrated
    r = CliRunner().invoke(app, ["export", str(d), "--format", "odas", "-o", str(tmp_path / "odas"), "-q"])
    assert r.exit_code == 0, r.output
    assert len(list((tmp_path / "odas").glob("*.cfg"))) == len(load_calibration(d).arrays)
    r = CliRunner().invoke(app, ["export", str(d), "--format", "vrml", "-o", str(tmp_path / "x")])
    assert r.exit_code == 2 and "--format must be one of" in r.stderr and not (tmp_path / "x").exists()
    r = CliRunner().invoke(app, ["export", str(tmp_path), "--format", "json", "-o", str(tmp_path / "y")])
    assert r.exit_code == 2 and r.stderr.startswith("error: ") and "calibration.json" in r.stderr
    (tmp_path / "bad.json").write_text('{"format": "something else"}')
    r = CliRunner().invoke(app, ["export", str(tmp_path / "bad.json"), "--format", "json", "-o", str(tmp_path / "z")])
    assert r.exit_code == 2 and "not a calib calibration.json" in r.stderr


def test_version_help_and_python_m():
    from calib import __version__

    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.stdout.strip() == f"calib {__version__}"
    assert CliRunner().invoke(app, ["run", "-h"]).exit_code == 0
    p = subprocess.run([sys.executable, "-m", "calib", "--help"], capture_output=True, text=True)
    assert p.returncode == 0 and "export" in p.stdout and "--version" in p.stdout
    h = CliRunner().invoke(app, ["simulate", "--help"], env={"COLUMNS": "200"}).stdout
    assert "[default: paper-traj3]" in h and "<bool>" not in h  # defaults in help texts stay visible
    f = CliRunner().invoke(app, ["features", "--help"], env={"COLUMNS": "200"}).stdout
    assert "--detect-threshold" in f and "--threshold " not in f  # one name per option


def test_estimate_cli_writes_calibration_json_and_old_features_still_work(tmp_path):
    from calib.pipeline.formats.io import write_features

    feats, _ = simulate_features(1, seed=4)  # features written before meta.json carried mics
    write_features(tmp_path / "features", feats)
    r = CliRunner().invoke(app, ["estimate", str(tmp_path / "features"), "-o", str(tmp_path / "cal"), "-q"])
    assert r.exit_code == 0, r.output
    cal = load_calibration(tmp_path / "cal")
    assert all(a.mics is None for a in cal.arrays) and cal.clock.reference_offset is None
    assert cal.covariance is not None and cal.names == feats["meta"]["arrays"]
    with pytest.raises(ValueError, match="reference_offset"):
        cal.to_emitter_time(cal.names[1], 1.0)  # no anchor: said, not guessed
    r = CliRunner().invoke(app, ["export", str(tmp_path / "cal"), "-f", "pyroomacoustics", "-o", str(tmp_path / "m.npy")])
    assert r.exit_code == 2 and "needs the mic geometry" in r.stderr and not (tmp_path / "m.npy").exists()
    assert CliRunner().invoke(app, ["export", str(tmp_path / "cal"), "-f", "tf", "-o", str(tmp_path / "t.sh")]).exit_code == 0


def test_malformed_meta_mics_is_one_clear_error_and_nothing_written(tmp_path):
    from calib.pipeline.formats.io import write_features

    feats, _ = simulate_features(1, seed=4)
    feats["meta"]["mics"] = {feats["meta"]["arrays"][0]: [[0.0, 0.1]]}
    write_features(tmp_path / "features", feats)
    r = CliRunner().invoke(app, ["estimate", str(tmp_path / "features"), "-o", str(tmp_path / "cal")])
    assert r.exit_code == 2 and r.stderr.strip() == (
        f"error: meta.json: 'mics' of {feats['meta']['arrays'][0]!r} must be a non-empty list of finite [x, y, z]")
    assert not (tmp_path / "cal").exists()
