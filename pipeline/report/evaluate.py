"""Calibration vs ground truth: the metrics of docs/formats.md section 4 (the paper's, Zhang et al. 2025)."""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.clock import header_time_base
from calib.pipeline.formats.io import InputError
from calib.geometry import mirror
from calib.tables import columns

P_PAPER = np.ones(3) / np.sqrt(3.0)


def _rms(v):
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else float("nan")


def array_table(df):
    """The columns of an arrays DataFrame that scoring reads, as plain values: ``names`` (list), ``xyz``
    (n, 3), ``quat`` (n, 4, scalar first), ``offset`` (n,), ``drift`` (n,)."""
    return {"names": df["array"].tolist(), "xyz": columns(df, ("x", "y", "z")),
            "quat": columns(df, ("qw", "qx", "qy", "qz")), "offset": df["offset"].to_numpy(float),
            "drift": df["drift"].to_numpy(float)}


def source_table(df):
    """The columns of a sources DataFrame that scoring reads: ``event`` (K,) and ``xyz`` (K, 3)."""
    return {"event": df["event"].to_numpy(), "xyz": columns(df, ("x", "y", "z"))}


def array_errors(est, truth, reference=None, undetermined=()):
    """Per-array errors of a calibration against truth.

    est, truth : arrays DataFrames (docs/formats.md sections 3/4), or their :func:`array_table`.
    ``reference``: name of the reference array
    (default: the truth row at the origin with identity rotation, else the first row). ``undetermined``:
    report.json's list of what the data left undetermined; those errors are NaN (not scored), and for a
    linear array / mic pair (``roll``, with its ``axis``) the orientation is scored by ``axis_deg``, the
    angle between the estimated and true axis directions, instead of the full rotation.

    Returns a dict of (n,) arrays over the non-reference arrays present in both: ``array``,
    ``position_m``, ``geodesic_deg``, ``paper_deg``, ``axis_deg``, ``offset_s``, ``drift``, ``relative_drift``
    (NaN where truth is unknown or the calibration says undetermined).
    """
    # positional lookups on plain arrays (pandas indexing costs more than the metrics at the paper's size;
    # the Monte-Carlo study scores every run and stage)
    est = est if isinstance(est, dict) else array_table(est)
    truth = truth if isinstance(truth, dict) else array_table(truth)
    e_row = {a: k for k, a in enumerate(est["names"])}
    t_names = truth["names"]
    missing = [a for a in t_names if a not in e_row]
    if missing:
        raise InputError(f"calibration has no array {missing[0]!r} that truth has")
    t_xyz = truth["xyz"]
    if reference is None:
        at_origin = (np.linalg.norm(t_xyz, axis=1) < 1e-12)
        reference = t_names[int(np.argmax(at_origin))] if at_origin.any() else t_names[0]
    it = np.array([k for k, a in enumerate(t_names) if a != reference], int)
    names = [t_names[k] for k in it]
    ie = np.array([e_row[a] for a in names], int)
    pos = np.linalg.norm(est["xyz"][ie] - t_xyz[it], axis=1)
    qe = est["quat"][ie]
    qt = truth["quat"][it]
    geo = np.full(len(names), np.nan)
    paper = np.full(len(names), np.nan)
    ok = np.all(np.isfinite(qt), axis=1)
    if ok.any():
        angle, cosang = rotation_errors(qe[ok], qt[ok])
        geo[ok] = np.rad2deg(angle)
        paper[ok] = np.rad2deg(np.arccos(np.clip(cosang, -1.0, 1.0)))
    e_off, t_off = est["offset"], truth["offset"]
    e_dr, t_dr = est["drift"], truth["drift"]
    off = e_off[ie] - t_off[it]
    dr = e_dr[ie] - t_dr[it]
    t_ref = t_names.index(reference)
    ref_dr = float(e_dr[e_row[reference]]) - float(t_dr[t_ref]) if reference in e_row else np.nan
    out = {"array": names, "position_m": pos, "geodesic_deg": geo, "paper_deg": paper,
           "axis_deg": np.full(len(names), np.nan), "offset_s": off, "drift": dr, "relative_drift": dr - ref_dr}
    _unscored(out, qe, qt, undetermined)
    return out


