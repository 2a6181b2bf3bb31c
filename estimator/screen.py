"""Rows the estimator does not trust, taken out before the solve — rows, never whole arrays.

Two kinds (docs/method.md, "Screened rows"):

* **absurd**: a TDOA no room can produce. Per array, TDOA-M follows its clock line ``offset + drift · t`` up
  to the geometry (|Δd|/c), TDOA-S the emission interval ``(1 + drift) Δt`` up to the range change. A row off
  its array's robust line by more than ``ABSURD_S`` (100 m of path) is a bookkeeping or detection failure
  (one TDOA of −95 s reached the estimator, issue 27); it would otherwise decide the initialisation.
* **nlos**: the frontend's evidence that an arrival is a reflection only (flag ``nlos``: late against the
  array's own range track along the odometry, docs/frontend.md). Such a row is late by metres of path and
  would pull the array that heard it — and through the shared sources every other array.
* **weak_direct** (DOA rows; counted, not taken out): the arrival's direct path is weaker than a reflection
  within a few pulse widths after it (a mount or obstacle attenuates it by 10–20 dB; docs/frontend.md). Its
  time is the direct path's, but its DOA is the direct path's seen through the reflection's leakage: 2–8° off
  on occluded-lab seed 41 (0.2–1° for the arrays in line of sight), several times its own spread, and biased
  alike over an array's events (the array tilts 7–10° at 3.5σ). One such row is left to the outlier tests;
  an array with most of its DOAs such is distrusted as a whole.

Each kind of doubt is judged on its own. An array whose rows are mostly ``nlos`` loses them like any other
while it keeps at least ``MIN_TRUSTED_EVENTS`` events in line of sight (in a U- or L-shaped room every array
hears the direct path in only part of the trajectory: keeping the reflections, each such array refitted alone,
collapsed a U-shaped room to 5.6 m, issue 27); the verdict names it (calibrated from a minority of its events).
With fewer left, or mostly ``weak_direct``, the array keeps those rows: it is reported as distrusted instead,
solved apart, and the verdict names it (:func:`distrusted`).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from calib.tables import has_flag

ABSURD_S = 0.3              # s: 100 m of path, beyond any room's geometry; a row further off its clock line is absurd
MAX_DOUBTED_FRACTION = 0.5  # an array with more of its events doubted for one reason is named by the verdict
# An array keeps its doubted rows (distrusted as a whole instead) when fewer of its events than this would be left:
# its pose and clock are 8 parameters and an event in line of sight gives 3 rows (TDOA-M, the DOA's 2 axes), so 4
# events over-determine it by 4 rows, the fewest that let the outlier tests judge one row
MIN_TRUSTED_EVENTS = 4
# frontend doubts (the ``flag`` column) and the tables where they count; ``nlos`` rows are taken out, while
# ``weak_direct`` ones only count towards an array mostly doubted (kept, named and solved apart): one such DOA
# is a row like any other for the outlier tests (taking them out cost moving seeds 0-1 up to 3 cm: a
# reference array's DOAs), only a bias shared by most of an array's events escapes those tests
DROP_FLAGS = {"nlos": ("tdoa_m", "tdoa_s", "doa"), "weak_direct": ("doa",)}
ARRAY_ONLY = ("weak_direct",)


def _robust_line_residuals(t, y):
    """Residuals of y against a robust line in t (Theil–Sen slope from consecutive pairs, median intercept)."""
    if len(y) < 2:
        return y - np.median(y) if len(y) else y
    order = np.argsort(t)
    dt, dy = np.diff(t[order]), np.diff(y[order])
    ok = dt > 0
    slope = float(np.median(dy[ok] / dt[ok])) if ok.any() else 0.0
    r = y - slope * t
    return r - np.median(r)


def _groups(df):
    """Row indices of each array's rows of table ``df``."""
    codes, uniq = pd.factorize(df["array"])
    return [np.flatnonzero(codes == k) for k in range(len(uniq))]


