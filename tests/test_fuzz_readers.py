"""Property-based fuzzing of every reader (hypothesis): whatever the bytes of an input file, a reader
returns or raises calib.errors.InputError — never another exception (docs/reliability.md).

Each example starts from a valid file and applies random edits: a token replaced by a value from a list
of troublemakers (1e300, nan, true, "343", huge integers, empty, unknown names, …) or by random text,
lines dropped or duplicated, random characters inserted, a BOM, CRLF line ends, truncation.

CI runs a few dozen examples per reader. The long run (docs/reliability.md)::

    CALIB_FUZZ_EXAMPLES=20000 python -m pytest -q -p no:cacheprovider tests/test_fuzz_readers.py
"""
import json
import os
import re
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from hypothesis import HealthCheck, given, settings, strategies as st

from calib.errors import InputError
from calib.jsonutil import dumps_json
from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import read_calibration, read_events, read_features, read_truth, write_features, write_truth
from calib.pipeline.formats.export import FORMATS, export
from calib.pipeline.formats.results import load_calibration
from calib.pipeline.montecarlo import read_grid
from calib.pipeline.simulate.roomsim import load_scenario
from calib.pipeline.formats.session import read_session

EXAMPLES = int(os.environ.get("CALIB_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
TROUBLE = ["1e300", "-1e300", "1e-320", "nan", "NaN", "inf", "-inf", "", " ", "true", "false", '"343"', "343",
           "0", "-0", "-1", "1.5", "99999999999999999999999999", "1" + "0" * 400, "[]", "{}", "[1, 2]",
           "[[1, 2, 3]]", '"x"', "null", "A1", "A9", "Z", "0x10", "1_000", "é", "\x00", "\ufeff", ",", "\"",
           "[", "]", "=", "{", "}", ":", "\n", "'", "#", "[[arrays]]", "[chirp]"]
SPLIT = re.compile(r"([,\n=\[\]{}\":])")


@st.composite
def mutated(draw, text):
    """A randomly edited copy of ``text`` (see the module docstring)."""
    parts = SPLIT.split(text)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["token", "random", "drop_line", "dup_line", "insert", "truncate"]))
        if op in ("token", "random") and parts:
            k = draw(st.integers(0, len(parts) - 1))
            parts[k] = draw(st.sampled_from(TROUBLE)) if op == "token" else draw(st.text(max_size=12))
        elif op in ("drop_line", "dup_line"):
            lines = "".join(parts).split("\n")
            k = draw(st.integers(0, len(lines) - 1))
            lines[k:k + 1] = [] if op == "drop_line" else [lines[k]] * draw(st.integers(2, 50))
            parts = SPLIT.split("\n".join(lines))
        elif op == "insert":
            s = "".join(parts)
            k = draw(st.integers(0, len(s)))
            parts = SPLIT.split(s[:k] + draw(st.text(max_size=8)) + s[k:])
        else:
            s = "".join(parts)
            parts = SPLIT.split(s[:draw(st.integers(0, len(s)))])
    out = "".join(parts)
    if draw(st.booleans()):
        out = out.replace("\n", "\r\n")
    if draw(st.booleans()):
        out = "\ufeff" + out
    return out


