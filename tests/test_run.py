"""`pipeline.run`: the end-to-end pipeline on simulated recordings, stage skipping by content hash,
re-estimation from hand-edited features, and interrupt safety."""
import hashlib
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib import estimator
from calib.pipeline import features as pfeatures
from calib.pipeline.formats import io as pio
from calib.pipeline.formats.io import InputError, read_calibration
from calib.pipeline.simulate.roomsim import make_scenario, simulate
from calib.pipeline.run import STAMP, run


def tree_digest(root):
    """{relative path: sha256} of every file under ``root``."""
    root = Path(root)
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def no_temporaries(root):
    return not [p for p in Path(root).rglob("*") if ".tmp-" in p.name or ".old-" in p.name]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A small simulated lab session (3 arrays, 8 events) with truth/."""
    d = tmp_path_factory.mktemp("rec") / "lab"
    sc = make_scenario("lab3", 3, n_events=8, interval=1.0, chirp={"duration": 0.2}, rt60=0.2, snr=30)
    simulate(sc, d)
    return d


@pytest.fixture(scope="module")
def base(session, tmp_path_factory):
    """One complete run of the pipeline on ``session``; tests copy its output folder."""
    out = tmp_path_factory.mktemp("base") / "out"
    res = run(session, out)
    return out, res


def copy_of(base, tmp_path):
    dst = tmp_path / "out"
    shutil.copytree(base[0], dst)
    return dst


def test_first_run_writes_every_stage(base):
    out, res = base
    assert [s for s, v in res["stages"].items() if v["status"] == "run"] == ["features", "estimate", "report"]
    for d in ("features", "calibration", "report"):
        assert (out / d / STAMP).is_file()
    for f in ("features/tdoa_m.csv", "features/doa.csv", "calibration/arrays.csv", "report/summary.md",
              "report/scene_3d.png", "report/residuals.png", "report/metrics.json", "diagnostics/diagnostics.json"):
        assert (out / f).is_file(), f
    assert no_temporaries(out)
    # truth/ exists, so the metrics are computed; the small lab scene calibrates to a few cm
    assert res["metrics"]["position_rmse_m"] < 0.10


def test_second_run_skips_everything_and_changes_nothing(base, session, tmp_path):
    out = copy_of(base, tmp_path)  # stamps hold no absolute paths: a moved output folder stays valid
    before = tree_digest(out)

    def must_not_run(*a, **k):
        raise AssertionError("a skipped stage ran its computation")

    with pytest.MonkeyPatch.context() as mp:  # a skip means no stage computes anything
        mp.setattr(estimator, "calibrate", must_not_run)
        mp.setattr(pfeatures, "session_features", must_not_run)
        res = run(session, out)
    assert {v["status"] for v in res["stages"].values()} == {"skipped"}
    assert tree_digest(out) == before
    assert res["metrics"]["position_rmse_m"] == pytest.approx(base[1]["metrics"]["position_rmse_m"])


@pytest.mark.slow
def test_deleted_output_is_recomputed(base, session, tmp_path):
    out = copy_of(base, tmp_path)
    (out / "report" / "summary.md").unlink()
    res = run(session, out)
    assert res["stages"]["report"] == {**res["stages"]["report"], "status": "run", "reason": "output missing"}
    assert (out / "report" / "summary.md").is_file()
    assert res["stages"]["estimate"]["status"] == "skipped"


@pytest.mark.slow
def test_edited_tdoa_reestimates_but_keeps_features(base, session, tmp_path):
    out = copy_of(base, tmp_path)
    p = out / "features" / "tdoa_m.csv"
    tm = pd.read_csv(p)
    tm.loc[2, "tdoa"] += 3e-3  # a gross error (30 σ) typed in by hand
    tm.to_csv(p, index=False, float_format="%.12g")
    edited = p.read_bytes()
    logs = []
    res = run(session, out, log=lambda *a: logs.append(a))
    st = {s: v["status"] for s, v in res["stages"].items()}
    assert st == {"features": "skipped", "estimate": "run", "report": "run"}
    assert "features/tdoa_m.csv" in res["stages"]["estimate"]["reason"]
    assert p.read_bytes() == edited  # the user's edit survives
    # the estimate really used the edited file: that row is now flagged as an outlier
    outl = read_calibration(out / "calibration")["report"]["outliers"]
    assert any(o["type"] == "tdoa_m" and o["line"] == 4 and o["residual_us"] < -2000 for o in outl)  # data row 2
    assert ("estimate", "run", res["stages"]["estimate"]["reason"]) in logs


@pytest.mark.slow
def test_changed_setting_reruns_only_downstream(base, session, tmp_path):
    out = copy_of(base, tmp_path)
    before = tree_digest(out / "calibration")
    res = run(session, out, estimate_options={"outlier_threshold": 4.0})
    st = {s: v["status"] for s, v in res["stages"].items()}
    changed = {k: v for k, v in tree_digest(out / "calibration").items() if k != STAMP} != \
        {k: v for k, v in before.items() if k != STAMP}
    # the report depends on the calibration's content only: it re-runs exactly when that changed
    assert st == {"features": "skipped", "estimate": "run", "report": "run" if changed else "skipped"}
    assert "outlier_threshold" in res["stages"]["estimate"]["reason"]


@pytest.mark.slow
def test_crash_while_writing_features_leaves_nothing_trusted(base, session, tmp_path, monkeypatch):
    out = copy_of(base, tmp_path)
    before = tree_digest(out / "features")
    real = pio.write_table

    def crash_on_doa(df, path, *a, **k):
        if Path(path).name == "doa.csv":
            raise RuntimeError("disk full (injected)")
        return real(df, path, *a, **k)

    monkeypatch.setattr(pio, "write_table", crash_on_doa)
    with pytest.raises(RuntimeError, match="injected"):
        run(session, out, force=True)
    monkeypatch.undo()
    assert not (out / "features" / STAMP).exists()  # nothing a later run would trust
    assert no_temporaries(out)
    after = {k: v for k, v in tree_digest(out / "features").items() if k != STAMP}
    assert after == {k: v for k, v in before.items() if k != STAMP}  # the old files, untouched
    res = run(session, out)
    assert res["stages"]["features"]["status"] == "run"
    assert (out / "features" / STAMP).is_file()


@pytest.mark.slow
def test_interrupt_in_estimate_then_resume(base, session, tmp_path, monkeypatch):
    out = copy_of(base, tmp_path)
    p = out / "features" / "tdoa_s.csv"
    ts = pd.read_csv(p)
    ts.loc[0, "tdoa"] += 1e-6
    ts.to_csv(p, index=False, float_format="%.12g")

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(estimator, "calibrate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(session, out)
    monkeypatch.undo()
    assert not (out / "calibration" / STAMP).exists()
    assert (out / "features" / STAMP).exists()
    assert no_temporaries(out)
    res = run(session, out)
    assert {s: v["status"] for s, v in res["stages"].items()} == \
        {"features": "skipped", "estimate": "run", "report": "run"}


def test_bad_input_writes_nothing(session, tmp_path):
    with pytest.raises(InputError, match="nowhere: not a directory"):
        run(tmp_path / "nowhere", tmp_path / "o1")
    assert not (tmp_path / "o1").exists()
    bad = tmp_path / "bad"
    shutil.copytree(session, bad)
    (bad / "truth" / "arrays.csv").write_text("array,x,y\nA1,0,0\n")
    with pytest.raises(InputError, match="arrays.csv.*missing column"):
        run(bad, tmp_path / "o2")
    assert not (tmp_path / "o2").exists()


@pytest.mark.slow
def test_end_to_end_paper_scene(tmp_path):
    """Acceptance: 5 arrays, paper trajectory 3, RT60 0.3 s, SNR 20 dB → errors within the issue's bounds."""
    rec = tmp_path / "rec"
    simulate(make_scenario("paper-traj3", 1, rt60=0.3, snr=20.0), rec)
    res = run(rec, tmp_path / "out")
    m = res["metrics"]
    assert m["position_rmse_m"] <= 0.05
    assert m["orientation_geodesic_deg"] <= 3.0
    assert m["offset_rmse_s"] <= 50e-6
    assert m["drift_rmse"] <= 5e-6
    assert np.isfinite(m["source_rmse_m"])


