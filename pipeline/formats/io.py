"""Readers and writers for the directories of ``docs/formats.md`` (features/, calibration/, truth/).

Every reader validates what it reads and raises :class:`InputError` with a one-line message that names
the file, the row (1-based line number in the file, header = line 1) and the problem. Every writer is
atomic: it writes into a temporary sibling directory and renames it into place, so an interrupted or
failed write never leaves a partial directory that a later run could trust.

In-memory representation (pandas DataFrames, sorted, with clean dtypes):

``features``
    a :class:`calib.records.Features` (read like a dict; :func:`validate_features` and the writers also
    take the dict form): ``meta`` (dict), ``events`` (event, t_emit, odom_x, odom_y, odom_z), ``tdoa_m``
    (event, array, tdoa), ``tdoa_s`` (array, from_event, to_event, tdoa), ``doa`` (event, array, ux, uy,
    uz). Extra columns (e.g. ``quality``) are kept.
``calibration``
    ``arrays`` (array, x, y, z, qw, qx, qy, qz, offset, drift, optional ``*_std``), ``sources``
    (event, x, y, z, optional ``*_std``), ``report`` (dict).
``truth``
    ``arrays`` and ``sources`` as in calibration, with NaN where unknown.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from calib import kinds as K
from calib.records import Features
from calib.tables import ARRAYS_COLUMNS, LINE_COLUMN


from calib.errors import InputError  # noqa: F401  (re-exported: readers raise it)
from calib.jsonutil import dumps_json  # noqa: F401

from calib.pipeline.formats import validate as V
from calib.pipeline.formats.outputs import publish, write_replacing


EVENTS_COLS = ["event", "t_emit", "odom_x", "odom_y", "odom_z"]
ARRAYS_COLS = list(ARRAYS_COLUMNS)   # (calib.tables: from the per-array parameters)
SOURCES_COLS = ["event", "x", "y", "z"]
DOA_NORM_TOL = 1e-3


# ----------------------------------------------------------------------------------------------- atomic
@contextlib.contextmanager
def atomic_dir(path, command="calib"):
    """Yield a temporary directory that replaces ``path`` only if the ``with`` block succeeds.

    The output policy applies (pipeline/formats/outputs.py): ``path`` is replaced only if calib owns it (marker
    ``.calib-output``, every file unedited); the published folder gets a marker.
    """
    with publish([path], command=command) as (tmp,):
        yield tmp


def atomic_write_text(path, text):
    """Write ``text`` to ``path`` through a temporary file and a rename.

    For files inside a folder calib is writing (a temporary of :func:`atomic_dir`, a stage's stamp); a file a
    user names goes through ``outputs.write_file`` (the output policy)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_replacing(path, text)


# ----------------------------------------------------------------------------------------------- CSV
# spaces and tabs around a separator (matched only where there are some: no per-cell replacement)
_CELL_SPACE = re.compile(r"[ \t]+(?=[,\n])|(?<=[,\n])[ \t]+")


def read_table(path, columns, *, int_cols=(), str_cols=(), optional_cols=(), bounds=None, max_rows=None):
    """Read a CSV with validation.

    Parameters
    ----------
    path : path of the CSV file (UTF-8; a BOM and CRLF line ends are accepted).
    columns : required columns, in canonical order.
    int_cols, str_cols : columns parsed as integers / kept as strings; all others are floats.
    optional_cols : numeric columns whose empty cells are allowed (become NaN).
    bounds : {column: (lo, hi)} allowed ranges; default: integers in [0, MAX_EVENT_ID], floats within
        ±MAX_ABS_TIME (validate.py).
    max_rows : refuse longer files (memory), default ``validate.MAX_EVENTS * validate.MAX_ARRAYS``.

    Returns a DataFrame with the required columns first, then any extra columns (kept as read).
    Raises :class:`InputError` on a missing file or column, an unparsable, non-finite or out-of-range number.
    """
    path = Path(path)
    text = V.read_text(path)
    # spaces around cells are ignored: removed in one pass over the text (a strip of every cell costs ~1 s per
    # million cells), or cell by cell when quotes may hold separators
    quoted = '"' in text
    if not quoted:
        text = _CELL_SPACE.sub("", text).strip(" \t")
    try:
        raw = pd.read_csv(io.StringIO(text), dtype=str, keep_default_na=False, skipinitialspace=True)
    except Exception as exc:  # pandas raises many kinds on malformed files
        raise InputError(f"{path}: cannot parse CSV ({_first_line(exc)})") from None
    raw.columns = [str(c).strip() for c in raw.columns]
    missing = [c for c in columns if c not in raw.columns]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}")
    if len(set(raw.columns)) != len(raw.columns):
        raise InputError(f"{path}: duplicate column name")
    limit = max_rows if max_rows is not None else V.MAX_EVENTS * V.MAX_ARRAYS
    if len(raw) > limit:
        raise InputError(f"{path}: {len(raw)} rows, more than the {limit} calib handles in one session")
    bounds = bounds or {}
    out = {col: _column(raw[col].str.strip() if quoted else raw[col], col, path, col in str_cols, col in int_cols,
                        col in optional_cols, bounds.get(col)) for col in columns}
    df = pd.DataFrame(out, index=pd.RangeIndex(len(raw)))
    extra = [c for c in raw.columns if c not in columns]
    for c in extra:
        conv = pd.to_numeric(raw[c].replace("", np.nan), errors="coerce")
        df[c] = conv if conv.notna().sum() == (raw[c] != "").sum() else raw[c]
    df[LINE_COLUMN] = np.arange(len(df)) + 2  # line in the file (header = 1), for error and outlier reports
    df.attrs["path"] = str(path)
    return df