def absurd_rows(features):
    """{table: (rows,) bool} TDOA rows off their array's clock line by more than ``ABSURD_S``."""
    ev = features["events"]
    t_of = pd.Series(ev["t_emit"].to_numpy(float), index=ev["event"].to_numpy(int))
    out = {}
    tm = features["tdoa_m"]
    bad = np.zeros(len(tm), bool)
    t_m = tm["event"].map(t_of).to_numpy(float)
    for idx in _groups(tm):
        y = tm["tdoa"].to_numpy(float)[idx]
        bad[idx] = ~np.isfinite(y) | (np.abs(_robust_line_residuals(t_m[idx], np.nan_to_num(y))) > ABSURD_S)
    out["tdoa_m"] = bad
    ts = features["tdoa_s"]
    bad = np.zeros(len(ts), bool)
    dt_s = ts["to_event"].map(t_of).to_numpy(float) - ts["from_event"].map(t_of).to_numpy(float)
    for idx in _groups(ts):
        dt = dt_s[idx]
        y = ts["tdoa"].to_numpy(float)[idx]
        yy = np.nan_to_num(y)
        k = float(np.median(yy[dt > 0] / dt[dt > 0])) if np.any(dt > 0) else 1.0   # the array's (1 + drift)
        r = yy - k * dt
        bad[idx] = ~np.isfinite(y) | (np.abs(r - np.median(r)) > ABSURD_S)
    out["tdoa_s"] = bad
    for name, tab in (("tdoa_m", tm), ("tdoa_s", ts)):
        # most of an array's rows off its line: the model (e.g. the emission times) is wrong, not the rows
        for idx in _groups(tab):
            if out[name][idx].sum() > MAX_DOUBTED_FRACTION * len(idx):
                out[name][idx] = ~np.isfinite(tab["tdoa"].to_numpy(float)[idx])
    return out


def _row_events(df):
    """(rows,) lists of the events each row depends on."""
    if "event" in df.columns:
        return [[int(e)] for e in df["event"].to_numpy(int)]
    return [[int(a), int(b)] for a, b in zip(df["from_event"].to_numpy(int), df["to_event"].to_numpy(int))]


def own_doubted_events(features, doubt, array):
    """The events whose arrival at ``array`` itself is in doubt: a TDOA-M row carries the reference's doubts
    too, so those come from its DOA rows (its own arrival), else from its TDOA-S rows (an event whose every
    TDOA-S row is flagged)."""
    d = features["doa"]
    if "doa" in doubt and np.any(m := (d["array"].astype(str) == array).to_numpy()):
        return set(d["event"].to_numpy(int)[m & doubt["doa"]].tolist())
    ts = features["tdoa_s"]
    if "tdoa_s" not in doubt:
        return set()
    m = (ts["array"].astype(str) == array).to_numpy()
    rows = [(evs, f) for evs, f, k in zip(_row_events(ts), doubt["tdoa_s"], m) if k]
    events = {e for evs, _ in rows for e in evs}
    return {e for e in events if all(f for evs, f in rows if e in evs)}


def mostly_doubted(features, doubt):
    """Arrays whose own doubted events (:func:`own_doubted_events`) are more than MAX_DOUBTED_FRACTION of
    the events they have rows for: {array: (number of doubted events, number of events)}."""
    seen = {}
    for name in doubt:
        df = features[name]
        for a, evs in zip(df["array"].astype(str), _row_events(df)):
            seen.setdefault(a, set()).update(evs)
    out = {}
    for a, evs in seen.items():
        n = len(own_doubted_events(features, doubt, a))
        if n > MAX_DOUBTED_FRACTION * len(evs):
            out[a] = (n, len(evs))
    return out


def _doubts(features, names):
    """{reason: ({table: (rows,) bool doubted for it}, {array: its doubted events, kept because they are
    most of its events (:func:`mostly_doubted`) and too few would be left (MIN_TRUSTED_EVENTS; every array
    for an ARRAY_ONLY reason)}, {array: (doubted events, events), taken out although most of its events})}
    for each reason of DROP_FLAGS with a doubted row."""
    out = {}
    for why, tables in DROP_FLAGS.items():
        doubt = {n: has_flag(features[n], (why,)) if n in tables else np.zeros(len(features[n]), bool) for n in names}
        if any(d.any() for d in doubt.values()):
            most = mostly_doubted(features, doubt)
            kept = {a: n for a, (n, m) in most.items() if why in ARRAY_ONLY or m - n < MIN_TRUSTED_EVENTS}
            out[why] = (doubt, kept, {a: nm for a, nm in most.items() if a not in kept})
    return out