@pytest.mark.slow
def test_stage_code_digest_covers_every_module_the_stages_load(base, session, tmp_path):
    """Run the whole pipeline in a fresh interpreter and list the source files of the calib modules it loaded:
    each must be hashed into the stage keys (a module outside them could change and leave a stale stage
    marked "skipped")."""
    import json
    import subprocess
    import sys

    from calib.pipeline.run import source_files

    out = copy_of(base, tmp_path)
    code = ("import json, sys\nfrom calib.pipeline.run import run\n"
            f"run({str(session)!r}, {str(out)!r}, force=True)\n"
            "print(json.dumps(sorted(m.__file__ for n, m in list(sys.modules.items())"
            " if (n == 'calib' or n.startswith('calib.')) and getattr(m, '__file__', None))))")
    loaded = json.loads(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                       text=True).stdout.strip().splitlines()[-1])
    hashed = {str(Path(f).resolve()) for f in source_files()}
    assert len(loaded) > 20 and {str(Path(f).resolve()) for f in loaded} - hashed == set()


def test_editing_any_source_file_changes_the_stage_key(tmp_path, monkeypatch):
    """The stage key covers every calib source, sub-packages included (pipeline/formats, simulate, report)."""
    from calib.pipeline import run as R

    k0 = R.stage_key({}, {})[0]
    for rel in ("pipeline/formats/io.py", "pipeline/simulate/featsim.py", "pipeline/report/summary.py"):
        target = next(f for f in R.source_files() if f.as_posix().endswith(rel))
        copy = tmp_path / target.parent.name / target.name   # the same name, other contents
        copy.parent.mkdir(exist_ok=True)
        copy.write_bytes(target.read_bytes() + b"# edited\n")
        files = [copy if f == target else f for f in R.source_files()]
        monkeypatch.setattr(R, "source_files", lambda files=files: files)
        assert R.stage_key({}, {})[0] != k0, rel
        monkeypatch.undo()
