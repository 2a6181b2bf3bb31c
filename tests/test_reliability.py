"""Reliability (issue 11, docs/reliability.md): every bad input → one ``error: <file>: <problem>`` line and
exit 2, no traceback, nothing partial written, inputs untouched; the output policy (never lose a user's
file); interrupts (SIGINT/SIGTERM) and concurrent runs into one folder.

The table ``CASES`` holds one crafted bad input per class of the issue's "Why" (and more); each is a CLI
invocation on a fresh copy of a valid session / features / calibration / truth.
"""
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.cli.main import app
from calib.errors import InputWarning
from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import write_calibration, write_features, write_truth
from calib.pipeline.formats.outputs import MARKER
from calib.pipeline.simulate.roomsim import make_scenario, simulate
from calib.pipeline.formats.session import read_session

runner = CliRunner()
CALIB = [sys.executable, "-m", "calib"]


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A valid tree: rec/ (a small simulated session), feats/, cal/ (a calibration), truth/."""
    root = tmp_path_factory.mktemp("base")
    simulate(make_scenario("lab3", 5, n_events=6, interval=0.8, chirp={"duration": 0.2}, rt60=0.15, snr=30),
             root / "rec")
    feats, truth = simulate_features(trajectory=1, seed=2)
    write_features(root / "feats", feats)
    write_truth(root / "truth", truth)
    from calib.estimator import calibrate

    write_calibration(root / "cal", calibrate(feats))
    for d in ("rec", "feats", "truth", "cal"):  # inputs a user made or got from elsewhere: no calib marker
        for m in (root / d).rglob(MARKER):
            m.unlink()
    return root


def tree_digest(folder):
    """{relative path: sha256} of every file under ``folder`` (to prove inputs are never touched)."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def edit(path, old, new, count=1):
    text = Path(path).read_text()
    assert old in text, (old, path)
    Path(path).write_text(text.replace(old, new, count))


def set_cell(path, line, col, value):
    """Replace one CSV cell (1-based file line, header = 1)."""
    rows = Path(path).read_text().splitlines()
    header = rows[0].split(",")
    cells = rows[line - 1].split(",")
    cells[header.index(col)] = value
    rows[line - 1] = ",".join(cells)
    Path(path).write_text("\n".join(rows) + "\n")


def set_meta(path, **kw):
    meta = json.loads(Path(path).read_text())
    meta.update(kw)
    Path(path).write_text(json.dumps(meta))


def many_events(path, n):
    rows = [f"{k},{0.5 * k},0,0,0" for k in range(n)]
    Path(path).write_text("event,t_emit,odom_x,odom_y,odom_z\n" + "\n".join(rows) + "\n")


def mics_of(toml, name):
    """The line ``mics = ...`` of array ``name`` in a session.toml text."""
    block = toml.split(f'name = "{name}"')[1]
    return next(line for line in block.splitlines() if line.startswith("mics = "))


def set_mics(rec, name, new):
    text = (rec / "session.toml").read_text()
    head, block = text.split(f'name = "{name}"', 1)
    block = block.replace(mics_of(text, name), f"mics = {new}", 1)
    (rec / "session.toml").write_text(head + f'name = "{name}"' + block)


# ----------------------------------------------------------------------------------------------- the table
# (id, argv with {rec} {feats} {cal} {truth} {out} {tmp}, crafting function(tmp) or None, fragments of the
# error line). Every case must exit 2 with one error line; {out} must not exist afterwards.
def _noop(t):
    pass


# the commands of the cases (the placeholders are filled in per test)
FEATURES = ["features", "{rec}", "-o", "{out}"]
ESTIMATE = ["estimate", "{feats}", "-o", "{out}"]
RUN = ["run", "{rec}", "-o", "{out}"]
EVALUATE = ["evaluate", "{cal}", "{truth}"]


def toml_case(name, argv, old, new, fragments):
    """A case that edits session.toml (``old`` → ``new``) and expects an error naming it and ``fragments``."""
    return name, argv, lambda t: edit(t / "rec/session.toml", old, new), ["session.toml", *fragments]