def screen_rows(features):
    """Features without the rows not trusted, and the record of what was taken out and why.

    Returns (features copy, record): record = {"rows": [{"type", "array", "events", "reason"[, "line"]}],
    "kept_doubted": {array: its doubted events, kept because they are most of its events}, "kept_reasons":
    {array: [the reasons its rows were kept for]}, "mostly_taken_out": {array: {reason: [doubted events,
    events]}} for the arrays whose doubted rows, most of their events, were taken out all the same}.
    """
    absurd = absurd_rows(features)
    names = [n for n in ("tdoa_m", "tdoa_s", "doa") if len(features[n])]
    doubts = _doubts(features, names)
    out, rows = dict(features), []
    ref = str(features["meta"].get("reference_array"))
    ref_bad = {why: own_doubted_events(features, d, ref) for why, (d, _, _) in doubts.items()}
    for name in names:
        df = features[name]
        arr = df["array"].astype(str).to_numpy()
        bad = absurd.get(name, np.zeros(len(df), bool))
        reason = np.where(bad, "absurd", "").astype(object)
        for why, (doubt, kept, _) in doubts.items():   # the first reason that takes a row out names it
            if why not in ARRAY_ONLY:
                reason[(reason == "") & doubt[name] & ~np.isin(arr, list(kept))] = why
        drop = reason != ""
        for k, evs in zip(np.flatnonzero(drop), [e for e, d in zip(_row_events(df), drop) if d]):
            # the reference's arrival, not its own
            via = name == "tdoa_m" and not bad[k] and evs[0] in ref_bad.get(reason[k], ())
            rows.append({"type": name, "array": str(arr[k]), "events": evs, "reason": str(reason[k]),
                         **({"via_reference": True} if via else {}),
                         **({"line": int(df["csv_line"].iloc[k])} if "csv_line" in df.columns else {})})
        if drop.any():
            out[name] = df[~drop]
    kept, reasons, most = {}, {}, {}
    for why, (_, k, m) in doubts.items():
        for a, n in k.items():
            kept[a] = max(kept.get(a, 0), n)
            reasons.setdefault(a, []).append(why)
        for a, nm in m.items():
            most.setdefault(a, {})[why] = list(nm)
    return out, {"rows": rows, "kept_doubted": kept, "kept_reasons": reasons, "mostly_taken_out": most}


def without_screened(features, record):
    """``features`` without the rows report.json's ``screened`` record (:func:`screen_rows`) took out, matched by
    table, array and events: the rows the estimator solved with, for a calibration read back from disk."""
    out = dict(features)
    for name in ("tdoa_m", "tdoa_s", "doa"):
        gone = {(r["array"], tuple(r["events"])) for r in (record or {}).get("rows", []) if r.get("type") == name}
        df = features.get(name)
        if gone and df is not None and len(df):
            keys = zip(df["array"].astype(str), map(tuple, _row_events(df)))
            out[name] = df[[k not in gone for k in keys]]
    return out


def distrusted(record):
    """Summary for the report: {array: {reason: number of rows}} of the screened rows, plus the arrays whose
    doubted rows were kept (``"<reason>_kept"``: its doubted events)."""
    out = {}
    for r in record["rows"]:
        d = out.setdefault(r["array"], {})
        d[r["reason"]] = d.get(r["reason"], 0) + 1
    for a, n in record["kept_doubted"].items():
        for why in record.get("kept_reasons", {}).get(a, ["nlos"]):
            out.setdefault(a, {})[f"{why}_kept"] = n
    return out


def isolated(record, names):
    """Indices (into ``names``) of the arrays whose doubted rows were kept because they are most of their
    rows (``record["kept_doubted"]``; None: nothing screened): distrusted as a whole, they are solved
    without (``joint.consistency_stage``) and refitted alone, so their rows pull no other array."""
    kept = (record or {}).get("kept_doubted") or {}
    return [k for k, n in enumerate(map(str, names)) if n in kept]
