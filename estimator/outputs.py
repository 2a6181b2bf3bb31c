"""A solution as the tables a user reads: arrays and sources (docs/formats.md section 3), residuals per
measurement type, and the parameters the data leave undetermined."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.records import Record
from calib.tables import ARRAY_PARAMS

from .factors import KINDS, natural
from .problem import Problem, State

AUDIBLE_RANGE = 1000.0   # m: no calibration chirp is recorded farther away (a speaker's sweep is ~60 dB SPL there)
# s: no recording's clock is this far from the emitter's (~115 days; the tables' readers refuse beyond it:
# pipeline/formats/validate.MAX_ABS_TIME)
CLOCK_SPAN = 1e7
DRIFT_SPAN = 0.5   # |drift|: 1 + drift a positive clock rate (the calibration.json reader's bound)


@dataclass(frozen=True, eq=False)
class CalibrationResult(Record):
    """What ``calibrate(features)`` returns (SI units; N arrays, K events). Frozen; reads like the dict of
    earlier versions (``result["arrays"]``, ``.get``, ``{**result}``): a field that is None is not a key.

    arrays : DataFrame, N rows: ``array``, each per-array parameter's columns (``calib.tables.ARRAY_PARAMS``: x,
        y, z m; qw, qx, qy, qz array → reference frame; offset s; drift) and 1-σ ``*_std`` (rx_std, ry_std,
        rz_std: rad about the array's own axes; NaN: not determined). sources : DataFrame, K rows: event, x, y,
        z (m) and their ``*_std``. report : report.json (``verdict`` first; docs/method.md). state, problem :
        the final ``State`` and the ``Problem`` with the final sigmas; stage_states : {"init", "ive"}: the state
        after each stage that ran. converged, cost, outliers, undetermined, unreliable_arrays : with
        ``outputs="solution"`` (no tables, no report), what the report would say. clock_models : {array: clock
        components} (estimator/clockmodel.py); clock : the report's ``clock`` block of a solution.
        array_covariance : (labels, cov) of the free array parameters, the ``*_std`` columns' covariance
        (``assess.labelled_array_covariance``; calibration.json's ``covariance``), None where a position
        was left unknown.
    """
    arrays: pd.DataFrame | None = None
    sources: pd.DataFrame | None = None
    report: dict[str, Any] | None = None
    state: State | None = None
    problem: Problem | None = None
    stage_states: dict[str, State] | None = None
    converged: bool | None = None
    cost: float | None = None
    outliers: list | None = None
    undetermined: list | None = None
    unreliable_arrays: list | None = None
    clock_models: dict | None = None
    clock: dict | None = None
    array_covariance: tuple | None = None


def undetermined_parameters(p):
    """What the data leave undetermined but the estimator can work around, per parameter (report.json
    ``undetermined``): orientations of arrays with DOAs for fewer than 2 events (single microphones, arrays
    without usable DOAs) are not estimated — kept at identity with NaN std — while their positions and
    clocks come from the TDOAs. Returns a list of {"parameter", "array", "reason"}."""
    out = []
    for i in range(p.N):
        if i != p.ref and p.rot_free[i] and p.rot_fixed_axis[i] >= 0:
            out.append({"parameter": "roll", "array": str(p.names[i]), "axis": p.cone_axis[i].tolist(),
                        "reason": "linear array / mic pair: the rotation about its axis is not observable (not "
                                  "estimated, NaN std); the axis direction is"})
        if i != p.ref and not p.rot_free[i]:
            nd = int(p.n_doa_events[i])
            out.append({"parameter": "orientation", "array": str(p.names[i]),
                        "reason": f"DOAs for {nd} event(s) (>= 2 needed): not estimated, reported as identity "
                                  "with NaN std; position and clock from the TDOAs"})
    return out + list(p.unobservable)   # found by the rank check (observability.py)


def residual_table(fs, mask=None):
    """Per measurement type: count, RMS in natural units (µs, deg, cm)."""
    out = {}
    for f in fs:
        if len(f.r) == 0:
            continue
        keep = mask[f.kind] if mask and f.kind in mask else np.ones(len(f.r), bool)
        r = natural(f)[keep]
        if f.dim == 3:
            r = np.linalg.norm(r.reshape(-1, 3), axis=1)
        unit, scale = KINDS[f.kind].unit, KINDS[f.kind].scale
        out[f.kind] = {"n": int(len(r)), f"rms_{unit}": float(np.sqrt(np.mean(r * r)) * scale) if len(r) else 0.0}
    return out


def _quaternions(R):
    """(N, 4) scalar-first unit quaternions of rotation matrices (N, 3, 3), with qw >= 0."""
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q


def to_tables(p: Problem, st: State) -> tuple[dict[str, Any], dict[str, Any]]:
    """State → the plain tables scoring reads (``pipeline.report.evaluate.array_table`` / ``source_table``):
    the values :func:`to_frames` would put in its DataFrames, without building them (the Monte-Carlo study
    scores every run and stage)."""
    arrays = {"names": list(p.names), "xyz": st.x, "quat": _quaternions(st.R), "offset": st.offset,
              "drift": st.drift}
    return arrays, {"event": np.asarray(p.events), "xyz": st.s}


def to_frames(p: Problem, st: State, std: dict[str, np.ndarray] | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """State (+ std) → arrays and sources DataFrames of docs/formats.md section 3."""
    arrays = {"array": list(p.names)}
    for a in ARRAY_PARAMS:
        v = _quaternions(getattr(st, a.state)) if a.rotation else getattr(st, a.key).reshape(p.N, -1)
        arrays.update({c: v[:, k] for k, c in enumerate(a.columns)})
    sources = {"event": np.asarray(p.events), **{c: st.s[:, k] for k, c in enumerate("xyz")}}
    if std is not None:   # the columns collected first: one DataFrame each (a column insert costs ~0.1 ms)
        for a in ARRAY_PARAMS:
            v = std[a.key].reshape(len(std[a.key]), -1)   # (N, dim)
            arrays.update({c: v[:, k] for k, c in enumerate(a.std_columns)})
        sources.update({f"{c}_std": std["s"][:, k] for k, c in enumerate("xyz")})
    return pd.DataFrame(arrays), pd.DataFrame(sources)


def without_claims(std, arrays):
    """``std`` with NaN for the parameters of ``arrays`` (indices; in place): an unreliable array's pose was
    refitted alone from data the rest contradict; the joint covariance holds no row of it (its std came out
    ~1e-8 m), so no uncertainty is claimed (empty, as the reference's)."""
    for i in arrays:
        for a in ARRAY_PARAMS:
            std[a.key][i] = np.nan
    return std


def out_of_earshot(xa, xs):
    """(arrays (N,), sources (K,)) bool: a known position farther than AUDIBLE_RANGE from every known counterpart
    (an array only when some source is known). xa (N, 3), xs (K, 3) m, NaN where unknown."""
    d = np.linalg.norm(xa[:, None, :] - xs[None, :, :], axis=2)          # (N, K); NaN where either is unknown
    near = np.where(np.isnan(d), False, d <= AUDIBLE_RANGE)
    far_a = np.isfinite(xa).all(axis=1) & ~near.any(axis=1) & np.isfinite(xs).all(axis=1).any()
    return far_a, np.isfinite(xs).all(axis=1) & ~near.any(axis=0)


def blank_diverged(out):
    """An array farther than AUDIBLE_RANGE from every source, or a source farther than it from every array, is
    a place no recording can come from: the solve diverged (data that fit no one geometry, e.g. another
    session's events.csv). Their positions become NaN (the tables' "unknown": what a reader takes back, unlike
    the 1e5 m such a solve may reach), their std NaN, and the verdict is ``failed``, naming them. In place on
    ``calibrate``'s output; returns it."""
    arrays, sources = out["arrays"], out["sources"]
    xa, xs = arrays[["x", "y", "z"]].to_numpy(float), sources[["x", "y", "z"]].to_numpy(float)
    far_a, far_s = out_of_earshot(xa, xs)
    ref = out["problem"].ref             # the gauge: placed by definition, not solved; it heard the sources, so
    if far_a[ref]:                       # when it is far from all of them, everything solved ran off together
        far_a, far_s = np.isfinite(xa).all(axis=1), np.isfinite(xs).all(axis=1)
    far_a[ref] = False
    # a clock run off (a refit alone of data no clock explains) is unknown too: not a time any recording has
    off_clock = ~far_a & ((np.abs(arrays["offset"].to_numpy(float)) > CLOCK_SPAN) |
                          (np.abs(arrays["drift"].to_numpy(float)) > DRIFT_SPAN) if "offset" in arrays else False)
    if off_clock.any():
        arrays.loc[off_clock, ["offset", "drift", *(c for c in ("offset_std", "drift_std") if c in arrays)]] = np.nan
        out["array_covariance"] = None
        out["report"]["verdict"]["reasons"].append(
            f"the clock of array(s) {', '.join(str(a) for a in arrays['array'][off_clock])} ran off (offset beyond "
            f"{CLOCK_SPAN:g} s or drift beyond {DRIFT_SPAN:g}): not written (NaN)")
        out["report"]["verdict"]["status"] = "failed"
        out["report"]["verdict"]["flagged_arrays"] = list(dict.fromkeys(
            [*(str(a) for a in arrays["array"][off_clock]), *out["report"]["verdict"].get("flagged_arrays", [])]))
    if not (far_a.any() or far_s.any()):
        return out
    names = [str(a) for a in arrays["array"][far_a]]
    where = np.abs(np.concatenate([xa[far_a], xs[far_s]])).max()
    std_cols = [c for c in arrays.columns if c.endswith("_std")]
    arrays.loc[far_a, ["x", "y", "z", *std_cols]] = np.nan
    out["array_covariance"] = None   # (calibration.json: no covariance of a geometry partly unknown)
    sources.loc[far_s, ["x", "y", "z", *(c for c in sources.columns if c.endswith("_std"))]] = np.nan
    what = "; ".join(filter(None, [
        f"array(s) {', '.join(names)} farther than {AUDIBLE_RANGE:g} m from every source" if names else "",
        f"{int(far_s.sum())} source position(s) farther than {AUDIBLE_RANGE:g} m from every array" if far_s.any() else ""]))
    verdict = out["report"]["verdict"]
    verdict["status"] = "failed"
    verdict["reasons"].insert(0, f"the solve diverged: {what} (up to {where:.3g} m from the "
                                 "origin; no chirp is recorded that far): the measurements fit no one geometry; those positions are "
                                 "not written (NaN). Check that events.csv (t_emit, odometry) and the recordings "
                                 "belong to the same session")
    verdict["flagged_arrays"] = list(dict.fromkeys([*names, *verdict.get("flagged_arrays", [])]))
    return out
