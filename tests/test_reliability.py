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
from calib.pipeline.formats.outputs import MARKER, make_temp_dir
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

    write_calibration(root / "cal", calibrate(feats), features=feats)  # + calibration.json (calib export)
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


def _second_event_at(path, dt):
    """Log event 1 ``dt`` s after event 0."""
    rows = Path(path).read_text().splitlines()
    t0 = float(rows[1].split(",")[1])
    set_cell(path, 3, "t_emit", repr(t0 + dt))


def _keep_first_array(path):
    text = Path(path).read_text()
    Path(path).write_text(text[:text.index("[[arrays]]", text.index("[[arrays]]") + 1)])


def _only_reference(feats):
    ref = json.loads((feats / "meta.json").read_text())["reference_array"]
    for name in ("tdoa_m", "tdoa_s", "doa"):
        rows = (feats / f"{name}.csv").read_text().splitlines()
        head = rows[0].split(",").index("array")
        (feats / f"{name}.csv").write_text("\n".join([rows[0]] + [r for r in rows[1:] if r.split(",")[head] == ref]) + "\n")


def _header_only(path):
    Path(path).write_text(Path(path).read_text().splitlines()[0] + "\n")


def _cal_json(t, quaternion=None, **top):
    """Edit cal/calibration.json: top-level keys, or the second array's quaternion."""
    p = t / "cal" / "calibration.json"
    doc = json.loads(p.read_text())
    doc.update(top)
    if quaternion is not None:
        doc["arrays"][1]["quaternion"] = quaternion
    p.write_text(json.dumps(doc))


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
EXPORT = ["export", "{cal}", "--format", "yaml", "-o", "{out}"]


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
    toml_case("toml-speed-1e300", FEATURES, "speed_of_sound = 343.0", "speed_of_sound = 1e300",
              ["speed_of_sound"]),
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
    toml_case("toml-sigma-out-of-range", FEATURES, "sigma_odo = 0.01", "sigma_odo = 0.01\nsigma_tdoa = 5.0",
              ["sigma_tdoa"]),
    toml_case("toml-hemisphere-zero", FEATURES, "doa_hemisphere = [0.0, 0.0, 1.0]", "doa_hemisphere = [0, 0, 0]",
              ["doa_hemisphere"]),
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
    # --- issue 29, class 3: crashes → one line
    ("events-1e-7-apart", RUN, lambda t: _second_event_at(t / "rec/events.csv", 1e-7),
     ["events.csv", "event 1", "1e-07 s after event 0", "logged twice"]),
    ("session-one-array", RUN, lambda t: _keep_first_array(t / "rec/session.toml"), ["session.toml", "only one array"]),
    ("features-only-reference", ESTIMATE, lambda t: _only_reference(t / "feats"), ["feats", "no measurement"]),
    ("truth-header-only", EVALUATE, lambda t: _header_only(t / "truth/arrays.csv"), ["truth/arrays.csv", "no arrays"]),
    ("calibration-header-only", EVALUATE, lambda t: _header_only(t / "cal/arrays.csv"), ["cal/arrays.csv", "no arrays"]),
    ("calibration-json-format-version", EXPORT, lambda t: _cal_json(t, format_version="x"),
     ["calibration.json", "format_version"]),
    ("calibration-json-zero-quaternion", EXPORT, lambda t: _cal_json(t, quaternion=[0, 0, 0, 0]),
     ["calibration.json", "quaternion", "not a unit quaternion"]),
    ("calibration-json-arrays-object", EXPORT, lambda t: _cal_json(t, arrays={"A1": 1}),
     ["calibration.json", "'arrays' must be a list"]),
    ("features-diagnostics-is-out", ["features", "{rec}", "-o", "{out}", "--diagnostics", "{out}"], _noop,
     ["out", "other output"]),
    ("chirp-fs-1e9", ["chirp", "-o", "{out}", "--fs", "1e9"], _noop, ["--fs", "1e+06"]),
    ("chirp-too-long", ["chirp", "-o", "{out}", "--fs", "1000000", "--duration", "60", "--interval", "100"], _noop,
     ["--duration × --fs"]),
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
    assert not list(tmp_path.glob(".*lock")) and not list(out.glob(".*"))  # no lock file, no litter
    dead = make_temp_dir(out / "report")  # a killed run's temporary folder
    (dead / "summary.md").write_text("half")
    (out / ".report.tmp-dead").mkdir()  # the user's folder that merely looks like one: never deleted
    (out / ".report.tmp-dead" / "notes.md").write_text("mine")
    tm = out / "features" / "tdoa_m.csv"
    tm.write_text(tm.read_text().replace("\n", "\n", 1))  # unchanged content: fine
    edited = tm.read_text().splitlines()
    edited[1] = ",".join(edited[1].split(",")[:2] + ["0.001"] + edited[1].split(",")[3:])
    tm.write_text("\n".join(edited) + "\n")
    r = runner.invoke(app, ["run", str(tmp_path / "rec"), "-o", str(out), "-q"])
    assert r.exit_code == 0, r.stderr  # the edit re-estimates; the features stage is skipped
    assert tm.read_text() == "\n".join(edited) + "\n"
    assert not dead.exists() and (out / ".report.tmp-dead" / "notes.md").read_text() == "mine"
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
    return [p for p in Path(folder).rglob(".*") if ".calib-tmp-" in p.name or ".calib-old-" in p.name
            or p.name.endswith(".calib-lock")]


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_interrupted_run_exits_cleanly(base, tmp_path, sig, code):
    """SIGTERM/SIGINT during the features stage: one message, exit 143/130, no litter, inputs untouched;
    the next run completes."""
    shutil.copytree(base / "rec", tmp_path / "rec")
    before = tree_digest(tmp_path / "rec")
    p = _start(["run", tmp_path / "rec", "-o", tmp_path / "out", "-q"], tmp_path)
    deadline = time.time() + 60
    while not (tmp_path / ".out.calib-lock").exists() and p.poll() is None and time.time() < deadline:
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
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
@pytest.mark.parametrize("after", [0.0, 0.02, 0.1, 0.3])
def test_sigterm_while_starting(tmp_path, sig, code, after):
    """SIGTERM / SIGINT while calib starts (imports; issue 29: a traceback in the first 0.3 s, a silent death at
    0.1 s): exit 143 / 130, one line, no traceback — from the moment the entry module has installed its
    handlers (the interpreter's own start comes before)."""
    p = _start(["simulate", "-o", tmp_path / "s", "-q"], tmp_path)
    deadline = time.time() + 30
    while not _catches_sigterm(p.pid) and p.poll() is None and time.time() < deadline:
        time.sleep(0.002)  # until calib's handler is installed (before its slow imports)
    time.sleep(after)
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code and "Traceback" not in err and len(err.strip().splitlines()) == 1, (p.returncode, err)
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