_REPR = re.compile(r"^\s*(np|numpy)\.\w+\(.*\)\s*$")


def _column(vals, col, path, is_str, is_int, optional, bound):
    """One validated column (vectorised): strings, or floats / ints within ``bound`` (see read_table)."""
    empty = (vals == "").to_numpy()
    if is_str:
        if empty.any():
            raise InputError(f"{path}: line {np.flatnonzero(empty)[0] + 2}: empty '{col}'")
        return vals.to_numpy(dtype=object).astype(str)
    if empty.any() and not optional:
        raise InputError(f"{path}: line {np.flatnonzero(empty)[0] + 2}: empty '{col}'")
    arr = pd.to_numeric(vals.where(~empty, "nan"), errors="coerce").to_numpy(dtype=float)
    bad = np.isnan(arr) & ~empty
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        v = vals.iloc[k]
        why = "is not finite" if v.lower().lstrip("+-") in ("nan", "inf", "infinity") else "is not a number"
        if _REPR.match(v):  # a script wrote repr(x) of a NumPy scalar: "np.float64(227.98)"
            why += " (a NumPy repr: write float(x) or str(x), not repr(x))"
        raise InputError(f"{path}: line {k + 2}: '{col}' {why}: {v!r}")
    if np.isinf(arr).any():
        k = int(np.flatnonzero(np.isinf(arr))[0])
        raise InputError(f"{path}: line {k + 2}: '{col}' is not finite: {vals.iloc[k]!r}")
    lo, hi = bound if bound is not None else ((0, V.MAX_EVENT_ID) if is_int else (-V.MAX_ABS_TIME, V.MAX_ABS_TIME))
    out = (arr < lo) | (arr > hi)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise InputError(f"{path}: line {k + 2}: '{col}' = {vals.iloc[k]} is outside [{lo:g}, {hi:g}]")
    if is_int:
        frac = arr != np.round(arr)
        if frac.any():
            k = int(np.flatnonzero(frac)[0])
            raise InputError(f"{path}: line {k + 2}: '{col}' is not an integer: {vals.iloc[k]!r}")
        return arr.astype(np.int64)
    return arr


def _first_line(exc):
    msg = str(exc).strip().splitlines()
    return msg[0] if msg else type(exc).__name__


def _check_unique(df, keys, path):
    dup = df.duplicated(subset=list(keys), keep="first").to_numpy()
    if dup.any():
        k = int(np.flatnonzero(dup)[0])
        what = ", ".join(f"{c}={df[c].iloc[k]}" for c in keys)
        raise InputError(f"{path}: line {k + 2}: duplicate row ({what})")


