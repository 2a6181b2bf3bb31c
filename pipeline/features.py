"""The features stage as files: a recording folder → features/ and diagnostics/ (both atomic)."""
from __future__ import annotations

from collections.abc import Mapping

from calib.frontend import DEFAULTS, extract_features, plot_detections
from calib.errors import InputError
from calib.jsonutil import dumps_json
from calib.records import Features

from calib.pipeline.formats.io import write_features_files
from calib.pipeline.formats.outputs import publish
from calib.pipeline.formats.session import read_session
from calib.pipeline.headerrate import (REFINE_ROUNDS, detections_only, fast_clocks, rate_corrections, refine_rates,
                                      with_rates)
from calib.pipeline.retime import retime_moving


def session_features(recordings, progress=None, jobs=1, **options):
    """Read the session folder ``recordings`` (or take an already read session) and run the frontend.

    progress : optional ``progress(done, total, message)``. jobs : arrays at a time (threads; −1: one per
    core; the results do not depend on it). options : ``calib.frontend.DEFAULTS`` overrides. A source moving
    during the sweep: its arrivals timed again with stretches predicted from a first solve (pipeline/retime.py).
    An array whose WAV header states a rate the chirps' spacing contradicts: extracted again at the measured
    rate (pipeline/headerrate.py; meta.json and diagnostics ``header_rates``).
    Returns (features, diagnostics) as :func:`calib.frontend.extract_features`.
    """
    session = recordings if isinstance(recordings, Mapping) else read_session(recordings)
    opt = {**DEFAULTS, **options}

    done = {}   # rates read → extraction (a fast clock dropped again goes back to the first pass's)

    def extract(fixes):
        key = tuple(sorted((name, f["used"]) for name, f in fixes.items()))
        if key not in done:
            done[key] = extract_features(with_rates(session, fixes), progress=progress, jobs=jobs, **options)
        return done[key]

    try:
        first = extract({})
    except InputError as exc:   # an array with too few chirps to associate: a wrong header's rate, or it stands
        first, fixes = None, _header_fixes_or_raise(session, opt, exc)
    else:
        fixes = rate_corrections(session, first[1], opt["threshold"])
    fast = {} if first is None else fast_clocks(session, first[0], first[1], opt["max_drift"], skip=fixes)
    if fixes:   # a header's rate the chirps contradict: every array again, those at the measured rate
        first = extract(fixes)
    # the rates refined by a first solve's drift, and clocks no crystal gives taken at theirs
    for _ in range(REFINE_ROUNDS if fixes or fast else 0):
        fixes, changed = refine_rates(with_rates(session, fixes), first[0], {**fixes, **fast})
        fast = {}
        if not changed:
            break
        first = extract(fixes)
    session = with_rates(session, fixes)
    feats, diag = retime_moving(session, *first, progress=progress)
    if fixes:
        diag = {**diag, "header_rates": fixes}
    return add_session_meta(feats, session, diag), diag


def _header_fixes_or_raise(session, opt, exc):
    """The header rates the chirps contradict in a session the frontend refused (``exc``), else ``exc``."""
    try:
        fixes = rate_corrections(session, detections_only(session, opt["threshold"]), opt["threshold"])
    except InputError:
        fixes = {}
    if not fixes:
        raise exc
    return fixes


def add_session_meta(feats, session, diag):
    """Extend features/meta.json with what later stages need from the session (docs/formats.md).

    ``mics``: {array: (M, 3) list, array frame, WAV channel order}, so ``calib estimate`` can write the mic
    geometry into calibration.json. ``reference_detections_s``: {event: local time (s) of the reference
    array's matched chirp detections} (the frontend's detection times, same chirp point as its arrivals): the
    anchor of the reference array's absolute clock offset. Returns a new :class:`calib.records.Features`.
    """
    meta = dict(feats["meta"])
    meta["mics"] = {a["name"]: [[float(v) for v in m] for m in a["mics"]] for a in session["arrays"]}
    dets = (diag.get("arrays", {}).get(session["reference_array"]) or {}).get("detections") or []
    meta["reference_detections_s"] = {str(d["event"]): float(d["time"]) for d in dets if d.get("event") is not None}
    if diag.get("header_rates"):   # arrays whose samples were taken at the measured rate (pipeline/headerrate.py)
        meta["header_rates"] = diag["header_rates"]
    # the rates local times count samples at where not the WAV header's (declared in session.toml, or measured)
    rates = {a["name"]: int(a["sample_rate"]) for a in session["arrays"] if a.get("sample_rate") is not None}
    if rates:
        meta["sample_rates"] = rates
        meta["header_sample_rates"] = header_sample_rates(session, diag.get("header_rates") or {})
    return Features.from_dict({**feats, "meta": meta})


def header_sample_rates(session, measured):
    """{array: Hz its WAV header states} of the arrays read at another rate (a ``sample_rate`` declared in
    session.toml, or one ``measured``: ``header_rates``), so that a calibration can be put on the header's time
    base (calibration.json ``header_sample_rate``); an unreadable header is left out (unknown)."""
    from calib.frontend.signals import read_header

    out = {}
    for a in session["arrays"]:
        if a.get("sample_rate") is None:
            continue
        if a["name"] in measured:
            out[a["name"]] = int(measured[a["name"]]["header"])
            continue
        try:
            out[a["name"]] = int(read_header({**a, "sample_rate": None}).samplerate)
        except (InputError, OSError):
            pass
    return out


def write_diagnostics_files(folder, diag):
    """Write ``diagnostics.json`` and ``detections.png`` into the existing (temporary) folder ``folder``."""
    (folder / "diagnostics.json").write_text(dumps_json(diag, drop_private=True, indent=2) + "\n")
    plot_detections(folder / "detections.png", diag)


def write_feature_outputs(features_dir, diagnostics_dir, feats, diag, command="calib features"):
    """Features and diagnostics, published together: both are written, or neither (pipeline/formats/outputs.py)."""
    with publish([features_dir, diagnostics_dir], command=command) as (f_tmp, d_tmp):
        write_features_files(f_tmp, feats)
        write_diagnostics_files(d_tmp, diag)
