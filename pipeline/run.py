"""``calib run``: recordings → features → calibration → report, with content-hash stage caching.

Layout of an output folder ``OUT`` (every sub-folder is written atomically, docs/formats.md formats)::

    OUT/features/      features (section 2) + .calib-stage.json     ← stage "features"
    OUT/diagnostics/   detection diagnostics of the frontend         (same stage)
    OUT/calibration/   calibration (section 3) + .calib-stage.json  ← stage "estimate"
    OUT/report/        summary.md, PNG plots, metrics.json + stamp   ← stage "report"

A stage's *key* is the sha256 of (its input files' contents, sorted by name; its settings; the calib
version and a digest of every calib source file: a rule that cannot miss a module a stage runs). The stamp ``.calib-stage.json`` is
written LAST, after the stage's output is atomically in place, and removed before a stage recomputes, so
an interrupted stage never leaves a stamp a later run would trust. A stage is skipped when its stamp holds
the same key and its outputs exist. Stage outputs are inputs of the next stage *by content*: a
hand-edited ``OUT/features/tdoa_m.csv`` changes the estimate's key (re-estimated), not the features' key
(the recordings did not change, so the user's edit is kept).

Library use (a notebook)::

    from calib.pipeline.run import run
    result = run("sample_data/lab3", "calib-out")
    result["calibration"]["arrays"], result["metrics"], result["stages"]
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.util
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

from calib import __version__
from calib.kinds import tables

from calib.pipeline.formats import validate as V
from calib.pipeline.formats.io import InputError, atomic_write_text, dumps_json, read_calibration, read_features, read_truth
from calib.pipeline.formats.outputs import check_replaceable, check_separate, owned_output

STAMP = ".calib-stage.json"
STAGES = ("features", "estimate", "report")
OUT_DIRS = ("features", "diagnostics", "calibration", "report")  # the sub-folders of OUT that run owns
CALIBRATION_FILES = ("arrays.csv", "sources.csv", "report.json")
TRUTH_FILES = ("arrays.csv", "sources.csv")
# files whose absence makes a stamped stage run again (a user deleted part of an output)
REQUIRED = {"features": ("meta.json", "events.csv"), "diagnostics": ("diagnostics.json",),
            "calibration": ("arrays.csv", "report.json", "calibration.json"), "report": ("summary.md",)}


# ----------------------------------------------------------------------------------------------- hashing
def file_sha256(path, chunk=1 << 20):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


CALIB_PACKAGES = ("calib", "calib.frontend", "calib.estimator", "calib.pipeline", "calib.cli")


def source_files():
    """Every calib source file (all ``*.py`` under the packages' folders, sub-packages included), sorted."""
    out = []
    for pkg in CALIB_PACKAGES:
        spec = importlib.util.find_spec(pkg)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            out += Path(folder).rglob("*.py")
    return sorted(out)


def code_digest():
    """sha256 over the source of every calib module (path relative to its package folder, and contents)."""
    h = hashlib.sha256()
    for f in source_files():
        h.update(f"{f.parent.name}/{f.name}".encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def stage_key(inputs, settings):
    """Key of a stage run.

    inputs : dict label → sha256 hex (or None for an absent optional file); labels are relative names
        (``recordings/A1.wav``, ``features/tdoa_m.csv``) so moving folders does not invalidate a stage.
    settings : JSON-able dict of the options that change the stage's output.

    Returns (key hex, the stamp dict without timings).
    """
    stamp = {"inputs": dict(sorted(inputs.items())), "settings": settings,
             "version": __version__, "code": code_digest()}
    key = hashlib.sha256(json.dumps(stamp, sort_keys=True, default=str).encode()).hexdigest()
    return key, {"key": key, **stamp}


def hash_files(root, label, names):
    """{label/name: sha256 or None} for the files ``names`` of folder ``root`` (absent files → None)."""
    root = Path(root)
    return {f"{label}/{n}": file_sha256(root / n) if (root / n).is_file() else None for n in names}


def read_stamp(directory):
    """A stage's stamp, or None when absent or not one calib wrote (a damaged stamp: the stage runs again)."""
    try:
        stamp = json.loads((Path(directory) / STAMP).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    ok = isinstance(stamp, dict) and all(isinstance(stamp.get(k), dict) for k in ("inputs", "settings"))
    return stamp if ok else None


def why_stale(old, new):
    """One line saying why a stage must run (``None`` when the stamp matches)."""
    if old is None:
        return "no previous result"
    if old.get("key") == new["key"]:
        return None
    changed = [k for k in sorted(set(old.get("inputs", {})) | set(new["inputs"]))
               if old.get("inputs", {}).get(k) != new["inputs"].get(k)]
    if changed:
        more = f" (+{len(changed) - 3} more)" if len(changed) > 3 else ""
        return "changed: " + ", ".join(changed[:3]) + more
    if old.get("settings") != new["settings"]:
        diff = [k for k in sorted(set(old.get("settings", {})) | set(new["settings"]))
                if old.get("settings", {}).get(k) != new["settings"].get(k)]
        return "settings changed: " + ", ".join(diff)
    return "software changed"


# ----------------------------------------------------------------------------------------------- inputs
def session_inputs(session):
    """Hashes of the files a recording session's feature extraction reads (session.toml, events, WAVs)."""
    d = Path(session["dir"])
    files = {d / "session.toml", d / "events.csv"} | {Path(f) for a in session["arrays"] for f in a["files"]}
    if session["chirp"].get("reference") is not None:
        files.add(Path(session["chirp"]["reference"]))
    files = sorted(files)
    labels = []
    for f in files:
        try:
            rel = f.resolve().relative_to(d.resolve())
        except ValueError:  # a WAV outside the session folder: name it by its absolute path
            rel = f.resolve()
        labels.append(f"recordings/{rel.as_posix()}")
    # hashlib releases the GIL on large blocks: the WAVs (~30 MB each on a hall session) hash in parallel
    with ThreadPoolExecutor(min(len(files), os.cpu_count() or 1)) as pool:
        return dict(zip(labels, pool.map(file_sha256, files)))


def features_inputs(out):
    return hash_files(Path(out) / "features", "features", feature_files())


def feature_files():
    """The files of features/ the estimate reads: meta.json, events.csv and each kind's CSV (``calib.kinds``)."""
    return ("meta.json", "events.csv", *(f"{t.name}.csv" for t in tables()))


# ----------------------------------------------------------------------------------------------- stages
def features_stage(recordings, out, options, progress=None, jobs=1):
    """Frontend: recordings → OUT/features/ and OUT/diagnostics/ (published together). Returns the diagnostics."""
    from calib.pipeline.features import session_features, write_feature_outputs

    cb = None if progress is None else (lambda done, total, msg: progress("features", done, total, msg))
    feats, diag = session_features(recordings, progress=cb, jobs=jobs, **options)
    write_feature_outputs(Path(out) / "features", Path(out) / "diagnostics", feats, diag, command="calib run")
    return diag


def estimate_stage(out, options, setup=()):
    """Estimator: OUT/features/ → OUT/calibration/ (atomic). Returns the calibration dict.

    setup : the set-up findings (``calib.pipeline.setupcheck.stage_findings``), ranked first in the verdict."""
    from calib.pipeline.formats.io import write_calibration
    from calib.pipeline.setupcheck import apply_findings

    calib, feats = estimate_features(Path(out) / "features", options, veto=functools.partial(session_failure, setup))
    calib = apply_findings(calib, setup)
    write_calibration(Path(out) / "calibration", calib, features=feats)  # + calibration.json
    return calib


def session_failure(setup):
    """Why a clock model is not selected for a session whose set-up failed as a whole (a ``failed`` finding
    that names no array: the odometry, the emission times, the speed of sound or the trajectory contradicted
    by the arrivals), else None. No array's estimate can then be trusted, and the selection's scans would only
    fit clock terms to the mistake, solve after solve (a session with another session's odometry: 4 min of CPU,
    15 min wall at load 6, where the linear clock takes seconds)."""
    failed = [f for f in setup if f["status"] == "failed" and not f.get("array")]
    return f"the set-up of the whole session failed ({failed[0]['what']}: {failed[0]['check']})" if failed else None


def estimate_features(features_dir, options, findings=False, veto=None):
    """Read a features folder and calibrate it (options: ``estimate_defaults()``; loss "linear" = none).
    Returns (calibration, features). ``findings``: with the set-up findings the features show
    (``setupcheck.feature_findings``) in its report and verdict, computed in a second process meanwhile
    (:class:`calib.pipeline.background.Background`); a session they fail as a whole gets no clock-model
    selection (:func:`session_failure`); without them, ``veto`` is the estimator's ``clock_veto``.

    Data that cannot determine the calibration raises InputError naming the features folder.
    """
    from calib.estimator import ObservabilityError, calibrate
    from calib.pipeline.background import Background
    from calib.pipeline.setupcheck import apply_findings, feature_findings

    feats = read_features(features_dir)
    _check_something_to_place(feats, features_dir)
    opts = dict(options)
    loss = opts.pop("loss", "cauchy")
    with Background(feature_findings, feats) if findings else contextlib.nullcontext() as job:
        if findings:   # asked by the clock-model veto once the first solve is done, then applied
            found = functools.cache(job.result)
            veto = functools.partial(_failure_of, found)
        try:
            calib = calibrate(feats, loss=None if loss == "linear" else loss, clock_veto=veto, **opts)
        except ObservabilityError as exc:
            raise InputError(f"{features_dir}: {exc}") from None
        return (apply_findings(calib, found()) if findings else calib), feats


def _failure_of(findings):
    return session_failure(findings())


def _check_something_to_place(feats, where):
    """InputError when no array but the reference has a measurement: there is nothing to calibrate."""
    ref = feats["meta"].get("reference_array")
    measured = {str(a) for t in tables() if "array" in t.columns and feats.get(t.name) is not None
                for a in feats[t.name]["array"]} - {ref}
    if not measured:
        raise InputError(f"{where}: no measurement of any array but the reference {ref}: calib places the other "
                         "arrays relative to it (record with at least two arrays)")


def report_stage(out, truth_dir=None, progress=None):
    """Report: OUT/features + calibration (+ truth, diagnostics) → OUT/report/ (atomic). Returns metrics."""
    from calib.pipeline.report.summary import make_report

    out = Path(out)
    feats = read_features(out / "features")
    calib = read_calibration(out / "calibration")
    truth = read_truth(truth_dir) if truth_dir is not None else None
    diag_dir = out / "diagnostics"
    cb = None if progress is None else (lambda done, total, msg: progress("report", done, total, msg))
    return make_report(out / "report", feats, calib, truth=truth,
                       diagnostics_dir=diag_dir if diag_dir.is_dir() else None, progress=cb)


# ----------------------------------------------------------------------------------------------- driver
def estimate_defaults():
    """{name: default} of the estimator options `calib run` takes (``calib.estimator.options``, flagged ones)."""
    from calib.options import cli_options

    return {o.name: o.default for o in cli_options()}


def _check_options(estimate_options):
    defaults = estimate_defaults()
    opts = {**defaults, **(estimate_options or {})}
    unknown = set(opts) - set(defaults)
    if unknown:
        raise TypeError(f"unknown estimate option(s): {', '.join(sorted(unknown))}")
    return V.estimate_options(opts)


def run(recordings: str | Path, out: str | Path, *, force: bool = False, features_options: dict | None = None,
        estimate_options: dict | None = None, progress: Callable | None = None, log: Callable | None = None,
        on_wait: Callable | None = None, jobs: int = 1) -> dict[str, Any]:
    """Run the pipeline on a recording session, skipping stages whose inputs and settings are unchanged.

    Parameters
    ----------
    recordings : session folder (docs/formats.md section 1); ``recordings/truth`` is used for evaluation if present.
    out : output folder (created); its sub-folders features/, diagnostics/, calibration/, report/ belong
        to this function and are replaced atomically.
    force : recompute every stage.
    features_options : options of ``frontend.extract_features`` (e.g. ``{"threshold": 8.0}``).
    estimate_options : method, use_tdoa_s, emission_sigma, noise ("auto", "meta", "estimate"),
        loss ("cauchy", "huber", "linear"),
        outlier_threshold, array_noise (see ``estimator.calibrate``).
    progress : optional ``progress(stage, done, total, message)`` callback.
    log : optional ``log(stage, status, detail)`` callback, called when a stage starts ("run", reason),
        is skipped ("skipped", reason) or ends ("done", seconds).
    on_wait : optional ``on_wait(message)``, called if another process is writing ``out`` (this run waits).
    jobs : arrays the features stage processes at a time (threads; −1: one per core). Not a setting: the
        results do not depend on it, so changing it does not make a stage stale.

    Output policy (pipeline/formats/outputs.py): ``out`` must not equal, contain or lie inside an input; one run
    at a time per ``out`` (a lock); a sub-folder is replaced only if calib wrote it and no file in it was
    added or edited since (else InputError naming the file, before the stage runs).

    Returns
    -------
    dict: ``out`` (Path), ``stages`` {name: {"status": "run" | "skipped", "reason", "seconds", "output"}},
    ``calibration`` (dict as ``pipeline.formats.io.read_calibration``), ``metrics`` (dict or None, the metrics of
    ``pipeline.report.evaluate.evaluate``), ``report`` (Path of summary.md), ``seconds`` (total).
    """
    from calib.pipeline.formats.session import read_session

    t_start = time.perf_counter()
    out = Path(out)
    est_opts = _check_options(estimate_options)
    feat_opts = V.features_options(features_options or {})
    jobs = V.jobs_option(jobs)
    # validate every input before any work, so bad input fails fast and writes nothing
    session = read_session(recordings)
    if len(session["arrays"]) < 2:
        raise InputError(f"{Path(recordings) / 'session.toml'}: only one array ({session['arrays'][0]['name']}): calib "
                         "places arrays relative to the reference array; record with at least two")
    truth_dir: Path | None = Path(recordings) / "truth" if (Path(recordings) / "truth").is_dir() else None
    if truth_dir is not None:
        read_truth(truth_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    inputs = [Path(recordings), *(f for a in session["arrays"] for f in a["files"]), session["chirp"].get("reference")]
    check_separate([out], inputs)
    subdirs = [out / n for n in OUT_DIRS]
    with owned_output(subdirs, inputs, command="calib run", on_wait=on_wait, lock=out,
                      check=False):
        res = _run_stages(recordings, out, session, truth_dir, force, (feat_opts, jobs), est_opts, progress, log)
    return {**res, "seconds": time.perf_counter() - t_start}


def _run_stages(recordings, out, session, truth_dir, force, feat_run, est_opts, progress, log):
    """The stages of :func:`run` (lock held, inputs validated; ``feat_run`` = (features options, jobs)).
    Returns run's dict without seconds."""
    feat_opts, jobs = feat_run
    log = log or (lambda stage, status, detail: None)
    stages = {}
    metrics = None

    def stage(name, out_dirs, inputs, settings, work):
        key, stamp = stage_key(inputs, settings)
        stamp_dir = out_dirs[0]
        old = read_stamp(stamp_dir)
        reason = "--force" if force else why_stale(old, stamp)
        if reason is None and not all((d / f).is_file() for d in out_dirs for f in REQUIRED.get(d.name, ())):
            reason = "output missing"
        if reason is None:
            log(name, "skipped", "inputs and settings unchanged")
            stages[name] = {"status": "skipped", "reason": "unchanged", "seconds": 0.0,
                            "output": str(stamp_dir)}
            return None
        for d in out_dirs:  # a user's file in the way stops the run before the stage's work
            check_replaceable(d)
        log(name, "run", reason)
        (Path(stamp_dir) / STAMP).unlink(missing_ok=True)  # from here until the new stamp, the output is untrusted
        t0 = time.perf_counter()
        result = work()
        secs = time.perf_counter() - t0
        done = {**stamp, "stage": name, "seconds": secs, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        atomic_write_text(Path(stamp_dir) / STAMP, dumps_json(done, indent=2) + "\n")
        stages[name] = {"status": "run", "reason": reason, "seconds": secs, "output": str(stamp_dir)}
        log(name, "done", secs)
        return result

    from calib.pipeline.setupcheck import explain_failure, stage_findings

    out.mkdir(parents=True, exist_ok=True)
    threshold = feat_opts.get("threshold", 8.0)
    try:
        stage("features", [out / "features", out / "diagnostics"], session_inputs(session), feat_opts,
              lambda: features_stage(recordings, out, feat_opts, progress, jobs))
    except InputError as exc:  # say the set-up mistake that explains it, if one does
        raise explain_failure(session, exc, threshold) from None
    # the set-up consistency stage (seconds): its findings lead the verdict; part of the estimate's settings
    setup = stage_findings(session, out, threshold)
    try:
        stage("estimate", [out / "calibration"], features_inputs(out), {**est_opts, "setup": setup},
              lambda: estimate_stage(out, est_opts, setup))
    except InputError as exc:
        failed = [f["text"] for f in setup if f["status"] == "failed"]
        if not failed:
            raise
        raise InputError(f"{failed[0]}; then: {exc}") from None

    rep_inputs = {**features_inputs(out),
                  **hash_files(out / "calibration", "calibration", CALIBRATION_FILES),
                  **hash_files(out / "diagnostics", "diagnostics", ("diagnostics.json", "detections.png"))}
    if truth_dir is not None:
        rep_inputs.update(hash_files(truth_dir, "truth", TRUTH_FILES))
    metrics = stage("report", [out / "report"], rep_inputs, {"truth": truth_dir is not None},
                    lambda: report_stage(out, truth_dir, progress))
    calib = read_calibration(out / "calibration")
    if metrics is None and truth_dir is not None:  # report skipped: same metrics as `calib evaluate`
        from calib.pipeline.report.evaluate import evaluate

        metrics = evaluate(calib, read_truth(truth_dir))

    return {"out": out, "stages": stages, "calibration": calib,
            "metrics": metrics, "report": out / "report" / "summary.md"}