def _check_member(df, col, allowed, path, what):
    allowed = set(allowed)
    bad = ~df[col].isin(allowed).to_numpy()
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        v = df[col].iloc[k]
        v = repr(str(v)) if isinstance(v, str) else v
        raise InputError(f"{path}: line {k + 2}: unknown {what} {v}")


def table_csv(df, columns=None, float_format="%.10g"):
    """A DataFrame's CSV text as calib writes it. ``columns`` fixes the leading column order."""
    # bookkeeping columns (the readers' csv_line, any private "_" column) stay in memory
    df = df[[c for c in df.columns if c != LINE_COLUMN and not str(c).startswith("_")]]
    if columns is not None:
        rest = [c for c in df.columns if c not in columns]
        df = df[[c for c in columns if c in df.columns] + rest]
    return df.to_csv(index=False, float_format=float_format, lineterminator="\n")


def write_table(df, path, columns=None, float_format="%.10g"):
    """Write a DataFrame as CSV (atomic; inside a folder calib is writing). See :func:`table_csv`."""
    atomic_write_text(path, table_csv(df, columns, float_format))


def _read_json(path):
    """A JSON file (BOM and CRLF accepted) → Python value. Raises InputError naming the file."""
    path = Path(path)
    text = V.read_text(path)
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: invalid JSON ({_first_line(exc)})") from None


# ----------------------------------------------------------------------------------------------- events
def read_events(path):
    """Read and validate an ``events.csv`` (docs/formats.md section 1/2). Sorted by event."""
    pos = (-V.MAX_ABS_POSITION, V.MAX_ABS_POSITION)
    ev = read_table(path, EVENTS_COLS, int_cols=("event",), max_rows=V.MAX_EVENTS,
                    bounds={"odom_x": pos, "odom_y": pos, "odom_z": pos})
    if len(ev) == 0:
        raise InputError(f"{path}: no events")
    _check_unique(ev, ["event"], path)
    if (ev["event"] < 0).any():
        k = int(np.flatnonzero(ev["event"].to_numpy() < 0)[0])
        raise InputError(f"{path}: line {k + 2}: negative event id")
    ev = ev.sort_values("event", kind="stable").reset_index(drop=True)
    if np.any(np.diff(ev["t_emit"].to_numpy()) <= 0):
        k = int(np.flatnonzero(np.diff(ev["t_emit"].to_numpy()) <= 0)[0]) + 1
        raise InputError(f"{path}: event {ev['event'].iloc[k]}: t_emit does not increase with event id")
    ev.attrs["path"] = str(path)
    return ev


# ----------------------------------------------------------------------------------------------- features
# every meta.json key calib knows (docs/formats.md); others are warned about with a did-you-mean
META_KEYS = ("speed_of_sound", "reference_array", "arrays", "chirp_drift_bias", "sigmas_estimated",
             "doa_mirror_normals", "doa_axes", "mics", "reference_detections_s", "chirp_stretch_shift",
             "doa_time_s", "stretch_time_s", "tdoa_shared_arrivals", "header_rates", "sample_rates",
             "header_sample_rates", "sigma_arrival_per_array")   # + the kinds' noise keys