CASES = [
    # --- data loss: an output that is, contains or lies inside an input
    ("features-out-is-input", ["features", "{rec}", "-o", "{rec}"], _noop, ["is the input"]),
    ("estimate-out-is-input", ["estimate", "{feats}", "-o", "{feats}"], _noop, ["is the input"]),
    ("features-out-contains-input", ["features", "{rec}", "-o", "{tmp}"], _noop, ["contains the input"]),
    ("run-out-contains-input", ["run", "{rec}", "-o", "{tmp}"], _noop, ["contains the input"]),
    ("run-out-inside-input", ["run", "{rec}", "-o", "{rec}/out"], _noop, ["inside the input"]),
    ("estimate-out-inside-input", ["estimate", "{feats}", "-o", "{feats}/cal"], _noop, ["inside the input"]),
    ("features-out-symlink-to-input", ["features", "{rec}", "-o", "{tmp}/link"],
     lambda t: (t / "link").symlink_to(t / "rec"), ["link", "is the input"]),
    ("run-out-is-input", ["run", "{rec}", "-o", "{rec}"], _noop, ["is the input"]),
    # --- files the user wrote, in folders the user did not name
    ("features-default-diagnostics-user-file", ["features", "{rec}", "-o", "{tmp}/x/feats"],
     lambda t: ((t / "x" / "diagnostics").mkdir(parents=True), (t / "x/diagnostics/notes.txt").write_text("mine")),
     ["notes.txt", "did not"]),
    ("estimate-into-user-folder", ["estimate", "{feats}", "-o", "{tmp}/mine"],
     lambda t: ((t / "mine").mkdir(), (t / "mine" / "thesis.tex").write_text("mine")), ["thesis.tex"]),
    ("run-user-file-in-report", ["run", "{rec}", "-o", "{tmp}/o"],
     lambda t: ((t / "o" / "report").mkdir(parents=True), (t / "o/report/keep.md").write_text("mine")),
     ["keep.md"]),
    ("estimate-out-is-a-file", ["estimate", "{feats}", "-o", "{tmp}/file"],
     lambda t: (t / "file").write_text("mine"), ["file"]),
    # --- values that used to raise a traceback
    toml_case("toml-array-name-not-string", FEATURES, 'name = "A1"', "name = 5", ["name"]),
    toml_case("toml-noise-is-list", FEATURES, "[chirp]", "noise = [1, 2]\n[chirp]", ["noise"]),
    ("toml-speed-1e300", FEATURES,
     lambda t: edit(t / "rec/session.toml", "speed_of_sound = 343.0", "speed_of_sound = 1e300"),
     ["session.toml", "speed_of_sound"]),
    ("events-t-emit-1e300", FEATURES,
     lambda t: set_cell(t / "rec/events.csv", 3, "t_emit", "1e300"), ["events.csv", "line 3", "t_emit"]),
    ("events-id-1e300", FEATURES,
     lambda t: set_cell(t / "rec/events.csv", 2, "event", "1e300"), ["events.csv", "line 2", "event"]),
    ("events-200k", FEATURES,
     lambda t: many_events(t / "rec/events.csv", 200_000), ["events.csv", "rows"]),
    ("features-events-200k", ESTIMATE,
     lambda t: many_events(t / "feats/events.csv", 200_000), ["events.csv", "rows"]),
    ("meta-speed-1e300", ESTIMATE,
     lambda t: set_meta(t / "feats/meta.json", speed_of_sound=1e300), ["meta.json", "speed_of_sound"]),
    ("tdoa-m-1e300", ESTIMATE,
     lambda t: set_cell(t / "feats/tdoa_m.csv", 2, "tdoa", "1e300"), ["tdoa_m.csv", "line 2"]),
    ("truth-x-1e300", EVALUATE,
     lambda t: set_cell(t / "truth/arrays.csv", 2, "x", "1e300"), ["truth/arrays.csv", "line 2", "'x'"]),
    ("overlong-output-name", ["estimate", "{feats}", "-o", "{tmp}/" + "x" * 300], _noop, ["x" * 20]),
    ("simulate-rt60-1e300", ["simulate", "{out}", "--rt60", "1e300"], _noop, ["--rt60"]),
    ("simulate-fs-zero", ["simulate", "{out}", "--fs", "0"], _noop, ["--fs"]),
    ("diagnostics-under-a-file", FEATURES + ["--diagnostics", "{tmp}/f/diag"],
     lambda t: (t / "f").write_text("a file"), ["f"]),
    # --- wrong results that used to exit 0
    ("meta-speed-true", ESTIMATE,
     lambda t: set_meta(t / "feats/meta.json", speed_of_sound=True), ["meta.json", "speed_of_sound"]),
    ("meta-speed-string", ESTIMATE,
     lambda t: set_meta(t / "feats/meta.json", speed_of_sound="343"), ["meta.json", "speed_of_sound"]),
    ("toml-speed-string", FEATURES,
     lambda t: edit(t / "rec/session.toml", "speed_of_sound = 343.0", 'speed_of_sound = "343"'),
     ["session.toml", "speed_of_sound"]),
    toml_case("two-arrays-one-wav", FEATURES, 'wav = "A2.wav"', 'wav = "A1.wav"', ["share"]),
    toml_case("boolean-mic-coordinate", FEATURES, "mics = [[", "mics = [[true, ", ["mics"]),
    toml_case("chirp-above-nyquist", FEATURES, "f1 = ", "f1 = 9000.0\nf1_old = ", ["Nyquist"]),
    ("estimate-outlier-threshold-nan", ESTIMATE + ["--outlier-threshold", "nan"], _noop,
     ["--outlier-threshold"]),
    ("estimate-outlier-threshold-negative", ESTIMATE + ["--outlier-threshold", "-1"],
     _noop, ["--outlier-threshold"]),
    ("estimate-emission-sigma-nan", ESTIMATE + ["--emission-sigma", "nan"], _noop,
     ["--emission-sigma"]),
    ("estimate-emission-sigma-negative", ESTIMATE + ["--emission-sigma", "-1"], _noop,
     ["--emission-sigma"]),
    ("features-max-drift-nan", FEATURES + ["--max-drift", "nan"], _noop, ["--max-drift"]),
    ("run-detect-threshold-inf", RUN + ["--detect-threshold", "inf"], _noop,
     ["--detect-threshold"]),
    ("estimate-method-unknown", ESTIMATE + ["--method", "magic"], _noop, ["--method"]),
    ("montecarlo-runs-zero", ["montecarlo", "-o", "{out}", "--runs", "0"], _noop, ["--runs"]),
    # --- messages naming the right file and array
    ("coincident-mics", FEATURES,
     lambda t: set_mics(t / "rec", "A1", "[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0]]"),
     ["session.toml", "'A1'", "same place"]),
    ("mic-count-vs-wav-channels", FEATURES,
     lambda t: set_mics(t / "rec", "A2", "[[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]"), ["A2.wav", "channels"]),
    # --- other readers and values
    toml_case("toml-invalid", RUN, "[chirp]", "[chirp", ["invalid TOML"]),
    toml_case("toml-no-chirp", RUN, "[chirp]", "[chirpy]", ["chirp"]),
    ("toml-sigma-out-of-range", FEATURES,
     lambda t: edit(t / "rec/session.toml", "sigma_odo = 0.01", "sigma_odo = 0.01\nsigma_tdoa = 5.0"),
     ["session.toml", "sigma_tdoa"]),
    ("toml-hemisphere-zero", FEATURES,
     lambda t: edit(t / "rec/session.toml", "doa_hemisphere = [0.0, 0.0, 1.0]", "doa_hemisphere = [0, 0, 0]"),
     ["session.toml", "doa_hemisphere"]),
    ("wav-missing", RUN, lambda t: (t / "rec/A3.wav").unlink(), ["A3.wav", "not found"]),
    ("wav-garbage", FEATURES,
     lambda t: (t / "rec/A3.wav").write_bytes(b"RIFF1234WAVEjunk"), ["A3.wav", "cannot read audio"]),
    ("events-nan", FEATURES,
     lambda t: set_cell(t / "rec/events.csv", 2, "odom_x", "nan"), ["events.csv", "line 2", "not finite"]),
    ("events-missing-column", ESTIMATE,
     lambda t: edit(t / "feats/events.csv", "odom_z", "odom_q"), ["events.csv", "odom_z"]),
    ("events-not-increasing", ESTIMATE,
     lambda t: set_cell(t / "feats/events.csv", 3, "t_emit", "0"), ["events.csv", "t_emit"]),
    ("meta-invalid-json", ESTIMATE,
     lambda t: (t / "feats/meta.json").write_text("{nope"), ["meta.json", "invalid JSON"]),
    ("meta-reference-unknown", ESTIMATE,
     lambda t: set_meta(t / "feats/meta.json", reference_array="Z9"), ["meta.json", "reference_array"]),
    ("meta-sigma-negative", ESTIMATE,
     lambda t: set_meta(t / "feats/meta.json", sigma_tdoa=-1e-4), ["meta.json", "sigma_tdoa"]),
    ("tdoa-m-unknown-array", ESTIMATE,
     lambda t: set_cell(t / "feats/tdoa_m.csv", 2, "array", "Z9"), ["tdoa_m.csv", "line 2", "Z9"]),
    ("doa-not-unit", ESTIMATE,
     lambda t: set_cell(t / "feats/doa.csv", 2, "ux", "3"), ["doa.csv", "line 2", "unit"]),
    ("calibration-quaternion", EVALUATE,
     lambda t: set_cell(t / "cal/arrays.csv", 2, "qw", "7"), ["cal/arrays.csv", "line 2", "quaternion"]),
    ("calibration-missing", EVALUATE,
     lambda t: (t / "cal/arrays.csv").unlink(), ["cal/arrays.csv", "not found"]),
    ("calibration-report-not-object", EVALUATE,
     lambda t: (t / "cal/report.json").write_text("[1, 2]"), ["report.json", "object"]),
    ("too-few-events", ESTIMATE,
     lambda t: many_events(t / "feats/events.csv", 2), ["feats"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_one_line_exit_2(base, tmp_path, case):
    name, argv, craft, fragments = case
    for d in ("rec", "feats", "cal", "truth"):
        shutil.copytree(base / d, tmp_path / d, symlinks=True)
    craft(tmp_path)
    before = tree_digest(tmp_path)
    paths = {k: str(tmp_path / k) for k in ("rec", "feats", "cal", "truth", "out")}
    args = [a.format(tmp=tmp_path, **paths) for a in argv]
    r = runner.invoke(app, args)
    assert r.exit_code == 2, (name, r.exit_code, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if not ln.startswith("warning: ")]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    assert "Traceback" not in r.stdout + r.stderr
    assert tree_digest(tmp_path) == before  # inputs and the user's files untouched, nothing partial written
    assert not (tmp_path / "out").exists()


def test_table_covers_the_issue():
    assert len(CASES) >= 40


# ----------------------------------------------------------------------------------------------- output policy
@pytest.mark.slow
def test_run_rerun_user_edit_and_user_files(base, tmp_path):
    """A second run replaces only calib's own folders; a hand edit is kept while its stage is skipped and
    stops the run (not overwritten) when the stage must run; litter of killed runs is removed."""
    shutil.copytree(base / "rec", tmp_path / "rec")
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(tmp_path / "rec"), "-o", str(out), "-q"])
    assert r.exit_code == 0, r.stderr
    for sub in ("features", "diagnostics", "calibration", "report"):
        assert (out / sub / MARKER).is_file()
    assert not list(tmp_path.glob(".*.lock")) and not list(out.glob(".*"))  # no lock file, no litter
    (out / ".report.tmp-dead").mkdir()  # a killed run's temporary folder
    (out / ".report.tmp-dead" / "summary.md").write_text("half")
    tm = out / "features" / "tdoa_m.csv"
    tm.write_text(tm.read_text().replace("\n", "\n", 1))  # unchanged content: fine
    edited = tm.read_text().splitlines()
    edited[1] = ",".join(edited[1].split(",")[:2] + ["0.001"] + edited[1].split(",")[3:])
    tm.write_text("\n".join(edited) + "\n")
    r = runner.invoke(app, ["run", str(tmp_path / "rec"), "-o", str(out), "-q"])
    assert r.exit_code == 0, r.stderr  # the edit re-estimates; the features stage is skipped
    assert tm.read_text() == "\n".join(edited) + "\n"
    assert not (out / ".report.tmp-dead").exists()
    shutil.rmtree(out / "diagnostics")  # the features stage must run again: it would overwrite the edit
    before = tree_digest(out)
    r = runner.invoke(app, ["run", str(tmp_path / "rec"), "-o", str(out), "-q"])
    assert r.exit_code == 2 and "tdoa_m.csv" in r.stderr and "edited" in r.stderr, r.stderr
    assert tree_digest(out) == before


def test_features_atomic_as_a_command(base, tmp_path, monkeypatch):
    """A failure while writing the diagnostics leaves neither the features nor the diagnostics."""
    import calib.pipeline.features as pf

    def boom(path, diag):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(pf, "plot_detections", boom)
    r = runner.invoke(app, ["features", str(base / "rec"), "-o", str(tmp_path / "x" / "feats"), "-q"])
    assert r.exit_code == 2 and "No space left" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "x").exists()  # not even the folder made for it