def only_input_errors(read, *args):
    """Call a reader; an InputError is fine, anything else fails the test (with the message)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            read(*args)
        except InputError as exc:
            assert "\n" not in str(exc).strip(), str(exc)


# ----------------------------------------------------------------------------------------------- valid inputs
def _tiny_session(d):
    """Two arrays × 3 mics, 0.3 s of noise at 16 kHz, three events: a valid session folder."""
    d.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("A1", "A2"):
        sf.write(d / f"{name}.wav", 0.01 * rng.standard_normal((4800, 3)), 16000, subtype="FLOAT")
    (d / "session.toml").write_text(
        'speed_of_sound = 343.0\nreference_array = "A1"\n\n[chirp]\nf0 = 500.0\nf1 = 4000.0\nduration = 0.05\n'
        'kind = "linear"\nfade = 0.005\n\n[noise]\nsigma_odo = 0.01\n\n'
        '[[arrays]]\nname = "A1"\nwav = "A1.wav"\nmics = [[0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.03, 0.0, 0.0]]\n'
        'doa_hemisphere = [0.0, 0.0, 1.0]\n\n'
        '[[arrays]]\nname = "A2"\nwav = "A2.wav"\nmics = [[0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.03, 0.0, 0.0]]\n')
    (d / "events.csv").write_text("event,t_emit,odom_x,odom_y,odom_z\n0,0.05,0,0,0\n1,0.15,0.1,0,0\n2,0.25,0.2,0,0\n")


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid")
    feats, truth = simulate_features(trajectory=1, seed=3)
    feats = {**feats, "events": feats["events"].iloc[:12]}  # a small folder keeps each example fast
    keep = set(feats["events"]["event"])
    for k in ("tdoa_m", "doa"):
        feats[k] = feats[k][feats[k]["event"].isin(keep)]
    feats["tdoa_s"] = feats["tdoa_s"][feats["tdoa_s"]["from_event"].isin(keep) & feats["tdoa_s"]["to_event"].isin(keep)]
    write_features(root / "feats", feats)
    write_truth(root / "truth", truth)
    shutil.copytree(root / "truth", root / "cal")  # truth arrays/sources in the calibration format
    (root / "cal" / "report.json").write_text(json.dumps({"converged": True}))
    _tiny_session(root / "rec")
    (root / "grid.toml").write_text('sigma_tdoa = [5e-5, 1e-4]\nsigma_doa_deg = [5, 10]\ntrajectories = [1, 3]\n'
                                    'runs = 2\nmethods = ["hybrid"]\nsigma_odo = 0.03\nbase_seed = 0\n')
    _calibration_json(root / "caljson", feats, truth)
    (root / "scenario.toml").write_text('preset = "lab3"\nseed = 4\nrt60 = 0.2\nsnr = 30.0\nn_events = 4\n'
                                        '[chirp]\nduration = 0.2\n')
    return root


def _calibration_json(folder, feats, truth):
    """A valid calibration.json (the truth as a calibration of ``feats``: the format, not an estimate)."""
    from calib.pipeline.formats.calibration_json import calibration_document

    folder.mkdir()
    square = [[0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.03, 0.0, 0.0], [0.0, -0.03, 0.0]]  # every format needs mics
    feats = {**feats, "meta": {**feats["meta"], "mics": {a: square for a in feats["meta"]["arrays"]}}}
    cal = {"arrays": truth["arrays"], "sources": truth["sources"], "report": {}}
    (folder / "calibration.json").write_text(dumps_json(calibration_document(cal, feats), indent=1))


def export_every_format(folder):
    """What `calib export` does with a calibration.json, for every format (read, convert, write)."""
    cal = load_calibration(folder)
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in FORMATS:
            export(cal, fmt, Path(tmp) / f"x-{fmt}")  # (odas: a folder of <array>.cfg)


def _fuzz_file(valid, folder, name, reader, text):
    """Copy ``folder`` of the valid tree, replace ``name`` with ``text``, call ``reader`` on the copy."""
    with tempfile.TemporaryDirectory() as tmp:
        if folder:
            shutil.copytree(valid / folder, Path(tmp) / folder)
            target = Path(tmp) / folder / name
        else:
            target = Path(tmp) / name
        target.write_bytes(text.encode("utf-8", errors="surrogatepass"))
        only_input_errors(reader, Path(tmp) / folder if folder else target)


READERS = {  # id → (folder of the valid tree, file to mutate, reader)
    "events.csv": ("", "events.csv", read_events),
    "features/meta.json": ("feats", "meta.json", read_features),
    "features/events.csv": ("feats", "events.csv", read_features),
    "features/tdoa_m.csv": ("feats", "tdoa_m.csv", read_features),
    "features/tdoa_s.csv": ("feats", "tdoa_s.csv", read_features),
    "features/doa.csv": ("feats", "doa.csv", read_features),
    "calibration/arrays.csv": ("cal", "arrays.csv", read_calibration),
    "calibration/sources.csv": ("cal", "sources.csv", read_calibration),
    "calibration/report.json": ("cal", "report.json", read_calibration),
    "truth/arrays.csv": ("truth", "arrays.csv", read_truth),
    "truth/sources.csv": ("truth", "sources.csv", read_truth),
    "session.toml": ("rec", "session.toml", read_session),
    "session/events.csv": ("rec", "events.csv", read_session),
    "grid.toml": ("", "grid.toml", read_grid),
    "scenario.toml": ("", "scenario.toml", load_scenario),
    "calibration.json (calib export)": ("caljson", "calibration.json", export_every_format),
}
SOURCES = {"events.csv": ("feats", "events.csv"), "grid.toml": ("", "grid.toml"),
           "scenario.toml": ("", "scenario.toml")}


@pytest.mark.parametrize("which", list(READERS))
def test_reader_raises_only_input_errors(valid, which):
    folder, name, reader = READERS[which]
    src_folder, src_name = SOURCES.get(which, (folder, name))
    text = (valid / src_folder / src_name).read_text()

    @FUZZ
    @given(st.data())
    def check(data):
        _fuzz_file(valid, folder, name, reader, data.draw(mutated(text)))

    check()


@FUZZ
@given(st.binary(max_size=300))
def test_readers_on_random_bytes(data):
    """Arbitrary bytes (not UTF-8, NULs, …) in place of a text file: an InputError naming it."""
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "events.csv"
        p.write_bytes(data)
        only_input_errors(read_events, p)
        p = Path(tmp) / "grid.toml"
        p.write_bytes(data)
        only_input_errors(read_grid, p)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6)
    | st.sampled_from([1e300, -1e300, 343, "343", "A1", "A2", "sigma_tdoa", 10**400, [0, 0, 1], [0, 0, 0]]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6) | st.sampled_from(["A1", "A2"]),
                                                                inner, max_size=3),
    max_leaves=8)


@FUZZ
@given(st.data())
def test_meta_json_typed_values(valid, data):
    """meta.json stays valid JSON but its values are replaced by any JSON value (typed fuzzing reaches the
    validation that text edits rarely get past: 1e300, true, "343", nested lists, huge integers, NaN)."""
    meta = json.loads((valid / "feats" / "meta.json").read_text())
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(sorted(meta) + ["speed_of_sond", "sigma_doa_deg", "doa_mirror_normals", "doa_axes"]))
        if data.draw(st.booleans()) or key not in meta:
            meta[key] = data.draw(JSON_VALUES)
        else:
            meta.pop(key)
    _fuzz_file(valid, "feats", "meta.json", read_features, json.dumps(meta))


TOML_VALUES = ["1e300", "-1e300", "nan", "inf", "-inf", "true", "false", '"343"', '""', "0", "-1", "0.0", "1e-300",
               "9223372036854775807", "[]", "[1, 2]", "[[1, 2, 3]]", "[[true, 0.0, 0.0]]", "[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]",
               '["A1"]', "{ a = 1 }", '"A2.wav"', '"A1.wav"', '"../x.wav"', '"A1"', '"A9"', '"exponential"', "1979-05-27"]


@FUZZ
@given(st.data())
def test_session_toml_typed_values(valid, data):
    """session.toml stays valid TOML but values are replaced by any TOML literal (typed fuzzing)."""
    lines = (valid / "rec" / "session.toml").read_text().splitlines()
    assigns = [k for k, line in enumerate(lines) if " = " in line]
    for _ in range(data.draw(st.integers(1, 3))):
        k = data.draw(st.sampled_from(assigns))
        lines[k] = lines[k].split(" = ")[0] + " = " + data.draw(st.sampled_from(TOML_VALUES))
    _fuzz_file(valid, "rec", "session.toml", read_session, "\n".join(lines) + "\n")


def _draw_path(data, doc):
    """A random path of keys/indices into ``doc``: descend into a random child, stopping at each level with
    probability 1/3 (so a top-level key is as likely as a quaternion's component)."""
    path, node = (), doc
    while isinstance(node, (dict, list)) and node and (not path or data.draw(st.integers(0, 2)) > 0):
        key = data.draw(st.sampled_from(sorted(node) if isinstance(node, dict) else range(len(node))))
        path, node = path + (key,), node[key]
    return path


@FUZZ
@given(st.data())
def test_calibration_json_typed_values(valid, data):
    """calibration.json stays valid JSON but any value anywhere (an array's quaternion, its clock, 'arrays'
    itself, format_version, the covariance, ...) is replaced by any JSON value or removed; `calib export` of
    every format returns or raises InputError."""
    doc = json.loads((valid / "caljson" / "calibration.json").read_text())
    for _ in range(data.draw(st.integers(1, 3))):
        path = _draw_path(data, doc)
        if not path:
            continue
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        if data.draw(st.booleans()):
            parent[path[-1]] = data.draw(JSON_VALUES | st.sampled_from([[0, 0, 0, 0], [1, 0, 0, 0], [0.5, 0.5, 0.5]]))
        elif isinstance(parent, dict):
            parent.pop(path[-1])
    _fuzz_file(valid, "caljson", "calibration.json", export_every_format, json.dumps(doc))


# `calib chirp`'s options: each given or not, from values that are fine, out of range, not numbers, huge
CHIRP_VALUES = {
    "--fs": ["16000", "48000", "1000", "999", "1000001", "1e9", "1000000000", "0", "-1", "nan", "inf", "16000.5",
             "x", ""],
    "--n-events": ["3", "30", "2", "0", "-5", "10000", "10001", "1e3", "x"],
    "--interval": ["2", "0.5", "0", "-1", "nan", "inf", "3600", "3601", "1e-9", "1e300"],
    "--jitter": ["0.25", "0", "0.99", "1", "-0.1", "nan", "2"],
    "--seed": ["0", "7", "-1", "4294967295", "4294967296", "x"],
    "--f0": ["500", "100", "0", "-1", "nan", "inf", "4000", "7999", "8000", "1e300"],
    "--f1": ["4000", "500", "0", "-1", "nan", "inf", "7999", "8000", "24000", "1e300"],
    "--duration": ["0.2", "0.05", "0", "-0.1", "nan", "inf", "1e300", "0.0009", "1", "x"],
    "--fade": ["0.005", "0", "-1", "nan", "0.1", "1e300"],
    "--kind": ["linear", "exponential", "log", ""],
}


@FUZZ
@given(st.data())
def test_chirp_options(tmp_path_factory, data):
    """`calib chirp` with any combination of option values: exit 0 (files written) or exit 2 with an error,
    never an internal error, a traceback or a library warning."""
    from typer.testing import CliRunner

    from calib.cli.main import app

    args = []
    for opt, values in CHIRP_VALUES.items():
        if data.draw(st.booleans()):
            args += [opt, data.draw(st.sampled_from(values))]
    out = tmp_path_factory.mktemp("chirp") / "out"
    r = CliRunner().invoke(app, ["chirp", "-o", str(out), "-q", *args])
    text = r.stdout + r.stderr
    assert r.exit_code in (0, 2), (args, r.exit_code, text)
    assert "Traceback" not in text and "internal error" not in text and "Warning" not in text, (args, text)
    if r.exit_code == 0:
        assert {p.name for p in out.iterdir()} >= {"chirp.wav", "schedule.csv", "chirp.toml"}
    else:
        assert not out.exists(), args  # nothing written, not even the folder