def validate_meta(meta, path="meta.json"):
    """Check a features meta dict; returns a cleaned copy (sigmas as floats or absent).

    Typed values only (no numeric strings, no booleans), within the ranges of ``validate.py``; unknown
    keys warn with a did-you-mean.
    """
    if not isinstance(meta, dict):
        raise InputError(f"{path}: must be a JSON object")
    sigma_keys = tuple(K.noise_keys())
    V.check_keys([k for k in meta if not str(k).startswith("_")], (*META_KEYS, *sigma_keys), str(path))
    for key in ("speed_of_sound", "reference_array", "arrays"):
        if key not in meta:
            raise InputError(f"{path}: missing key '{key}'")
    out = dict(meta)
    out["speed_of_sound"] = V.speed_of_sound(meta["speed_of_sound"], f"{path}: 'speed_of_sound'")
    arrays = meta["arrays"]
    if not isinstance(arrays, list) or not arrays or not all(isinstance(a, str) and a for a in arrays):
        raise InputError(f"{path}: 'arrays' must be a non-empty list of names")
    if len(arrays) > V.MAX_ARRAYS:
        raise InputError(f"{path}: {len(arrays)} arrays, more than {V.MAX_ARRAYS}")
    if len(set(arrays)) != len(arrays):
        raise InputError(f"{path}: duplicate array name in 'arrays'")
    if not isinstance(meta["reference_array"], str) or meta["reference_array"] not in arrays:
        raise InputError(f"{path}: reference_array {meta['reference_array']!r} is not in 'arrays'")
    for key in sigma_keys:
        if meta.get(key) is None:
            out.pop(key, None)
            continue
        out[key] = V.sigma(key, meta[key], f"{path}: '{key}'")
    if meta.get("chirp_drift_bias") is not None:
        out["chirp_drift_bias"] = V.number(meta["chirp_drift_bias"], f"{path}: 'chirp_drift_bias'",
                                           lo=-V.MAX_ABS_TIME, hi=V.MAX_ABS_TIME)
    for key in ("doa_time_s", "stretch_time_s"):
        if meta.get(key) is not None:
            out[key] = V.number(meta[key], f"{path}: '{key}'", lo=0.0, hi=V.MAX_ABS_TIME)
    if meta.get("chirp_stretch_shift") is not None:
        out["chirp_stretch_shift"] = _stretch_curve(meta["chirp_stretch_shift"], path)
    if meta.get("tdoa_shared_arrivals") is not None and not isinstance(meta["tdoa_shared_arrivals"], bool):
        raise InputError(f"{path}: 'tdoa_shared_arrivals' must be true or false")
    est = meta.get("sigmas_estimated")
    if est is not None and (not isinstance(est, list) or not all(k in sigma_keys for k in est)):
        raise InputError(f"{path}: 'sigmas_estimated' must be a list of {', '.join(sigma_keys)}")
    for key in ("doa_mirror_normals", "doa_axes"):
        if meta.get(key) is not None:
            out[key] = _array_vectors(meta[key], key, arrays, path)
    both = set(out.get("doa_mirror_normals") or {}) & set(out.get("doa_axes") or {})
    if both:
        raise InputError(f"{path}: array {sorted(both)[0]!r} is in both 'doa_mirror_normals' and 'doa_axes'")
    if meta.get("header_rates") is not None:
        out["header_rates"] = _header_rates(meta["header_rates"], arrays, path)
    if meta.get("sigma_arrival_per_array") is not None:
        own = meta["sigma_arrival_per_array"]
        if not isinstance(own, dict) or not all(k in arrays for k in own):
            raise InputError(f"{path}: 'sigma_arrival_per_array' must map array names to arrival sigmas (s)")
        out["sigma_arrival_per_array"] = {k: V.sigma("sigma_tdoa", v, f"{path}: 'sigma_arrival_per_array' {k!r}")
                                          for k, v in own.items()}
    for key in ("sample_rates", "header_sample_rates"):
        rates = meta.get(key)
        if rates is None:
            continue
        if not isinstance(rates, dict) or not all(k in arrays for k in rates):
            raise InputError(f"{path}: '{key}' must map array names to rates (Hz)")
        out[key] = {k: V.number(v, f"{path}: '{key}' {k!r}", lo=V.SAMPLE_RATE[0], hi=V.SAMPLE_RATE[1], integer=True)
                    for k, v in rates.items()}
    return out


def _header_rates(value, arrays, path):
    """meta ``header_rates`` ({array: {header, used: Hz, scale, ...}}: pipeline/headerrate.py) → a clean copy."""
    if not isinstance(value, dict) or not all(k in arrays and isinstance(v, dict) for k, v in value.items()):
        raise InputError(f"{path}: 'header_rates' must map array names to {{\"header\": Hz, \"used\": Hz, \"scale\": r}}")
    out = {}
    for name, f in value.items():
        where = f"{path}: 'header_rates' {name!r}"
        out[name] = {**f, **{k: V.number(f.get(k), f"{where}: {k!r}", lo=V.SAMPLE_RATE[0], hi=V.SAMPLE_RATE[1],
                                       integer=True) for k in ("header", "used")},
                     "scale": V.number(f.get("scale"), f"{where}: 'scale'", lo=0.01, hi=100.0)}
    return out