def rotation_errors(qe, qt):
    """Geodesic angle (rad) between estimated and true rotations (m, 4 scalar-first quaternions each) and the
    cosine between their images of ``P_PAPER``: ``(Rt.inv() * Re).magnitude()`` and ``Σ Rt·p ⊙ Re·p``."""
    Re, Rt = Rotation.from_quat(qe, scalar_first=True), Rotation.from_quat(qt, scalar_first=True)
    return (Rt.inv() * Re).magnitude(), np.sum(Rt.apply(P_PAPER) * Re.apply(P_PAPER), axis=1)


# report.json ``undetermined`` parameter → the error keys it leaves unscored
_UNSCORED = {"position": ("position_m",), "orientation": ("geodesic_deg", "paper_deg"),
             "roll": ("geodesic_deg", "paper_deg"), "offset": ("offset_s",),
             "drift": ("drift", "relative_drift")}


def _unscored(out, qe, qt, undetermined):
    """NaN the errors of undetermined parameters (in place); a linear array's axis error instead of roll."""
    row = {a: k for k, a in enumerate(out["array"])}
    for u in undetermined or ():
        k = row.get(u.get("array"))
        if k is None:
            continue
        for key in _UNSCORED.get(u.get("parameter"), ()):
            out[key][k] = np.nan
        if u.get("parameter") == "roll" and u.get("axis") is not None and np.all(np.isfinite(qt[k])):
            a = np.asarray(u["axis"], float)
            be = Rotation.from_quat(qe[k], scalar_first=True).apply(a)
            bt = Rotation.from_quat(qt[k], scalar_first=True).apply(a)
            out["axis_deg"][k] = np.rad2deg(np.arccos(np.clip(be @ bt / np.linalg.norm(a) ** 2, -1.0, 1.0)))


def _source_differences(se, stt):
    """Estimated − true source positions (m, 3) of the events in both (:func:`source_table`s), in the
    truth's row order (as an inner merge on ``event``; duplicate event numbers are left to pandas' merge)."""
    ev_e = se["event"]
    if len(np.unique(ev_e)) < len(ev_e):
        frame = lambda t: pd.DataFrame({"event": t["event"], **{c: t["xyz"][:, k] for k, c in enumerate("xyz")}})  # noqa: E731
        m = frame(stt).merge(frame(se), on="event", suffixes=("_t", "_e"))
        return m[["x_e", "y_e", "z_e"]].to_numpy(float) - m[["x_t", "y_t", "z_t"]].to_numpy(float)
    row = {v: k for k, v in enumerate(ev_e.tolist())}
    pairs = [(k, row[v]) for k, v in enumerate(stt["event"].tolist()) if v in row]
    it, ie = (np.array(z, int) for z in zip(*pairs)) if pairs else (np.zeros(0, int), np.zeros(0, int))
    return se["xyz"][ie] - stt["xyz"][it]


def truth_tables(truth):
    """A truth dict with its frames as :func:`array_table` / :func:`source_table` (score many estimates
    against one truth without re-reading its DataFrames)."""
    out = {"arrays": array_table(truth["arrays"])}
    if truth.get("sources") is not None:
        out["sources"] = source_table(truth["sources"])
    return out


def rate_scales(calib):
    """{array: r = sample_rate / header_sample_rate} of the arrays whose samples the calibration took at another
    rate than their WAV header's (report.json ``clock.arrays``; files before 30 Nov 2026 lack the header rate:
    none, scored as is)."""
    entries = ((calib.get("report") or {}).get("clock") or {}).get("arrays") or {}
    return {str(n): e["sample_rate"] / e["header_sample_rate"] for n, e in entries.items()
            if e.get("sample_rate") and e.get("header_sample_rate")}


def header_arrays(calib):
    """The calibration's :func:`array_table` on each array's header time base (WAV sample / its header's rate,
    the simulator's truth's): an array taken at a declared or measured rate scored on its total drift and
    offset (:func:`calib.clock.header_time_base`). The offset needs the reference's local time at t0 (calib
    dict ``reference_offset``, calibration.json's): without it, NaN (unscored) where the time bases differ."""
    table = calib["arrays"] if isinstance(calib["arrays"], dict) else array_table(calib["arrays"])
    scales = rate_scales(calib)
    if not scales:
        return table
    r = np.array([scales.get(str(n), 1.0) for n in table["names"]])
    at_origin = (np.linalg.norm(table["xyz"], axis=1) < 1e-12) & (table["offset"] == 0.0)   # the reference
    r_ref = float(r[np.argmax(at_origin)]) if at_origin.any() else 1.0
    tau = calib.get("reference_offset")
    tau = np.where(r == r_ref, 0.0, np.nan if tau is None else float(tau))
    offset, drift = header_time_base(table["offset"], table["drift"], r, r_ref, tau)
    return {**table, "offset": offset, "drift": drift}