def test_internal_error_is_not_bad_input(base, tmp_path, monkeypatch):
    """A ValueError from a bug is an internal error: exit 1, the traceback in a file whose path is printed."""
    import calib.pipeline.run as pr

    def bug(*a, **k):
        raise ValueError("a programming error")

    monkeypatch.setattr(pr, "read_features", bug)
    r = runner.invoke(app, ["estimate", str(base / "feats"), "-o", str(tmp_path / "c")])
    assert r.exit_code == 1, r.stderr
    assert r.stderr.startswith("internal error: ValueError") and "Traceback" not in r.stderr
    path = r.stderr.split("traceback written to ")[1].split(";")[0]
    assert "a programming error" in Path(path).read_text() and "Traceback" in Path(path).read_text()
    os.unlink(path)
    assert not (tmp_path / "c").exists()


def test_unknown_keys_warn_with_did_you_mean(base, tmp_path):
    shutil.copytree(base / "rec", tmp_path / "rec")
    edit(tmp_path / "rec/session.toml", "speed_of_sound", "speed_of_sond")
    edit(tmp_path / "rec/session.toml", "sigma_odo = 0.01", "sigma_odo = 0.01\nsigma_tdao = 1e-4")
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        read_session(tmp_path / "rec")
    msgs = [str(w.message) for w in got if issubclass(w.category, InputWarning)]
    assert any("speed_of_sond" in m and "did you mean 'speed_of_sound'" in m for m in msgs), msgs
    assert any("sigma_tdao" in m and "did you mean 'sigma_tdoa'" in m for m in msgs), msgs