def _stretch_curve(value, path):
    """meta ``chirp_stretch_shift`` ({stretch: [...], shift_s: [...]}, stretches increasing, finite) → a clean copy."""
    msg = f"{path}: 'chirp_stretch_shift' must be {{\"stretch\": [...], \"shift_s\": [...]}}: equal lengths ≥ 2, " \
          "finite numbers, stretches increasing"
    if not isinstance(value, dict) or set(value) != {"stretch", "shift_s"}:
        raise InputError(msg)
    try:
        x, y = (np.asarray(value[k], float) for k in ("stretch", "shift_s"))
    except (TypeError, ValueError):
        raise InputError(msg) from None
    if x.ndim != 1 or x.shape != y.shape or len(x) < 2 or not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))) \
            or np.any(np.diff(x) <= 0) or np.any(np.abs(x) > V.MAX_ABS_DRIFT) or np.any(np.abs(y) > V.MAX_ABS_TIME):
        raise InputError(msg)
    return {"stretch": x.tolist(), "shift_s": y.tolist()}


def _array_vectors(value, key, arrays, path):
    """meta ``{array: [x, y, z]}`` (known arrays, non-zero vectors) → {array: unit vector as a list}."""
    if not isinstance(value, dict):
        raise InputError(f"{path}: '{key}' must map array names to [x, y, z]")
    clean = {}
    for name, n in value.items():
        if name not in arrays:
            raise InputError(f"{path}: '{key}' names unknown array {name!r}")
        v = np.asarray(V.vector3(n, f"{path}: '{key}' of {name!r}", nonzero=True))
        clean[name] = (v / np.linalg.norm(v)).tolist()
    return clean


def _not_reference(df, path, meta):
    """TDOA-M of the reference against itself is 0 by definition: dropped."""
    return df[df["array"] != meta["reference_array"]]


def _ordered_events(df, path, meta):
    bad = (df["to_event"] <= df["from_event"]).to_numpy()
    if bad.any():
        raise InputError(f"{path}: line {int(np.flatnonzero(bad)[0]) + 2}: to_event must be after from_event")
    return df


def _unit_vectors(df, path, meta):
    u = df[["ux", "uy", "uz"]].to_numpy(float)
    n = np.linalg.norm(u, axis=1)
    bad = np.abs(n - 1.0) > DOA_NORM_TOL
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InputError(f"{path}: line {k + 2}: DOA is not a unit vector (norm {n[k]:.4g})")
    df = df.copy()
    df[["ux", "uy", "uz"]] = u / n[:, None] if len(n) else u
    return df


def _doa_rows(df, path, meta):
    """doa.csv's checks: unit vectors (renormalised) and the optional per-row ``sigma_deg``."""
    return _row_sigmas(_unit_vectors(df, path, meta), path, "sigma_deg")


def _row_sigmas(df, path, col):
    """The optional per-row sigma column ``col`` (docs/formats.md): each cell empty (NaN in memory) or a
    positive finite number; returned as floats. Absent: ``df`` unchanged."""
    if col not in df.columns:
        return df
    raw = df[col]
    text = raw.astype(str).str.strip()
    vals = pd.to_numeric(text.where(raw.notna() & (text != ""), "nan"), errors="coerce").to_numpy(float)
    given = raw.notna().to_numpy() & (text != "").to_numpy() & (text.str.lower() != "nan").to_numpy()
    bad = given & ~(np.isfinite(vals) & (vals > 0))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InputError(f"{path}: line {k + 2}: {col} must be empty or a positive number (got {text.iloc[k]})")
    df[col] = vals
    return df


# the table-specific checks of the kinds' CSV tables (``calib.kinds``; a kind without one: none)
TABLE_CHECKS = {"tdoa_m": _not_reference, "tdoa_s": _ordered_events, "doa": _doa_rows}


def feature_tables():
    """The measurement tables of features/ (one per kind with a CSV of its own, ``calib.kinds.KINDS``)."""
    return [dataclasses.replace(t, check=TABLE_CHECKS.get(t.name, t.check)) for t in K.tables()]


def measurement_rows(feats):
    """Scalar residual rows per measurement kind of a features dict (a row of a kind of dimension d counts d)."""
    return {t.name: K.KINDS[t.name].dim * len(feats[t.name]) for t in feature_tables()
            if feats.get(t.name) is not None}