@pytest.mark.parametrize("name, code", [("INT", 130), ("TERM", 143)])
def test_an_interrupt_typer_swallowed_is_reported_with_its_own_code(name, code):
    """typer exits 130 in silence for an interrupt outside the command's own handling (while it parses the
    arguments): the command still says it was interrupted, in one line, with the signal's code (SIGTERM 143)."""
    script = ("import signal\nfrom calib.cli import signals\n"
              f"signals._pending = signal.SIG{name}   # the handler ran, then typer raised Exit(130)\n"
              "signals.leave(130)\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == code and len(r.stderr.strip().splitlines()) == 1, (r.returncode, r.stderr)
    assert r.stderr.startswith("terminated (SIGTERM)" if name == "TERM" else "interrupted (SIGINT)")


@pytest.mark.parametrize("name, code", [("INT", 130), ("TERM", 143)])
def test_an_interrupt_with_stderr_a_closed_pipe_still_exits_with_its_code(name, code):
    """`calib run ... 2>&1 | head` whose reader has gone: the one-line message cannot be written (EPIPE), and
    the command still exits with the signal's code, not with an internal error."""
    script = ("import os, signal\nfrom calib.cli import signals\n"
              "r, w = os.pipe(); os.close(r); os.dup2(w, 2)   # stderr: a pipe nobody reads any more\n"
              f"signals._pending = signal.SIG{name}\n"
              "signals.leave(130)\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == code, (r.returncode, r.stdout)


# ----------------------------------------------------------------------------------------------- writer safety
# Every writer (issue 29): never replace or delete a file or folder calib did not create, nor an input;
# --force replaces only calib's own outputs; a user's files named like calib's temporaries and a user's
# symlink inside an owned output survive. Each writer's command; {out} is its output, {force} its --force.
MC_CHEAP = ["--runs", "1", "--sigma-tdoa", "0.1", "--sigma-doa", "5", "--trajectories", "1", "--methods", "hybrid",
            "--no-check-convergence", "--no-crlb", "--jobs", "1", "-q"]
WRITERS = {  # name: (argv, output is a folder, has --force)
    "run": (["run", "{rec}", "-o", "{out}", "-q"], True, True),
    "features": (["features", "{rec}", "-o", "{out}", "-q"], True, False),
    "estimate": (["estimate", "{feats}", "-o", "{out}", "-q"], True, False),
    "simulate": (["simulate", "-o", "{out}", "--preset", "lab3", "--n-events", "4", "--interval", "0.8",
                  "--chirp-duration", "0.2", "--rt60", "0", "-q"], True, True),
    "chirp": (["chirp", "-o", "{out}", "--fs", "16000", "--n-events", "3", "-q"], True, False),
    "montecarlo": (["montecarlo", "-o", "{out}", *MC_CHEAP], True, False),
    "export": (["export", "{cal}", "--format", "yaml", "-o", "{out}", "-q"], False, False),
    "init": (["init", "{rec}", "-o", "{out}", "-q"], False, True),
}


def tree_state(folder):
    """{relative path: sha256 | 'dir' | 'link -> target'} of everything under ``folder`` (symlinks not followed)."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            out[rel] = (f"link -> {os.readlink(p)}" if p.is_symlink() else "dir" if p.is_dir()
                        else hashlib.sha256(p.read_bytes()).hexdigest())
    return out


def plant_user_files(folder, name):
    """A user's files at and around the output ``folder/name``: look-alikes of calib's temporaries beside it."""
    (folder / f".{name}.tmp-mine").write_text("my draft")
    (folder / f".{name}.old-v1").mkdir()
    (folder / f".{name}.old-v1" / "notes.txt").write_text("my old version")
    (folder / f".{name}.tmp-draft").mkdir()
    (folder / f".{name}.tmp-draft" / "events.csv").write_text("event,t_emit\n")
    (folder / "elsewhere.txt").write_text("linked to")


def user_folder(base, folder):
    """A folder holding what a user keeps: a recording, the robot's log, a summary, temporaries' look-alikes,
    a symlink."""
    folder.mkdir(parents=True)
    shutil.copy(next((base / "rec").glob("*.wav")), folder / "A1.wav")
    shutil.copy(base / "rec" / "events.csv", folder / "events.csv")
    (folder / "summary.csv").write_text("cell,loc_cm\n1,0.5\n")
    (folder / "chirp.wav").write_bytes((folder / "A1.wav").read_bytes())
    (folder / "schedule.csv").write_text("event,t_emit\n0,1.0\n")
    (folder / ".arrays.tmp-mine").write_text("mine")
    (folder / "link.csv").symlink_to(folder.parent / "elsewhere.txt")


def _invoke(argv, paths, force):
    args = [a.format(**paths) for a in argv] + (["--force"] if force else [])
    return runner.invoke(app, args)


def _writer_case(base, tmp_path, writer, where):
    """The tree and output path of one case: ``where`` = user-folder (the output is a user's folder or file),
    input (the output is the command's input), beside (a fresh output among look-alikes)."""
    argv, is_folder, _ = WRITERS[writer]
    for d in ("rec", "feats", "cal"):
        shutil.copytree(base / d, tmp_path / d, symlinks=True)
    area = tmp_path / "area"
    area.mkdir()
    plant_user_files(area, "out")
    user_folder(base, area / "mine")
    if where == "user-folder":
        out = area / "mine" if is_folder else area / "mine" / "A1.wav"
    elif where == "user-log":
        out = area / "mine" / ("summary.csv" if writer == "export" else "events.csv")
    elif where == "user-symlink":
        out = area / "mine" / "link.csv"
    elif where == "input":
        out = tmp_path / "cal" / "calibration.json" if writer == "export" else tmp_path / "rec" / "A1.wav"
    else:
        out = area / "out"
    paths = {"rec": tmp_path / "rec", "feats": tmp_path / "feats", "cal": tmp_path / "cal", "out": out}
    return argv, {k: str(v) for k, v in paths.items()}


SAFETY_CASES = [(w, where, force) for w, (_, folder, has_force) in WRITERS.items()
                for where in (["user-folder", "beside"] if folder else
                              ["user-folder", "user-log", "user-symlink", "input", "beside"])
                for force in ([False, True] if has_force else [False])]


@pytest.mark.parametrize("writer, where, force", SAFETY_CASES, ids=[f"{w}-{p}{'-force' if f else ''}"
                                                                    for w, p, f in SAFETY_CASES])
def test_writer_never_touches_user_files(base, tmp_path, writer, where, force):
    """Every writer, with and without --force: each file and folder that existed before is unchanged (a user's
    WAV, events.csv, summary.csv, chirp.wav, look-alikes of calib's temporaries, a symlink); an output onto a
    user's file or folder or an input is refused with one `error:` line (exit 2); a fresh output is written."""
    argv, paths = _writer_case(base, tmp_path, writer, where)
    before = tree_state(tmp_path)
    r = _invoke(argv, paths, force)
    after = tree_state(tmp_path)
    assert "Traceback" not in r.stdout + r.stderr and "internal error" not in r.stderr, r.stderr
    changed = [p for p, h in before.items() if after.get(p) != h]
    assert not changed, (changed, r.stderr)
    if where == "beside" or (writer, where) == ("run", "user-folder"):  # run writes OUT/<stage>/ beside them
        assert r.exit_code in (0, 3), r.stderr
        assert Path(paths["out"]).exists()
        assert not [p for p in after if "calib-tmp" in p or "calib-old" in p or p.endswith("calib-lock")]
    else:
        assert r.exit_code == 2, (r.exit_code, r.stderr)
        assert r.stderr.strip().splitlines()[-1].startswith("error: "), r.stderr
        assert set(after) == set(before)  # nothing written, no litter


def test_owned_output_with_a_user_symlink_and_look_alikes(base, tmp_path):
    """A user's symlink and a file named like a temporary inside a folder calib wrote: a re-run stops
    (exit 2) instead of deleting them; litter of a real killed run beside it is removed."""
    out = tmp_path / "cal"
    assert runner.invoke(app, ["estimate", str(base / "feats"), "-o", str(out), "-q"]).exit_code in (0, 3)
    (tmp_path / "mine.txt").write_text("mine")
    (out / "mine.csv").symlink_to(tmp_path / "mine.txt")
    dead = make_temp_dir(out)
    before = tree_state(tmp_path)
    r = runner.invoke(app, ["estimate", str(base / "feats"), "-o", str(out), "-q"])
    assert r.exit_code == 2 and "mine.csv" in r.stderr and "symbolic link" in r.stderr, r.stderr
    assert (out / "mine.csv").is_symlink() and (tmp_path / "mine.txt").read_text() == "mine"
    assert not dead.exists()  # calib's own temporary (its token inside) is litter
    (out / "mine.csv").unlink()
    (out / ".arrays.tmp-mine").write_text("mine")
    r = runner.invoke(app, ["estimate", str(base / "feats"), "-o", str(out), "-q"])
    assert r.exit_code == 2 and ".arrays.tmp-mine" in r.stderr, r.stderr
    assert (out / ".arrays.tmp-mine").read_text() == "mine"
    assert {p: h for p, h in tree_state(tmp_path).items() if p in before} == \
        {p: h for p, h in before.items() if not p.startswith(dead.name) and p != "cal/mine.csv"}


def test_single_file_outputs_replace_only_their_own(base, tmp_path):
    """`calib export` replaces its own earlier export (manifest), not a hand-edited one; `calib init --force`
    replaces the session.toml it wrote, never without --force."""
    out = tmp_path / "x.yaml"
    args = ["export", str(base / "cal"), "--format", "yaml", "-o", str(out), "-q"]
    assert runner.invoke(app, args).exit_code == 0
    first = out.read_text()
    assert runner.invoke(app, args).exit_code == 0 and out.read_text() == first
    out.write_text(first + "# my note\n")
    r = runner.invoke(app, args)
    assert r.exit_code == 2 and "edited since calib wrote it" in r.stderr
    assert out.read_text().endswith("# my note\n")
    shutil.copytree(base / "rec", tmp_path / "rec")
    (tmp_path / "rec" / "session.toml").unlink()
    init = ["init", str(tmp_path / "rec"), "-q"]
    assert runner.invoke(app, init).exit_code == 0
    r = runner.invoke(app, init)
    assert r.exit_code == 2 and "--force" in r.stderr
    assert runner.invoke(app, init + ["--force"]).exit_code == 0
    cal = tmp_path / "cal"  # a file another command wrote (estimate's arrays.csv) is not export's to replace
    assert runner.invoke(app, ["estimate", str(base / "feats"), "-o", str(cal), "-q"]).exit_code in (0, 3)
    before = tree_state(cal)
    r = runner.invoke(app, ["export", str(cal), "--format", "yaml", "-o", str(cal / "arrays.csv")])
    assert r.exit_code == 2 and "written by `calib estimate`" in r.stderr, r.stderr
    assert tree_state(cal) == before


# ----------------------------------------------------------------------------------------------- crashes and noise
def _scale_wav(path, factor, nan=False):
    """Rewrite a WAV as float32 times ``factor`` (1e-40: every sample a denormal); ``nan``: some NaN/inf."""
    import soundfile as sf

    x, fs = sf.read(path, dtype="float64", always_2d=True)
    x = (x * factor).astype(np.float32)
    if nan:
        x[100:110] = np.nan
        x[200] = np.inf
    sf.write(path, x[:, 0] if x.shape[1] == 1 else x, fs, subtype="FLOAT")


def _rename_arrays(t):
    """Non-Latin array names (CJK, Cyrillic): the plots' fonts lack the glyphs."""
    toml = t / "rec" / "session.toml"
    toml.write_text(toml.read_text().replace('name = "A2"', 'name = "麦克风"').replace('name = "A3"', 'name = "Микрофон"'))
    shutil.rmtree(t / "rec" / "truth")  # (named A2, A3)


def _map_columns(path, columns, f):
    """Rewrite the CSV cells of ``columns`` as ``f(cell text)``."""
    rows = Path(path).read_text().splitlines()
    head = rows[0].split(",")
    cols = [head.index(c) for c in columns]
    out = [rows[0]]
    for r in rows[1:]:
        cells = r.split(",")
        for c in cols:
            cells[c] = f(cells[c])
        out.append(",".join(cells))
    Path(path).write_text("\n".join(out) + "\n")


def _zero_odometry(path):
    _map_columns(path, ("odom_x", "odom_y", "odom_z"), lambda v: "0")


def _negate_doas(path):
    _map_columns(path, ("ux", "uy", "uz"), lambda v: repr(-float(v)))


def _bom(path):
    Path(path).write_bytes(b"\xef\xbb\xbf" + Path(path).read_bytes())


NOISE_CASES = [  # (id, argv, craft, allowed exit codes, fragment of the error line or None)
    ("denormal-float-wav", RUN, lambda t: _scale_wav(t / "rec/A2.wav", 1e-40), (0, 2, 3), None),
    ("nan-inf-chirp-reference", RUN, lambda t: _scale_wav(t / "rec/chirp.wav", 1.0, nan=True), (2,),
     "chirp.wav: contains non-finite samples"),
    ("non-latin-array-names", RUN, _rename_arrays, (0, 3), None),
    ("all-zero-odometry", ESTIMATE, lambda t: _zero_odometry(t / "feats/events.csv"), (0, 2, 3), None),
    ("every-doa-negated", ESTIMATE, lambda t: _negate_doas(t / "feats/doa.csv"), (0, 3), None),
    ("calibration-json-bom", EXPORT, lambda t: _bom(t / "cal/calibration.json"), (0,), None),
]


@pytest.mark.parametrize("case", NOISE_CASES, ids=[c[0] for c in NOISE_CASES])
def test_no_crash_and_no_library_noise(base, tmp_path, case):
    """Inputs that crashed or printed NumPy/matplotlib warnings (issue 29): an answer or one error line, never an
    internal error, a traceback or a library's warning; inputs untouched."""
    name, argv, craft, codes, fragment = case
    for d in ("rec", "feats", "cal", "truth"):
        shutil.copytree(base / d, tmp_path / d, symlinks=True)
    craft(tmp_path)
    before = tree_digest(tmp_path)
    paths = {k: str(tmp_path / k) for k in ("rec", "feats", "cal", "truth", "out")}
    r = runner.invoke(app, [a.format(tmp=tmp_path, **paths) for a in argv] + ["-q"])
    text = r.stdout + r.stderr
    assert r.exit_code in codes, (r.exit_code, text)
    assert "Traceback" not in text and "internal error" not in text, text
    assert "Warning" not in text and "warnings.warn" not in text, text  # RuntimeWarning, UserWarning (glyphs), …
    if fragment is not None:
        assert r.stderr.strip().splitlines()[-1].startswith("error: ") and fragment in r.stderr, r.stderr
    written = ("out", MARKER)  # the output, and the manifest naming it calib's beside it (a single-file output)
    assert {k: v for k, v in tree_digest(tmp_path).items() if not k.startswith(written)} == before


def check_markers(out):
    """Every owned folder under ``out`` holds exactly the files its marker lists, unedited."""
    for marker in Path(out).rglob(MARKER):
        folder = marker.parent
        files = json.loads(marker.read_text())["files"]
        present = {p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if p.is_file() and not p.name.startswith(".calib")}
        assert present == set(files), (folder, present ^ set(files))
        assert all(hashlib.sha256((folder / f).read_bytes()).hexdigest() == h for f, h in files.items())


@pytest.mark.slow
def test_run_and_features_into_nested_folders(base, tmp_path):
    """`calib run -o OUT` beside `calib features -o OUT/features` (issue 29: OUT inconsistent in 6 of 10 trials):
    the locks on OUT and its sub-folders serialise them; every folder matches its marker, and the next run
    brings OUT back to one consistent run."""
    for trial in range(CONCURRENCY_TRIALS):
        out = tmp_path / f"out{trial}"
        procs = [_start(["run", base / "rec", "-o", out, "-q"], tmp_path),
                 _start(["features", base / "rec", "-o", out / "features", "-q"], tmp_path)]
        errs = [p.communicate(timeout=300)[1] for p in procs]
        assert [p.returncode for p in procs] == [0, 0], errs
        check_markers(out)
        assert not _litter(tmp_path)
        r = runner.invoke(app, ["run", str(base / "rec"), "-o", str(out), "-q"])
        assert r.exit_code == 0, r.stderr
        check_consistent(out)
        check_markers(out)


def _silence(t):
    for wav in (t / "rec").glob("A*.wav"):
        _scale_wav(wav, 0.0)


@pytest.mark.parametrize("argv, craft", [
    (["run", "{rec}", "-o", "{tmp}/new/deep/out", "-q"], _silence),            # fails in the features stage
    (["features", "{rec}", "-o", "{tmp}/new/feats", "-q"], _silence),
    (["estimate", "{feats}", "-o", "{tmp}/new/cal", "-q"], lambda t: _only_reference(t / "feats")),
], ids=["run", "features", "estimate"])
def test_failed_command_leaves_no_empty_folder(base, tmp_path, argv, craft):
    """A command that fails after it started writing (issue 29: 23 failed runs left an empty output folder)
    removes the folders it made for its output: nothing is left."""
    for d in ("rec", "feats"):
        shutil.copytree(base / d, tmp_path / d, symlinks=True)
    craft(tmp_path)
    paths = {k: str(tmp_path / k) for k in ("rec", "feats")}
    r = runner.invoke(app, [a.format(tmp=tmp_path, **paths) for a in argv])
    assert r.exit_code == 2 and r.stderr.startswith("error: "), r.stderr
    assert not (tmp_path / "new").exists() and not _litter(tmp_path)


@pytest.mark.parametrize("force", [False, True])
def test_import_bag_never_replaces_the_robots_log(base, tmp_path, force):
    """`calib import-bag -o REC/events.csv [--force]` onto the session's own events.csv (the robot's log, not
    written by calib): refused before the bag is read; nothing changes."""
    shutil.copytree(base / "rec", tmp_path / "rec")
    before = tree_state(tmp_path)
    r = runner.invoke(app, ["import-bag", str(tmp_path / "robot.bag"), "-o", str(tmp_path / "rec" / "events.csv"),
                            "--schedule", str(tmp_path / "schedule.csv")] + (["--force"] if force else []))
    assert r.exit_code == 2 and "events.csv" in r.stderr and "calib did not write it" in r.stderr, r.stderr
    assert tree_state(tmp_path) == before