def evaluate(calib: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    """Metrics of a calibration dict against a truth dict (both as in ``pipeline.formats.io``).

    The frames may also be given as tables (:func:`array_table`, :func:`source_table`, :func:`truth_tables`).
    Returns a dict: ``position_rmse_m``, ``orientation_geodesic_deg`` (RMS over arrays),
    ``orientation_paper_deg`` (RMS of the angle between R_gt·p and R_est·p, p = [1,1,1]/√3),
    ``axis_rms_deg`` (linear arrays / mic pairs: RMS axis direction error; their full rotation is not
    scored, the roll about the axis being unobservable; undetermined parameters are not scored),
    ``offset_rmse_s``, ``drift_rmse`` (absolute drifts), ``relative_drift_rmse`` (δ_i − δ_ref, the paper's),
    ``source_rmse_m`` (when both have sources) and ``per_array`` (list of dicts). NaN where truth is unknown.
    """
    errs = array_errors(header_arrays(calib), truth["arrays"],
                        undetermined=(calib.get("report") or {}).get("undetermined", ()))
    out = {
        "position_rmse_m": _rms(errs["position_m"]),
        "orientation_geodesic_deg": _rms(errs["geodesic_deg"]),
        "orientation_paper_deg": _rms(errs["paper_deg"]),
        "axis_rms_deg": _rms(errs["axis_deg"]),
        "offset_rmse_s": _rms(errs["offset_s"]),
        "drift_rmse": _rms(errs["drift"]),
        "relative_drift_rmse": _rms(errs["relative_drift"]),
        "source_rmse_m": float("nan"),
    }
    se, stt = calib.get("sources"), truth.get("sources")
    if se is not None and stt is not None and len(stt["event"]):
        se = se if isinstance(se, dict) else source_table(se)
        stt = stt if isinstance(stt, dict) else source_table(stt)
        out["source_rmse_m"] = _rms(np.linalg.norm(_source_differences(se, stt), axis=1))
    out["per_array"] = [
        {"array": a, **{k: float(errs[k][n]) for k in errs if k != "array"}} for n, a in enumerate(errs["array"])
    ]
    if truth.get("clocks"):
        out["clock"] = clock_errors(calib, truth)
    return out


def feature_errors(feats, scenario):
    """Errors of features against a simulated scenario (``pipeline.simulate.roomsim``), per measurement row.

    Returns a dict of arrays: ``tdoa_m_raw`` (s, measured − true arrival difference), ``tdoa_m`` (s, after
    removing the matched-filter drift bias β(δ_i − δ_ref) the estimator models), ``tdoa_s`` (s), ``doa``
    (deg, angle to the true direction in the array frame), ``doa_folded`` (deg, the smaller of the angles
    to the true direction and to its mirror image across the mic plane, for planar arrays) and ``cone``
    (deg, rows of the linear arrays in meta ``doa_axes``: error of the angle to the axis; NaN elsewhere).
    """
    from calib.pipeline.simulate.roomsim import arrival_times  # the room simulator is only needed here

    a = arrival_times(scenario)
    arrays = scenario["arrays"]
    names = [x["name"] for x in arrays]
    ref = names.index(scenario["reference_array"])
    delta = np.array([x["drift"] for x in arrays], float)
    beta = float(feats["meta"].get("chirp_drift_bias", 0.0) or 0.0)
    index = {n: k for k, n in enumerate(names)}

    tm = feats["tdoa_m"]
    i, j = tm["array"].map(index).to_numpy(int), tm["event"].to_numpy(int)
    raw = tm["tdoa"].to_numpy(float) - (a[i, j] - a[ref, j])
    ts = feats["tdoa_s"]
    i2 = ts["array"].map(index).to_numpy(int)
    es = ts["tdoa"].to_numpy(float) - (a[i2, ts["to_event"].to_numpy(int)] - a[i2, ts["from_event"].to_numpy(int)])

    d = feats["doa"]
    i3, j3 = d["array"].map(index).to_numpy(int), d["event"].to_numpy(int)
    src = np.asarray(scenario["sources"], float)
    pos = np.array([x["position"] for x in arrays], float)
    rot = Rotation.from_quat(np.array([x["quat"] for x in arrays], float), scalar_first=True)
    v = src[j3] - pos[i3]
    ut = rot[i3].inv().apply(v / np.linalg.norm(v, axis=1, keepdims=True))
    u = d[["ux", "uy", "uz"]].to_numpy(float)
    ang = np.degrees(np.arccos(np.clip(np.sum(u * ut, axis=1), -1.0, 1.0)))
    folded = ang.copy()
    for k, mics in enumerate(np.asarray(x["mics"], float) for x in arrays):
        _, sv, vt = np.linalg.svd(mics - mics.mean(axis=0))
        rows = i3 == k
        if len(sv) == 3 and sv[1] >= 1e-6 > sv[2] and rows.any():   # planar (not linear: those are cones)
            n = vt[2]
            um = mirror(ut[rows], n)
            alt = np.degrees(np.arccos(np.clip(np.sum(u[rows] * um, axis=1), -1.0, 1.0)))
            folded[rows] = np.minimum(ang[rows], alt)
    axes = np.zeros((len(names), 3))
    for name, ax in (feats["meta"].get("doa_axes") or {}).items():
        axes[index[name]] = np.asarray(ax, float) / np.linalg.norm(ax)
    ax = axes[i3]
    cone = np.degrees(np.abs(np.arccos(np.clip(np.sum(u * ax, axis=1), -1, 1))
                             - np.arccos(np.clip(np.sum(ut * ax, axis=1), -1, 1))))
    return {"tdoa_m_raw": raw, "tdoa_m": raw - beta * (delta[i] - delta[ref]), "tdoa_s": es, "doa": ang,
            "doa_folded": folded, "cone": np.where(np.any(ax != 0, axis=1), cone, np.nan), "dd": delta[i] - delta[ref]}


# ----------------------------------------------------------------------------------------------- clocks
STEP_SIGMAS = 3.0   # a recovered step's size is right when within this many of its own σ of the truth


def clock_errors(calib, truth):
    """A calibration's clock models (its arrays' offsets and drifts, report.json ``clock``) against a simulation's true clocks
    (truth/clocks.json, :func:`calib.pipeline.simulate.clocks.clock_record`), or None without them.

    Per array (every array of the report's clock block or the truth's clocks): its true steps, each with
    ``found`` (a recovered step of the same sign, matched nearest in time, each used once), ``placed`` (in
    the same event interval), ``size_error_s`` and ``size_error_sigma`` (|error| / the step's own σ);
    ``false_steps`` (recovered steps matching none), the true and recovered drift model, the true and
    recovered nominal-rate ratio, and ``local_time_max_error_s`` / ``local_time_rms_error_s``: the recovered
    clock (offset, drift, steps and drift terms, :func:`calib.estimator.clockmodel.as_clock`) minus the true
    one at the session's emission times, relative to the reference's (the frame the data fix). Totals:
    ``steps_true``, ``steps_found``, ``steps_placed``, ``steps_size_ok`` (within STEP_SIGMAS σ),
    ``false_steps``, ``false_drift_models`` (a varying drift recovered for a linear true clock) and the
    largest local-time error.
    """
    records = truth.get("clocks") or {}
    if not records:
        return None
    from calib.clock import Clock

    report = calib.get("report") or {}
    clock = report.get("clock") or {}
    entries = clock.get("arrays") or {}
    t = truth["arrays"]
    names, offset, drift = t["array"].tolist(), t["offset"].to_numpy(float), t["drift"].to_numpy(float)
    rec0 = next(iter(records.values()))
    t0 = float(rec0.get("t0", 0.0))
    # (a clocks.json from before event_times: no interval nor local-time error to score)
    u = np.asarray(rec0.get("event_times") or [], float)
    # (a record's offset is its local time at t0, the truth's arrays.csv offset relative to the reference's: the
    # frame the calibration's offsets are in)
    true = {n: _relative(Clock.from_dict(records[n]), offset[k]) if n in records else Clock(offset[k], drift[k], t0)
            for k, n in enumerate(names)}
    est = _estimated_clocks(calib, t0)
    err = {n: (est[n].local(t0 + u) - true[n].local(t0 + u)) if n in est else np.full(len(u), np.nan) for n in names}
    ref = names[int(np.argmin(np.linalg.norm(columns(t, ("x", "y", "z")), axis=1)))]
    per = []
    for n in names:
        if n not in records and not (entries.get(n) or {}).get("components"):
            continue   # a linear clock recovered as linear: nothing to score beyond the offset and drift
        rel = err[n] - err[ref]
        per.append({"array": n, **_step_scores(records.get(n, {}), (entries.get(n) or {}).get("steps") or [], u),
                    "drift_model_true": _true_drift_model(records.get(n, {})),
                    "drift_model": (entries.get(n) or {}).get("drift_model", "linear"),
                    "rate_ratio_true": float(records.get(n, {}).get("rate_ratio", 1.0)),
                    "rate_ratio": _rate_ratio(entries.get(n) or {}, est.get(n)),
                    "local_time_max_error_s": (float(np.max(np.abs(rel))) if n != ref else 0.0) if len(u) else None,
                    "local_time_rms_error_s": (_rms(rel) if n != ref else 0.0) if len(u) else None})
    steps = [s for a in per for s in a["steps"]]
    return {"steps_true": len(steps), "steps_found": sum(s["found"] for s in steps),
            "steps_placed": sum(bool(s["placed"]) for s in steps),
            "steps_size_ok": sum(bool(s["size_error_sigma"] is not None and s["size_error_sigma"] <= STEP_SIGMAS)
                                 for s in steps),
            "false_steps": sum(a["false_steps"] for a in per),
            "false_drift_models": sum(a["drift_model_true"] == "linear" and a["drift_model"] != "linear" for a in per),
            "local_time_max_error_s": max((a["local_time_max_error_s"] or 0.0 for a in per), default=0.0)
            if len(u) else None,
            "per_array": per}


def _estimated_clocks(calib, t0):
    """{array: its recovered :class:`calib.clock.Clock`}: the calibration's offset and drift, and the steps
    and drift terms of its report's clock models."""
    from calib.estimator.clockmodel import as_clock, models_from_report

    models = models_from_report(calib.get("report"))
    a = calib["arrays"] if isinstance(calib["arrays"], dict) else array_table(calib["arrays"])
    h, scales = header_arrays(calib), rate_scales(calib)
    # on the header's time base (the truth's): steps and terms × r, offset and drift composed (:func:`header_arrays`)
    return {str(n): replace(as_clock(models.get(str(n), []), o, d, t0=t0).scaled(scales.get(str(n), 1.0)), offset=oh)
            for n, o, d, oh in zip(a["names"], a["offset"], a["drift"], h["offset"])}


def _rate_ratio(entry, clock):
    """The recovered nominal-rate ratio: the estimator's wrong-rate finding's, or for an array taken at a
    declared or measured rate its clock's total rate against its header's (None: a crystal's)."""
    if entry.get("sample_rate") and entry.get("header_sample_rate") and clock is not None:
        return 1.0 + float(clock.drift)
    return (entry.get("nominal_rate") or {}).get("ratio")


def _relative(clock, offset):
    """The true clock with the truth's relative ``offset`` (kept where that is unknown)."""
    return replace(clock, offset=float(offset)) if np.isfinite(offset) else clock


def _true_drift_model(record):
    """The true clock's drift model in the report's words: linear, or its terms' kinds."""
    words = {"exp": "warm-up", "table": "random walk", "quadratic": "quadratic", "hinge": "piecewise_linear"}
    kinds = sorted({words.get(e["kind"], e["kind"]) for e in record.get("terms") or ()})
    return "+".join(kinds) if kinds else "linear"


def _step_scores(record, recovered, u):
    """``steps`` (one score per true step) and ``false_steps`` of one array (:func:`clock_errors`)."""
    events = np.arange(len(u))
    left = list(recovered)
    out = []
    for s in sorted(record.get("steps") or (), key=lambda s: s["time"]):
        before, after = u < s["time"], u > s["time"]
        interval = (int(events[before].max()) if before.any() else None,
                    int(events[after].min()) if after.any() else None)
        same = [r for r in left if np.sign(r["size"]) == np.sign(s["size"])]
        r = min(same, key=lambda r: abs(r["time"] - s["time"])) if same else None
        if r is not None:
            left.remove(r)
        e = None if r is None else float(r["size"] - s["size"])
        out.append({"time": float(s["time"]), "size": float(s["size"]), "after_event": interval[0],
                    "before_event": interval[1], "found": r is not None,
                    "placed": (r is not None and (r.get("after_event"), r.get("before_event")) == interval)
                    if len(u) else None,
                    "size_error_s": e,
                    "size_error_sigma": abs(e) / r["std"] if r is not None and r.get("std") else None})
    return {"steps": out, "false_steps": len(left)}