def validate_features(feats):
    """Validate an in-memory features dict (as produced by a reader or a simulator). Returns it cleaned."""
    meta = validate_meta(feats["meta"], feats["meta"].get("_path", "meta.json"))
    arrays = meta["arrays"]
    ev = feats["events"]
    events = set(ev["event"].tolist())
    out = {"meta": meta, "events": ev}
    for t in feature_tables():
        df = feats.get(t.name)
        df = t.empty() if df is None else df
        p = df.attrs.get("path", f"{t.name}.csv")
        _check_member(df, "array", arrays, p, "array")
        for col in t.event_cols:
            _check_member(df, col, events, p, "event id")
        _check_unique(df, list(t.keys), p)
        df = t.check(df, p, meta) if t.check else df
        out[t.name] = df.sort_values(list(t.keys), kind="stable").reset_index(drop=True)
    where = Path(feats["meta"].get("_path", "features/meta.json")).parent
    V.check_problem_size(len(ev), len(arrays), measurement_rows(out), where)
    return out


def read_features(directory: str | Path) -> Features:
    """Read and validate a ``features/`` directory (docs/formats.md section 2) → :class:`calib.records.Features`
    (:func:`write_features` writes it back).

    The measurement tables (:func:`feature_tables`: tdoa_m.csv, tdoa_s.csv, doa.csv, ...) are optional (absent = no
    such measurements).
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory")
    meta = _read_json(d / "meta.json")
    meta = validate_meta(meta, d / "meta.json")
    feats = {"meta": meta, "events": read_events(d / "events.csv")}
    for t in feature_tables():
        p = d / f"{t.name}.csv"
        feats[t.name] = read_table(p, list(t.columns), int_cols=t.int_cols, str_cols=t.str_cols) if p.exists() \
            else None
    feats["meta"]["_path"] = str(d / "meta.json")
    out = validate_features(feats)
    out["meta"].pop("_path", None)
    return Features.from_dict(out)


def write_features(directory: str | Path, feats: Mapping[str, Any], command: str = "calib") -> None:
    """Write features (a :class:`calib.records.Features` or the dict form) to ``directory`` atomically
    (validated first, so nothing bad is written); :func:`read_features` reads them back."""
    with atomic_dir(directory, command=command) as tmp:
        write_features_files(tmp, feats)


def write_features_files(folder, feats):
    """Validate a features dict and write its files into the existing (temporary) folder ``folder``."""
    feats = validate_features({**feats, "meta": dict(feats["meta"])})
    meta = {k: v for k, v in feats["meta"].items() if not k.startswith("_")}
    (folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    write_table(feats["events"], folder / "events.csv", EVENTS_COLS, float_format="%.9f")
    for t in feature_tables():
        write_table(feats[t.name], folder / f"{t.name}.csv", list(t.columns), float_format=t.float_format)


# ----------------------------------------------------------------------------------------------- calibration / truth
def _read_arrays(path, *, known=None):
    opt = ARRAYS_COLS[1:]   # "empty cells where unknown" (FORMATS.md): e.g. a diverged solve's positions
    pos = (-V.MAX_ABS_POSITION, V.MAX_ABS_POSITION)
    df = read_table(path, ARRAYS_COLS, str_cols=("array",), optional_cols=opt, max_rows=V.MAX_ARRAYS,
                    bounds={"x": pos, "y": pos, "z": pos})
    _check_unique(df, ["array"], path)
    if known is not None:
        _check_member(df, "array", known, path, "array")
    q = df[["qw", "qx", "qy", "qz"]].to_numpy(float).copy()
    n = np.linalg.norm(q, axis=1)
    have = np.isfinite(n)
    bad = have & (np.abs(n - 1) > DOA_NORM_TOL)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InputError(f"{path}: line {k + 2}: quaternion is not unit norm (norm {n[k]:.4g})")
    q[have] /= n[have, None]
    df[["qw", "qx", "qy", "qz"]] = q
    return df.drop(columns=LINE_COLUMN).reset_index(drop=True)  # calibration/truth rows: no line needed


def _read_sources(path):
    pos = (-V.MAX_ABS_POSITION, V.MAX_ABS_POSITION)   # empty cells where unknown (FORMATS.md)
    df = read_table(path, SOURCES_COLS, int_cols=("event",), optional_cols=("x", "y", "z"),
                    max_rows=V.MAX_EVENTS, bounds={"x": pos, "y": pos, "z": pos})
    _check_unique(df, ["event"], path)
    return df.drop(columns=LINE_COLUMN).sort_values("event", kind="stable").reset_index(drop=True)


def _arrays_and_sources(directory, why_needed=""):
    """(folder, arrays.csv, sources.csv or None) of a calibration or truth folder (unknown values NaN)."""
    d = Path(directory)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory")
    arrays = _read_arrays(d / "arrays.csv")
    if len(arrays) == 0:
        raise InputError(f"{d / 'arrays.csv'}: no arrays (only a header){why_needed}")
    return d, arrays, _read_sources(d / "sources.csv") if (d / "sources.csv").exists() else None


def read_calibration(directory):
    """Read a ``calibration/`` directory (arrays.csv, sources.csv, optional report.json; from an optional
    calibration.json its ``clock.reference_offset``, the reference array's local time at t0 that puts an array
    taken at another rate on its header's time base: ``calib.pipeline.report.evaluate.header_arrays``)."""
    d, arrays, sources = _arrays_and_sources(directory)
    report = _read_json(d / "report.json") if (d / "report.json").exists() else {}
    if not isinstance(report, dict):
        raise InputError(f"{d / 'report.json'}: must be a JSON object")
    out = {"arrays": arrays, "sources": sources, "report": report}
    taken = [e for e in (((report.get("clock") or {}).get("arrays") or {}).values()) if isinstance(e, dict)
             and e.get("header_sample_rate") and e.get("sample_rate") != e.get("header_sample_rate")]
    if taken and (d / "calibration.json").exists():
        doc = _read_json(d / "calibration.json")
        clock = doc.get("clock") if isinstance(doc, dict) else None
        tau = clock.get("reference_offset") if isinstance(clock, dict) else None
        out["reference_offset"] = V.number(tau, f"{d / 'calibration.json'}: clock.reference_offset",
                                           lo=-V.MAX_ABS_TIME, hi=V.MAX_ABS_TIME, allow_none=True)
    return out


def write_calibration(directory, calib, features=None, command="calib"):
    """Write a calibration dict atomically: arrays.csv, sources.csv, report.json (+ calibration.json when the
    ``features`` it was estimated from are given: :mod:`calib.pipeline.formats.calibration_json`)."""
    with atomic_dir(directory, command=command) as tmp:
        write_table(calib["arrays"], tmp / "arrays.csv", ARRAYS_COLS, float_format="%.12g")
        if calib.get("sources") is not None:
            write_table(calib["sources"], tmp / "sources.csv", SOURCES_COLS, float_format="%.9g")
        (tmp / "report.json").write_text(dumps_json(calib.get("report", {}), indent=2) + "\n")
        if features is not None:
            from calib.pipeline.formats.calibration_json import calibration_document  # (imports the estimator: only when asked)

            (tmp / "calibration.json").write_text(dumps_json(calibration_document(calib, features), indent=2) + "\n")


def read_truth(directory: str | Path) -> dict[str, Any]:
    """Read a ``truth/`` directory; unknown values are NaN."""
    d, arrays, sources = _arrays_and_sources(directory, ": nothing to compare with")
    out = {"arrays": arrays, "sources": sources}
    if (d / "clocks.json").exists():   # faulty clocks of a simulation (calib.clock.Clock JSON form per array)
        try:
            out["clocks"] = json.loads((d / "clocks.json").read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{d / 'clocks.json'}: invalid JSON ({exc})") from None
    return out


def write_truth(directory, truth, extra_files=None):
    """Write a truth dict atomically; ``extra_files`` maps file names to text (e.g. a manifest)."""
    with atomic_dir(directory) as tmp:
        write_table(truth["arrays"], tmp / "arrays.csv", ARRAYS_COLS, float_format="%.12g")
        if truth.get("sources") is not None:
            write_table(truth["sources"], tmp / "sources.csv", SOURCES_COLS, float_format="%.12g")
        for name, text in (extra_files or {}).items():
            (tmp / name).write_text(text)