def test_bom_and_crlf_accepted_everywhere(base, tmp_path):
    """One convention: a UTF-8 BOM and CRLF line ends are accepted in CSV, JSON and TOML alike."""
    from calib.pipeline.formats.io import read_features

    for d in ("rec", "feats"):
        shutil.copytree(base / d, tmp_path / d)
    for p in [*(tmp_path / "feats").iterdir(), tmp_path / "rec/session.toml", tmp_path / "rec/events.csv"]:
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes().replace(b"\n", b"\r\n"))
    want = read_features(base / "feats")
    got = read_features(tmp_path / "feats")
    assert got["meta"] == want["meta"]
    np.testing.assert_array_equal(got["tdoa_m"]["tdoa"], want["tdoa_m"]["tdoa"])
    assert read_session(tmp_path / "rec")["speed_of_sound"] == read_session(base / "rec")["speed_of_sound"]


# ----------------------------------------------------------------------------------------------- signals
def _start(args, cwd):
    return subprocess.Popen(CALIB + [str(a) for a in args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _litter(folder):
    return [p for p in Path(folder).rglob(".*") if ".tmp-" in p.name or ".old-" in p.name or p.suffix == ".lock"]


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_interrupted_run_exits_cleanly(base, tmp_path, sig, code):
    """SIGTERM/SIGINT during the features stage: one message, exit 143/130, no litter, inputs untouched;
    the next run completes."""
    shutil.copytree(base / "rec", tmp_path / "rec")
    before = tree_digest(tmp_path / "rec")
    p = _start(["run", tmp_path / "rec", "-o", tmp_path / "out", "-q"], tmp_path)
    deadline = time.time() + 60
    while not (tmp_path / ".out.lock").exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)  # the lock file appears once inputs are validated and the run starts writing
    time.sleep(0.5)
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, (p.returncode, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not _litter(tmp_path), _litter(tmp_path)
    assert tree_digest(tmp_path / "rec") == before
    r = runner.invoke(app, ["run", str(tmp_path / "rec"), "-o", str(tmp_path / "out"), "-q"])
    assert r.exit_code == 0, r.stderr


def _catches_sigterm(pid):
    """Whether process ``pid`` has a handler for SIGTERM (Linux /proc/PID/status SigCgt mask)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = int(next(ln for ln in status.splitlines() if ln.startswith("SigCgt:")).split()[1], 16)
    return bool(mask >> (signal.SIGTERM - 1) & 1)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_sigterm_while_starting(tmp_path):
    """SIGTERM in the first second (imports): exit 143, one line, no traceback."""
    p = _start(["simulate", tmp_path / "s", "-q"], tmp_path)
    deadline = time.time() + 30
    while not _catches_sigterm(p.pid) and p.poll() is None and time.time() < deadline:
        time.sleep(0.005)  # until calib's handler is installed (before its slow imports)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143 and "Traceback" not in err, (p.returncode, err)
    assert not (tmp_path / "s").exists() and not _litter(tmp_path)


# ----------------------------------------------------------------------------------------------- concurrency
CONCURRENCY_TRIALS = int(os.environ.get("CALIB_CONCURRENCY_TRIALS", "2"))


def check_consistent(out):
    """Every stage stamp in ``out`` matches the files beside it (no report stamped for other inputs)."""
    from calib.pipeline.run import (CALIBRATION_FILES, STAMP, feature_files, hash_files, read_stamp)

    est = read_stamp(out / "calibration")
    rep = read_stamp(out / "report")
    assert est is not None and rep is not None
    feats = hash_files(out / "features", "features", feature_files())
    assert est["inputs"] == feats
    cal = hash_files(out / "calibration", "calibration", CALIBRATION_FILES)
    assert {k: v for k, v in rep["inputs"].items() if k.startswith(("features/", "calibration/"))} == {**feats, **cal}
    for sub in ("features", "diagnostics", "calibration", "report"):
        marker = json.loads((out / sub / MARKER).read_text())["files"]
        assert all(hashlib.sha256((out / sub / f).read_bytes()).hexdigest() == h for f, h in marker.items())
    assert (out / "features" / STAMP).is_file()


@pytest.mark.slow
def test_concurrent_runs_into_one_folder(base, tmp_path):
    """Two `calib run` of different sessions into one folder at once: the lock serialises them; the result
    is consistent. CALIB_CONCURRENCY_TRIALS=100 for the long run (docs/reliability.md)."""
    rec2 = tmp_path / "rec2"
    simulate(make_scenario("lab3", 6, n_events=6, interval=0.8, chirp={"duration": 0.2}, rt60=0.15, snr=30), rec2)
    for trial in range(CONCURRENCY_TRIALS):
        out = tmp_path / f"out{trial}"
        procs = [_start(["run", rec, "-o", out, "-q", "--force"], tmp_path) for rec in (base / "rec", rec2)]
        errs = [p.communicate(timeout=300)[1] for p in procs]
        assert [p.returncode for p in procs] == [0, 0], errs
        check_consistent(out)
        assert not _litter(tmp_path)
        print(f"trial {trial + 1}/{CONCURRENCY_TRIALS}: consistent", flush=True)  # visible with -s (long run)


_SWALLOWED = """
import gc, os, signal, sys
from calib.cli import signals
signals.install()

class Finalised:
    def __del__(self):  # Python swallows what a finaliser raises ("Exception ignored in ...")
        os.kill(os.getpid(), signal.SIG{name})
        for _ in range(1000):
            pass

Finalised()
gc.collect()
print("ran on", flush=True)
if sys.argv[1] == "check":
    try:
        signals.check()
    except KeyboardInterrupt as exc:
        signals.leave(signals.interrupted(exc, "re-raised"))
signals.leave(0)
"""


@pytest.mark.parametrize("name, code", [("INT", 130), ("TERM", 143)])
@pytest.mark.parametrize("where", ["check", "exit"])
def test_interrupt_swallowed_in_a_finaliser_is_not_lost(tmp_path, name, code, where):
    """An interrupt landing in a finaliser is swallowed by Python; the next progress point (check) raises it
    again, and a command that finishes anyway still exits as interrupted, without 'Exception ignored'."""
    script = tmp_path / "swallow.py"
    script.write_text(_SWALLOWED.replace("{name}", name))
    r = subprocess.run([sys.executable, str(script), where], capture_output=True, text=True, timeout=60)
    assert r.returncode == code, (r.returncode, r.stderr)
    assert r.stdout == "ran on\n"  # the interrupt did not stop the finaliser's caller: Python swallowed it
    assert "Exception ignored" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert ("re-raised" in r.stderr) == (where == "check"), r.stderr
